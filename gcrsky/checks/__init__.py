"""Independent checks of gcrsky: forward-model validation against matvis, calibration of the samplers.

- ``matvis``: gcrsky's visibilities at real observing times against
  ``matvis.simulate_vis`` (the ``[validate]`` extra) for the same sky, array and beams;
- ``uvsim``, ``gainsim``: matvis-simulated visibility files (pyuvdata ``UVData``) and known
  smooth antenna gains applied to them, with their ``UVCal``;
- ``twin``: a twin of a real file (its antennas, cadence and channels; the H1C file in the
  tests): matvis visibilities of a sky that is not the GSM prior mean, smooth gains, a sloped
  bandpass, radiometer noise, ``vis_units`` "uncalib", and the truth;
- ``sbc``: simulation-based calibration of any sampler with exact-size rank tests;
- ``imports``: the package's import graph (layers, floors, circles), parsed with ``ast``.

Submodules are imported on use (``from gcrsky.checks import sbc``).
"""

__all__ = ["gainsim", "imports", "matvis", "sbc", "twin", "uvsim"]
