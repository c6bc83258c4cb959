"""Simulation: truth skies, the paper's standard case and its configuration.

- ``config``: :class:`Config`, the scalar configuration of a simulated problem (defaults:
  the paper's standard case).
- ``sky``: truth skies: GSM2016 via pygdsm when its data are on disk, else the GSM map
  pyradiosky ships (offline) with a Gaussian small-scale extension.
- ``standard``: :func:`standard_case`, :func:`problem_from_config`, the dish beam of a
  configuration and the response-cache key.

Needs the ``[sim]`` extra (pyradiosky, pygdsm) to make a truth sky; both are
imported only then.
"""

from .config import Config
from .sky import SkyTruth, gsm2016_available, sky_truth
from .standard import beam_for_config, instrument_key, problem_from_config, standard_case

__all__ = [
    "Config",
    "SkyTruth",
    "beam_for_config",
    "gsm2016_available",
    "instrument_key",
    "problem_from_config",
    "sky_truth",
    "standard_case",
]
