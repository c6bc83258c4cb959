"""Dishes whose beams differ, for the simulators: the truth of the per-antenna beam tests (issue 41).

:class:`PerturbedDishBeam` is a pyuvdata analytic beam (matvis and pyuvsim take it): the
Gaussian dish of :class:`gcrsky.checks.uvsim.DipoleGaussianBeam` (a short dipole's
polarisation) with its own widths along East and North and a pointing offset, i.e. what
real dishes do (a feed displaced or defocused, a dish slightly elliptical), parametrised
physically, not in gcrsky's mode basis (:mod:`gcrsky.instrument.beammodes`), so that
fitting the basis to it is a test of the basis too.  :func:`scattered_beams` draws one per
antenna.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from pyuvdata.analytic_beam import diameter_to_sigma

from .uvsim import DipoleGaussianBeam

__all__ = ["BeamScatter", "PerturbedDishBeam", "scattered_beams"]


@dataclass(kw_only=True, eq=False)
class PerturbedDishBeam(DipoleGaussianBeam):
    """A Gaussian dish with its own widths and pointing (E-field, two feeds).

    The amplitude ``exp(-((x - dx)^2 / (2 sx^2) + (y - dy)^2 / (2 sy^2)))`` of the projected zenith
    angle ``(x, y) = za (cos az, sin az)`` (East, North), ``sx = sigma (1 + width_east)``,
    ``sy = sigma (1 + width_north)``, ``sigma`` the nominal dish's (pyuvdata's
    ``diameter_to_sigma``); ``(dx, dy) = (offset_east_rad, offset_north_rad)``.  All zero:
    exactly :class:`~gcrsky.checks.uvsim.DipoleGaussianBeam`.
    """

    width_east: float = 0.0
    width_north: float = 0.0
    offset_east_rad: float = 0.0
    offset_north_rad: float = 0.0

    def amplitude(self, az_grid, za_grid, f_grid):
        sig = diameter_to_sigma(self.diameter, f_grid)
        x, y = za_grid * np.cos(az_grid), za_grid * np.sin(az_grid)
        sx, sy = sig * (1 + self.width_east), sig * (1 + self.width_north)
        return np.exp(-((x - self.offset_east_rad) ** 2 / (2 * sx**2) + (y - self.offset_north_rad) ** 2 / (2 * sy**2)))


class BeamScatter(NamedTuple):
    """What :func:`scattered_beams` drew: the beams and their parameters, (Nant,) each."""

    beams: list
    width_east: np.ndarray
    width_north: np.ndarray
    offset_east_rad: np.ndarray
    offset_north_rad: np.ndarray


def scattered_beams(nant: int, *, diameter_m: float = 14.0, width_rms: float = 0.03, offset_rms_rad: float = 0.005,
                    seed: int = 0) -> BeamScatter:
    """One :class:`PerturbedDishBeam` per antenna: fractional widths ``N(0, width_rms)`` along each axis,
    pointing offsets ``N(0, offset_rms_rad)`` along each (``width_rms = offset_rms_rad = 0``: all nominal)."""
    rng = np.random.default_rng(seed)
    we, wn = width_rms * rng.standard_normal((2, nant))
    oe, on = offset_rms_rad * rng.standard_normal((2, nant))
    beams = [PerturbedDishBeam(diameter=diameter_m, width_east=float(we[i]), width_north=float(wn[i]),
                               offset_east_rad=float(oe[i]), offset_north_rad=float(on[i])) for i in range(nant)]
    return BeamScatter(beams, we, wn, oe, on)
