"""Reading and writing: run products (``results.h5``, JSON summaries).

- ``results``: :func:`write_results_h5` (draws, Wiener filter and the problem's
  inputs in one HDF5 file), :func:`write_json` (strict JSON).

Visibility files in (UVH5 through pyuvdata) and HEALPix FITS out will live here too.
"""

from .results import clean_json, json_default, write_json, write_results_h5

__all__ = ["clean_json", "json_default", "write_json", "write_results_h5"]
