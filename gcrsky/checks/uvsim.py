"""Visibility files to test the ingest with: matvis simulations written by pyuvdata.

:func:`simulate_uvdata` simulates a band-limited ICRS sky (realified coefficients at
some ``lmax``) with matvis (``polarized=True``: every feed product of every antenna pair,
autocorrelations included, with each antenna's own beam) at real observing times, adds
radiometer noise from the simulated autocorrelations, and returns a pyuvdata ``UVData``
in pyuvdata's conventions (``V_ij = <V_i^* V_j>``, ``uvw = x_j - x_i``, drift-scan
"unprojected" phase centre, ``vis_units`` ``"Jy"`` or ``"K str"``, ``pol_convention``
``"sum"``: a feed sees half of Stokes I, as matvis, pyuvsim and hera_sim write) plus
the noiseless visibilities.  The tests then store it in every variant the ingest must
read (conjugations, projected phase centres, flags, nsamples, missing baselines, unit
and convention changes) with pyuvdata's own methods.

matvis is an independent simulator: one point source per HEALPix pixel of the ICRS
map (nside ``nside_matvis``), astropy's ICRS -> AltAz per time, pyuvdata's beam
interpolation; gcrsky's response is a quadrature in the co-rotating frame at one
reference angle.  Their agreement is the validation table of
:mod:`gcrsky.checks.matvis` (~1e-4 to 1e-2 of the rms, by beam and nside).  As there,
the pixel fluxes carry the annual-aberration solid-angle factor so that both codes see
the same brightness.

Noise (per component, per product ``pq`` of pair ``(i, j)``):
``sigma^2 = |V_ii,pp V_jj,qq| / (2 dt dnu N)`` with ``N`` the nsample (1 here), the
autocorrelations the simulated (noiseless) ones; autocorrelations themselves get no
noise.  Use short integrations and narrow channels to make the noise dominate the
simulators' disagreement when a test needs that.

matvis is imported lazily (the ``[validate]`` extra).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from pyuvdata.analytic_beam import AnalyticBeam, diameter_to_sigma

from ..base.extras import require
from ..base.units import kelvin_sr_to_jy
from ..sphere.frames import time_array
from ..sphere.maps import alm_to_map
from .matvis import aberration_solid_angle_factor

__all__ = ["DipoleGaussianBeam", "SimulatedUVData", "simulate_uvdata"]

#: The feed products the simulation writes: (feed index on antenna i, feed index on antenna j) of
#: the pair (i, j), pyuvdata's order (``"xy"``: x on ant_1, y on ant_2).  matvis' polarised
#: ``vis[..., a, b]`` has feed ``b`` on the first antenna and ``a`` on the second (pinned in
#: ``tests/test_polarized_response.py``), so product ``(p, q)`` is ``vis[..., q, p]``.
PRODUCTS = {"xx": (0, 0), "yy": (1, 1), "xy": (0, 1), "yx": (1, 0)}


@dataclass(kw_only=True, eq=False)
class DipoleGaussianBeam(AnalyticBeam):
    """A Gaussian dish (pyuvdata ``GaussianBeam(diameter)``'s power) with a short dipole's polarisation.

    A physical E-field (x East, y North): smooth through zenith, unlike pyuvdata's unpolarised
    ``sqrt(P/2)`` on both (azimuth, zenith angle) unit vectors, whose cross kernel with a real
    E-field beam changes sign across zenith (``tests/test_polarized_response.py``).  The partner
    of a real E-field beam in per-antenna tests.
    """

    diameter: float = 14.0
    basis_vector_type = "az_za"

    def validate(self):
        self.feed_array = np.asarray(["x", "y"] if self.feed_array is None else self.feed_array)

    def amplitude(self, az_grid, za_grid, f_grid):
        """The dish's field amplitude (a subclass changes it, the polarisation stays the dipole's)."""
        return np.exp(-(za_grid**2) / (2 * diameter_to_sigma(self.diameter, f_grid) ** 2))

    def _efield_eval(self, *, az_grid, za_grid, f_grid):
        data = self._get_empty_data_array(az_grid.shape)
        amp = self.amplitude(az_grid, za_grid, f_grid)
        # (azimuth, zenith-angle) components of each feed; pyuvdata may ask for one feed only
        fields = {"x": (-np.sin(az_grid), np.cos(za_grid) * np.cos(az_grid)),
                  "y": (np.cos(az_grid), np.cos(za_grid) * np.sin(az_grid))}
        for k, feed in enumerate(self.feed_array):
            data[0, k], data[1, k] = fields[str(feed)][0] * amp, fields[str(feed)][1] * amp
        return data


class SimulatedUVData(NamedTuple):
    """What :func:`simulate_uvdata` returns.

    Attributes:
        uvdata: the pyuvdata ``UVData`` (noisy data, flags False, nsamples 1).
        model: (Nblts, Nfreqs, Npols) complex, the noiseless visibilities in the file's
            layout and units.
        sigma: (Nblts, Nfreqs, Npols) per-component noise std of ``uvdata``'s data (0 for
            autocorrelations).
    """

    uvdata: object
    model: np.ndarray
    sigma: np.ndarray


def _ecef_relative(positions_enu_m, location):
    from pyuvdata import utils

    enu = np.asarray(positions_enu_m, np.float64)
    xyz = utils.ECEF_from_ENU(enu, center_loc=location)
    x0 = np.array([location.x.to_value("m"), location.y.to_value("m"), location.z.to_value("m")])
    return xyz - x0[None, :]


def simulate_uvdata(
    positions_enu_m,
    location,
    times,
    freqs_hz,
    beams,
    a_icrs,
    lmax: int,
    *,
    beam_idx=None,
    nside_matvis: int = 64,
    pols=("xx", "yy"),
    vis_units: str = "Jy",
    pol_convention: str = "sum",
    dt_s: float = 10.0,
    dnu_hz: float = 1e5,
    noise_seed: int | None = 0,
    antenna_numbers=None,
) -> SimulatedUVData:
    """matvis visibilities of an ICRS sky at real times, as a pyuvdata ``UVData``.

    Args:
        positions_enu_m: (Nant, 3) ENU antenna positions, metres, about ``location``.
        location: astropy ``EarthLocation`` of the array.
        times: astropy ``Time`` (Nt,), UTC.
        freqs_hz: (Nf,) frequencies, Hz (inside every beam's frequency range).
        beams: one pyuvdata beam (E-field beams give every feed product; a power beam
            only its own), or a list of them with ``beam_idx`` (Nant,) the beam of each
            antenna.
        a_icrs: (n,) or (Nf, n) realified ICRS coefficients at ``lmax``, K.
        lmax: their degree.
        nside_matvis: HEALPix nside of the pixel sky matvis sums.
        pols: feed products to write (``"xx"``, ``"yy"``, ``"xy"``, ``"yx"``).
        vis_units: ``"Jy"`` or ``"K str"`` (Rayleigh-Jeans, ``kelvin_sr_to_jy``).
        pol_convention: ``"sum"`` (matvis' own: a feed sees I/2) or ``"avg"`` (products
            doubled: I-equivalent).
        dt_s, dnu_hz: integration time and channel width of the radiometer noise.
        noise_seed: seed of the noise; None: noiseless data.
        antenna_numbers: (Nant,) antenna numbers written to the file (default 0..Nant-1).

    Returns:
        :class:`SimulatedUVData`.
    """
    matvis = require("matvis", "validate", "simulated visibility files")
    if vis_units not in ("Jy", "K str"):
        raise ValueError(f"vis_units must be 'Jy' or 'K str', got {vis_units!r}")
    if pol_convention not in ("sum", "avg"):
        raise ValueError(f"pol_convention must be 'sum' or 'avg', got {pol_convention!r}")
    bad = [p for p in pols if p not in PRODUCTS]
    if bad:
        raise ValueError(f"unknown feed products {bad}; known: {sorted(PRODUCTS)}")
    pos = np.asarray(positions_enu_m, np.float64)
    nant = pos.shape[0]
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    times = time_array(times)
    beams = list(beams) if isinstance(beams, (list, tuple)) else [beams]
    beam_idx = np.zeros(nant, np.int64) if beam_idx is None else np.asarray(beam_idx, np.int64)
    pairs = np.array([(i, j) for i in range(nant) for j in range(i, nant)], np.int64)
    vis = _matvis_visibilities(matvis, pos, location, times, freqs, beams, beam_idx, a_icrs, lmax, nside_matvis,
                               pairs)
    if pol_convention == "avg":
        vis = 2.0 * vis
    if vis_units == "K str":
        vis = vis / kelvin_sr_to_jy(freqs)[:, None, None, None, None]
    model, sigma, data = _with_noise(vis, pairs, pols, dt_s, dnu_hz, noise_seed)

    # to pyuvdata's layout: blts time-major (all pairs at time 0, then time 1, ...)
    def blt(x):
        return np.transpose(x, (1, 2, 0, 3)).reshape(len(times) * pairs.shape[0], freqs.size, len(pols))

    numbers = np.arange(nant) if antenna_numbers is None else np.asarray(antenna_numbers, np.int64)
    uvd = uvdata_of(pos, location, numbers, pairs, times, freqs, pols, blt(data), vis_units, pol_convention, dt_s,
                  dnu_hz, f"gcrsky.checks.uvsim: matvis {getattr(matvis, '__version__', '?')} polarized simulation, "
                  f"ICRS sky at lmax {lmax}, nside {nside_matvis}, radiometer noise dt={dt_s} s dnu={dnu_hz} Hz")
    return SimulatedUVData(uvd, blt(model), blt(sigma))


def _matvis_visibilities(matvis, pos, location, times, freqs, beams, beam_idx, a_icrs, lmax, nside_matvis, pairs):
    """matvis' polarised visibilities of the ICRS sky ``a_icrs``: (Nf, Nt, Npairs, 2, 2) complex, Jy, "sum".

    The pixel sky (nside ``nside_matvis``) is brightness-matched for annual aberration
    (:mod:`gcrsky.checks.matvis`); matvis takes ``sqrt(I)``, so the positive and negative
    parts of the map are simulated apart.
    """
    import healpy as hp

    a = np.broadcast_to(np.asarray(a_icrs, np.float64), (freqs.size, (lmax + 1) ** 2))
    npix = hp.nside2npix(nside_matvis)
    theta, phi = hp.pix2ang(nside_matvis, np.arange(npix))
    jac = aberration_solid_angle_factor(nside_matvis, times.min() + (times.max() - times.min()) / 2)
    maps = np.stack([alm_to_map(a[f], lmax, nside_matvis) for f in range(freqs.size)], axis=1) * jac[:, None]
    jy = kelvin_sr_to_jy(freqs)[None, :] * (4 * np.pi / npix)
    ants = {i: pos[i] for i in range(pos.shape[0])}
    vis = 0.0
    for sign in (1.0, -1.0):
        part = np.clip(sign * maps, 0.0, None)
        keep = np.any(part > 0, axis=1)
        if not np.any(keep):
            continue
        v = matvis.simulate_vis(
            ants=ants, fluxes=part[keep] * jy, ra=phi[keep], dec=np.pi / 2 - theta[keep], freqs=freqs,
            times=times, beams=beams, beam_idx=beam_idx, telescope_loc=location, polarized=True, precision=2,
            antpairs=pairs,
        )
        vis = vis + sign * np.asarray(v)  # (Nf, Nt, Nbl, 2, 2), Jy, sum convention
    return np.asarray(vis)


def _with_noise(vis, pairs, pols, dt_s, dnu_hz, noise_seed):
    """``(model, sigma, data)`` (Nf, Nt, Npairs, Npols): the products, their radiometer sigma, noisy data.

    The radiometer equation on the (noiseless) autocorrelations of each feed,
    ``sigma^2 = |V_ii,pp V_jj,qq| / (2 dt dnu)``, written out here rather than taken from
    :mod:`gcrsky.model.noise`: the files test that implementation.  Autocorrelations get
    no noise.
    """
    nant = int(pairs.max()) + 1
    auto_row = {i: int(np.flatnonzero((pairs[:, 0] == i) & (pairs[:, 1] == i))[0]) for i in range(nant)}
    ai = np.array([auto_row[i] for i in pairs[:, 0]])
    aj = np.array([auto_row[j] for j in pairs[:, 1]])
    is_auto = pairs[:, 0] == pairs[:, 1]
    model = np.stack([vis[..., PRODUCTS[p][1], PRODUCTS[p][0]] for p in pols], axis=-1)  # (Nf, Nt, Nbl, Np)
    same_feed = np.array([PRODUCTS[p][0] == PRODUCTS[p][1] for p in pols])
    model = np.where(is_auto[None, None, :, None] & same_feed, model.real + 0j, model)  # autos are real (rounding)
    var = np.stack([np.abs(vis[:, :, ai, PRODUCTS[p][0], PRODUCTS[p][0]] * vis[:, :, aj, PRODUCTS[p][1],
                                                                                PRODUCTS[p][1]])
                    for p in pols], axis=-1) / (2.0 * dt_s * dnu_hz)
    sigma = np.where(is_auto[None, None, :, None], 0.0, np.sqrt(var))
    data = model
    if noise_seed is not None:
        rng = np.random.default_rng(noise_seed)
        data = model + sigma * (rng.standard_normal(model.shape) + 1j * rng.standard_normal(model.shape))
    return model, sigma, data


def uvdata_of(pos, location, numbers, pairs, times, freqs, pols, data_blt, vis_units, pol_convention, dt_s, dnu_hz,
            history):
    """The pyuvdata ``UVData`` of the simulation (drift scan, flags False, nsamples 1), checked."""
    from pyuvdata import Telescope, UVData, utils

    tel = Telescope.new(
        name="gcrsky-sim", location=location,
        antenna_positions={int(n): p for n, p in zip(numbers, _ecef_relative(pos, location))},
        instrument="matvis", x_orientation="east", feeds=["x", "y"], mount_type="fixed",  # kept only with a mount
    )
    uvd = UVData.new(
        freq_array=freqs, polarization_array=np.asarray([utils.polstr2num(p) for p in pols], np.int64),
        times=np.asarray(times.jd), telescope=tel,
        antpairs=[(int(numbers[i]), int(numbers[j])) for i, j in pairs], do_blt_outer=True,
        time_axis_faster_than_bls=False, integration_time=dt_s, channel_width=dnu_hz,
        data_array=data_blt.astype(np.complex128), vis_units=vis_units, history=history,
    )
    uvd.pol_convention = pol_convention
    uvd.check()
    return uvd
