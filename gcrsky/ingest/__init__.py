"""A visibility file in: the inference :class:`~gcrsky.model.Problem` of what it says.

The layer between the physics (:mod:`gcrsky.model`, :mod:`gcrsky.instrument`) and a run
(:mod:`gcrsky.run`): the file is read by :mod:`gcrsky.io` (no physics), then checked, its band
limit chosen, its beams and prior prepared, and the Problem built.

- ``spec``: :class:`IngestSpec`, the settings (selection, checks, beam, prior, band limit, noise);
- ``uvdata``: :func:`ingest` (the file's Problem, stage by stage) and :func:`from_uvdata` (the
  same with the settings as keywords);
- ``inspect``: :func:`inspect_uvdata` (what a run would use, without solving);
- ``beams``, ``prior``: the beams and the prior as given, resolved;
- ``datachecks``: the data checks in the order a run needs them (calibration record, noise
  excess and outliers, flux scale);
- ``beamprior``: beams as they come (compass products, preparation) and the prior's mean;
- ``gaincal``: the posterior-mean gains of sampled gain draws.
"""

from ..model.observed import DataConfig
from .gaincal import posterior_mean_gains
from .inspect import inspect_uvdata
from .spec import BeamSpec, DataChecks, IngestSpec, PriorSpec, Selection
from .uvdata import from_uvdata, ingest

__all__ = [
    "BeamSpec",
    "DataChecks",
    "DataConfig",
    "IngestSpec",
    "PriorSpec",
    "Selection",
    "from_uvdata",
    "ingest",
    "inspect_uvdata",
    "posterior_mean_gains",
]
