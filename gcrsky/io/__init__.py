"""Reading and writing files: visibility files in, run products (``results.h5``, JSON, HEALPix FITS, pyradiosky skyh5).

- ``results``: ``results.h5`` written batch by batch so that a killed run can be
  continued (:func:`create_results_h5`, :func:`append_batch`,
  :func:`finalize_results_h5`, :func:`read_results_state`, :func:`read_draws`; or
  :func:`write_results_h5` in one go), :func:`write_json` (strict JSON);
- ``fits``: HEALPix RING maps (:func:`write_healpix_fits`, ``healpy.write_map``) and
  complex healpy-ordered alm (:func:`write_alm_fits`, ``healpy.write_alm``), one
  channel per column / HDU;
- ``skymodel``: a pyradiosky ``SkyModel`` of HEALPix maps as ``skyh5``
  (:func:`write_skyh5`; the ``[sim]`` extra);
- ``atomic``: every file is written to a temporary name beside the target and
  renamed over it (:func:`atomic_path`), so a kill never leaves a half-written file.

- ``visdata``: :class:`Observation`, what a visibility file says (NumPy arrays on gcrsky's
  grids; product names :data:`POLS`, :func:`parse_products`);
- ``observation``: a visibility file in: :func:`read_observation` (any file pyuvdata
  reads, selected and read partially, as an :class:`Observation` in gcrsky's conventions:
  what the file says, no physics); ``calibration``: a gain solutions file applied by pyuvdata
  (:func:`read_calibrated_observation`); ``gaincal``: gains written as calfits / calh5.

This is the bottom layer of files: it imports :mod:`gcrsky.base` (and :mod:`gcrsky.sphere`'s mode
layout for the alm FITS files), no physics.  A file turned into a
:class:`~gcrsky.model.Problem` (beams, priors, checks, band limit) is :mod:`gcrsky.ingest`.
"""

from .atomic import atomic_path, atomic_write_text, is_temporary
from .calibration import read_calibrated_observation
from .fits import FRAMES, freq_column_names, write_alm_fits, write_healpix_fits
from .gaincal import write_gain_calibration
from .observation import read_observation, read_uvdata
from .results import (
    ResultsState,
    StoredDraws,
    append_batch,
    clean_json,
    create_results_h5,
    finalize_results_h5,
    inputs_fingerprint,
    json_default,
    read_draws,
    read_results_state,
    settings_json,
    write_json,
    write_results_h5,
)
from .skymodel import healpix_skymodel, write_skyh5
from .visdata import POLS, Observation, parse_products

__all__ = [
    "FRAMES",
    "Observation",
    "POLS",
    "ResultsState",
    "StoredDraws",
    "append_batch",
    "atomic_path",
    "atomic_write_text",
    "clean_json",
    "create_results_h5",
    "finalize_results_h5",
    "freq_column_names",
    "healpix_skymodel",
    "inputs_fingerprint",
    "is_temporary",
    "json_default",
    "parse_products",
    "read_draws",
    "read_calibrated_observation",
    "read_observation",
    "read_results_state",
    "read_uvdata",
    "settings_json",
    "write_alm_fits",
    "write_gain_calibration",
    "write_healpix_fits",
    "write_json",
    "write_results_h5",
    "write_skyh5",
]
