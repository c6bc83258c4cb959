"""A visibility file in: the inference :class:`~gcrsky.model.Problem` of what it says.

The layer between the physics (:mod:`gcrsky.model`, :mod:`gcrsky.instrument`) and a run
(:mod:`gcrsky.run`): the file is read by :mod:`gcrsky.io` (no physics), then checked, its band
limit chosen, its beams and prior prepared, and the Problem built.

- ``uvdata``: :func:`from_uvdata` (the file's Problem) and :func:`inspect_uvdata` (what it
  would use, without solving);
- ``datachecks``: the data checks in the order a run needs them (calibration record, noise
  excess and outliers, flux scale);
- ``beamprior``: beams as they come (compass products, preparation) and the prior's mean;
- ``gaincal``: the posterior-mean gains of sampled gain draws.
"""

from ..model.observed import DataConfig
from .gaincal import posterior_mean_gains
from .uvdata import from_uvdata, inspect_uvdata

__all__ = [
    "DataConfig",
    "from_uvdata",
    "inspect_uvdata",
    "posterior_mean_gains",
]
