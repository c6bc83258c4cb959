"""Reading and writing: run products (``results.h5``, JSON, HEALPix FITS, pyradiosky skyh5).

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

- ``observation``: a visibility file in: :func:`read_observation` (any file pyuvdata
  reads, selected and read partially, as an :class:`~gcrsky.model.Observation` in
  gcrsky's conventions: what the file says, no physics);
- ``uvdata``: real observations in: :func:`from_uvdata` (a
  :class:`~gcrsky.model.Problem` from any file pyuvdata reads: :func:`read_observation`
  then :func:`gcrsky.model.problem_from_observation`, with beam and prior files) and
  :func:`inspect_uvdata` (what it would use, without solving).
"""

from .atomic import atomic_path, atomic_write_text, is_temporary
from .calibration import read_calibrated_observation
from .fits import FRAMES, freq_column_names, write_alm_fits, write_healpix_fits
from .gaincal import posterior_mean_gains, write_gain_calibration
from .observation import read_observation
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
from .uvdata import POLS, DataConfig, from_uvdata, inspect_uvdata, read_uvdata

__all__ = [
    "posterior_mean_gains",
    "write_gain_calibration",
    "FRAMES",
    "POLS",
    "DataConfig",
    "ResultsState",
    "StoredDraws",
    "append_batch",
    "atomic_path",
    "atomic_write_text",
    "clean_json",
    "create_results_h5",
    "finalize_results_h5",
    "freq_column_names",
    "from_uvdata",
    "healpix_skymodel",
    "inputs_fingerprint",
    "inspect_uvdata",
    "is_temporary",
    "json_default",
    "read_draws",
    "read_calibrated_observation",
    "read_observation",
    "read_results_state",
    "read_uvdata",
    "settings_json",
    "write_alm_fits",
    "write_healpix_fits",
    "write_json",
    "write_results_h5",
    "write_skyh5",
]
