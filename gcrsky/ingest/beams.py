"""The beams stage of :func:`gcrsky.ingest.ingest`: the beams as given, one per antenna, prepared for the data.

:func:`resolve_beams` reads what was given (a beam object or file, per antenna by number or
name, or a dish diameter for a Gaussian beam); :func:`prepared_beams` also prepares each
distinct beam (:func:`gcrsky.ingest.beamprior.prepare_beams`: normalisation, frequencies, feed
orientation) and returns a :class:`PreparedBeams`.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..io.visdata import Observation

__all__ = ["PreparedBeams", "beams_by_antenna", "describe_beam", "prepared_beams", "resolve_beams"]


class PreparedBeams(NamedTuple):
    """The beams a Problem is built with.

    Attributes:
        beams: one prepared pyuvdata beam object per antenna (identical antennas share one object).
        note: how they were given (``DataConfig.beam``).
        record: ``DataConfig.checks["beam"]``: the preparation's record.
    """

    beams: list
    note: str
    record: dict


def resolve_beams(beam, dish_diameter_m, obs: Observation) -> tuple[list, str]:
    """``(beams, description)``: one beam object per antenna of ``obs`` (its ``antenna_numbers`` order).

    Args:
        beam: a beam object or file, a dict antenna number / name -> beam, a list in the file's
            ``antenna_numbers`` order, or None (then ``dish_diameter_m``).
        dish_diameter_m: a Gaussian beam with the Airy FWHM of that dish (m), or None.
        obs: the :class:`~gcrsky.io.Observation` (its antennas).
    """
    from ..instrument.beams import gaussian_beam, load_beam

    if beam is None and dish_diameter_m is None:
        raise ValueError("give the beam (a pyuvdata beam object or a beam file) or dish_diameter_m (a Gaussian beam "
                         "with the Airy FWHM of that dish)")
    if beam is not None and dish_diameter_m is not None:
        raise ValueError("give beam or dish_diameter_m, not both")
    if beam is None:
        b = gaussian_beam(float(dish_diameter_m))
        return [b] * obs.n_antennas, f"Gaussian, Airy-matched FWHM of a {float(dish_diameter_m):g} m dish"
    if isinstance(beam, (list, tuple)):
        nums = [int(n) for n in obs.telescope_antenna_numbers]
        if len(beam) != len(nums):
            raise ValueError(f"a beam list needs one beam per antenna of the file's telescope ({len(nums)}), "
                             f"in its antenna_numbers order; got {len(beam)} (or pass a dict number/name -> beam)")
        beam = dict(zip(nums, beam))
    if isinstance(beam, dict):
        return beams_by_antenna(beam, obs)
    b = load_beam(beam)
    return [b] * obs.n_antennas, describe_beam(beam, b)


def beams_by_antenna(beam: dict, obs: Observation) -> tuple[list, str]:
    """``(beams, description)``: per-antenna beams from a dict antenna number or name -> beam (object or file;
    each file read once), in ``obs.antenna_numbers`` order."""
    from ..instrument.beams import load_beam

    names = [str(n) for n in obs.telescope_antenna_names]
    nums = [int(n) for n in obs.telescope_antenna_numbers]
    by_num = {}
    for key, b in beam.items():
        num = int(key) if isinstance(key, (int, np.integer)) else (
            nums[names.index(str(key))] if str(key) in names else None)
        if num is None:
            raise ValueError(f"beam key {key!r} is neither an antenna number nor a name in the file")
        by_num[num] = b
    missing = [int(a) for a in obs.antenna_numbers if int(a) not in by_num]
    if missing:
        raise ValueError(f"no beam given for antennas {missing}")
    cache: dict = {}
    out = []
    for a in obs.antenna_numbers:
        b = by_num[int(a)]
        key = id(b) if not isinstance(b, (str, Path)) else str(b)
        if key not in cache:
            cache[key] = load_beam(b)
        out.append(cache[key])
    return out, f"per antenna ({len(cache)} distinct beams)"


def describe_beam(arg, b) -> str:
    """How the beam was given: ``"file PATH"`` or the beam object's type name."""
    if isinstance(arg, (str, Path)):
        return f"file {arg}"
    return type(b).__name__


def prepared_beams(beam, dish_diameter_m, obs: Observation, **how) -> PreparedBeams:
    """The beams resolved (:func:`resolve_beams`) and prepared for ``obs``
    (:func:`gcrsky.ingest.beamprior.prepare_beams`; ``how``: its normalisation and frequency options)."""
    from .beamprior import prepare_beams

    beams, note = resolve_beams(beam, dish_diameter_m, obs)
    beams, rec = prepare_beams(beams, beam, obs, **how)
    return PreparedBeams(beams, note, rec)
