"""The scalar configuration of a simulated problem; its defaults are the paper's standard case."""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from ..base.units import SPEED_OF_LIGHT
from ..instrument.antennas import HERA_HEIGHT_M, HERA_LATITUDE_DEG, HERA_LONGITUDE_DEG

__all__ = ["Config"]


@dataclasses.dataclass(frozen=True)
class Config:
    """Scalar configuration of a simulated problem (defaults: the paper's standard case).

    Units: frequencies Hz, LSTs sidereal hours, lengths metres, latitude degrees,
    dt seconds, dnu Hz.  ``noise_scale`` multiplies the noise *variance* N,
    ``prior_scale`` the prior variance S (paper cases B2-B8).  The dishes are
    pyuvdata's ``GaussianBeam(diameter=dish_diameter)`` (FWHM ~ lambda/D, 12.28 deg
    at 100 MHz for 14 m) unless ``beam_fwhm_deg`` is set: then a Gaussian power beam
    of exactly that FWHM at the first frequency, scaling as 1/frequency (the paper's
    D1 quotes FWHM = lambda/D = 57.3 deg for 3 m dishes, which the Airy-matched
    ``GaussianBeam(diameter=3)``, 63.4 deg, does not reproduce).  ``obs_date`` None
    is the paper's idealised mode (sky coefficients in the co-rotating frame);
    a date (e.g. ``"2026-03-21"``) observes at the real UTC times of that date
    whose local Earth rotation angles are the LSTs, with the sky in ICRS
    (DESIGN section 2, mode b; the site is longitude/latitude/height).
    """

    lmax: int = 20
    nside: int = 128
    freqs_hz: tuple = (100e6, 102e6)
    n_lst: int = 10
    lst_range_hours: tuple = (0.0, 8.0)
    dish_diameter: float = 14.0
    beam_fwhm_deg: Optional[float] = None
    antenna_spacing: float = 14.6
    rows: tuple = (3, 4, 3)
    latitude_deg: float = HERA_LATITUDE_DEG
    longitude_deg: float = HERA_LONGITUDE_DEG
    height_m: float = HERA_HEIGHT_M
    obs_date: Optional[str] = None
    dt_s: float = 60.0
    dnu_hz: float = 1e6
    noise_scale: float = 1.0
    prior_scale: float = 1.0
    prior_frac: float = 0.1
    prior_floor_std: float = 0.5
    flat_prior: bool = False
    zero_prior_mean: bool = False
    seed: int = 0
    sky_source: str = "auto"
    extend_seed: int = 2024

    def validate(self) -> "Config":
        if int(self.lmax) != self.lmax or self.lmax < 1:
            raise ValueError(f"lmax must be an integer >= 1, got {self.lmax}")
        if self.n_lst < 1:
            raise ValueError(f"n_lst must be >= 1, got {self.n_lst}")
        if len(self.lst_range_hours) != 2:
            raise ValueError("lst_range_hours must be (start, stop) in hours")
        if self.beam_fwhm_deg is not None and not 0 < self.beam_fwhm_deg < 180:
            raise ValueError(f"beam_fwhm_deg must be in (0, 180), got {self.beam_fwhm_deg}")
        for name in ("dish_diameter", "antenna_spacing", "dt_s", "dnu_hz", "noise_scale", "prior_scale", "prior_frac"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.obs_date is not None:
            from astropy.time import Time

            try:
                Time(self.obs_date, scale="utc")
            except ValueError as e:
                raise ValueError(f"obs_date {self.obs_date!r} is not a date astropy understands: {e}") from None
        if 3 * self.nside - 1 < self.lmax:
            raise ValueError(f"nside={self.nside} cannot resolve lmax={self.lmax} (need 3*nside-1 >= lmax)")
        if not 1e-150 < self.noise_scale < 1e150:  # its inverse square must be a normal float64
            raise ValueError(f"noise_scale {self.noise_scale:g} is outside (1e-150, 1e150): the inverse noise "
                             "variance would overflow or vanish in float64")
        if not 0 <= int(self.seed) < 2**63:
            raise ValueError(f"seed must be in [0, 2**63), got {self.seed}")
        self._check_beam_resolution()
        return self

    def _check_beam_resolution(self) -> None:
        """The beam is narrower than the sky and no narrower than a pixel of the quadrature grid (a simulation's
        data come from the same grid, so only a beam that falls between its pixels is refused)."""
        import healpy as hp

        freqs = np.asarray(self.freqs_hz, np.float64)
        if self.beam_fwhm_deg is not None:  # exactly this FWHM at the first frequency, as 1 / frequency
            widest, narrowest = (np.radians(self.beam_fwhm_deg) * freqs[0] / f for f in (freqs.min(), freqs.max()))
        else:  # pyuvdata's GaussianBeam(diameter=D): FWHM ~ lambda / D
            widest, narrowest = (SPEED_OF_LIGHT / f / self.dish_diameter for f in (freqs.min(), freqs.max()))
            if widest >= np.pi:
                raise ValueError(
                    f"dish_diameter {self.dish_diameter:g} m gives a beam FWHM (lambda / D) of "
                    f"{np.degrees(widest):.3g} deg at {freqs.min() / 1e6:g} MHz: wider than the sky; the dish "
                    f"must be wider than lambda / pi = {SPEED_OF_LIGHT / freqs.min() / np.pi:.3g} m")
        pixel = hp.nside2resol(int(self.nside))
        if narrowest < pixel:
            fit = 1 << int(np.ceil(np.log2(hp.nside2resol(1) / narrowest)))
            raise ValueError(
                f"the beam's FWHM, {np.degrees(narrowest):.3g} deg at {freqs.max() / 1e6:g} MHz, is narrower than "
                f"a pixel of the nside {self.nside} grid ({np.degrees(pixel):.3g} deg): the quadrature cannot "
                f"resolve it; use nside >= {fit} or a wider beam (a smaller dish)")

    @property
    def lsts_hours(self) -> np.ndarray:
        """The observation LSTs: ``linspace(start, stop, n_lst)`` (endpoints included)."""
        return np.linspace(self.lst_range_hours[0], self.lst_range_hours[1], self.n_lst)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(self).items()}
