"""Point sources (issue 12, item 4): their response, the flux block, and the two-block Gibbs sampler.

References and tolerances:

* the source response against matvis 1.3 (``simulate_vis``, CPU, precision 2, unpolarised;
  conventions pinned in ``tests/test_matvis.py``: ``V_gcrsky = 2 V_matvis``, Jy, pair
  ``(i, j)`` is ``<E_i^* E_j>``).  Handed gcrsky's own ENU directions (a matvis
  ``CoordinateRotation`` subclass) the two evaluate the same beam, fringe and units: rounding
  (measured 9e-15 of the largest visibility; tolerance 1e-10).  With real observing times
  and matvis' own astropy ICRS -> AltAz per time, the difference is the geometry gcrsky's
  frame omits (diurnal aberration, polar motion: <= 3.5e-6 rad), a fringe-phase error
  <= 2 pi |b|/lambda 3.5e-6 = 4.8e-4 rad at 21.9 wavelengths (measured 2.9e-4 of the
  largest visibility; tolerance 2e-3);
* the fringe sign and directions against gcrsky's own harmonic operator applied to the
  band-limited delta function at the source (the sharpest sky of degree <= L centred
  there): the difference is the baseline kernel's harmonic content above L (see
  :func:`test_response_equals_harmonic_operator_on_a_peaked_sky`);
* the flux block against dense NumPy algebra (the draw rebuilt from its standard normals:
  rounding) and against its analytic covariance (20000 draws);
* the two-block Gibbs chain against the dense joint Gaussian of ``[a; s]``, within
  Monte-Carlo error from the chain's effective sample size (z-scores < 4: a false-alarm
  rate <= 18 x 6.3e-5 = 1.1e-3 under the null, Bonferroni); negative controls (a sky block
  that ignores the sources, a flux block that ignores the sky) must fail the same check.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _hyper_fixtures import small_problem

from gcrsky.base import kelvin_sr_to_jy
from gcrsky.inference import (
    effective_sample_size,
    flux_setup,
    flux_step,
    gibbs_setup,
    sample_fluxes,
    sky_source_init,
    sky_source_step,
    sky_step,
    source_visibilities,
)
from gcrsky.inference.sources import flux_posterior
from gcrsky.instrument import (
    HERA_LATITUDE_DEG,
    antpairs,
    baseline_vectors,
    gaussian_beam,
    hex_array,
    icrs_to_corotating,
    make_array,
    point_source_response,
    problem_source_response,
    response_matrix,
    source_enu,
)
from gcrsky.model import build_problem, compress_problem
from gcrsky.model.operator import VisOperator, apply, dense_matrix
from gcrsky.sphere import mode_table
from gcrsky.sphere.frames import apply_frame, local_sidereal_angles
from gcrsky.sphere.harmonics import real_basis

LAT_RAD = np.deg2rad(HERA_LATITUDE_DEG)
HERA_LON_DEG, HERA_HEIGHT_M = 21.4283, 1073.0
FREQS_HZ = np.array([100e6, 150e6])
# three sources in the strip the array sees (Dec ~ latitude), and one that never rises
RA_RAD = np.deg2rad([10.0, 40.0, 70.0])
DEC_RAD = np.deg2rad([-30.0, -25.0, -36.0])
LSTS_RAD = np.deg2rad([0.0, 20.0, 45.0, 80.0])
Z_MAX = 4.0  # two-sided 6.3e-5 per z-score


@pytest.fixture(scope="module")
def array():
    return make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))


def _site():
    import astropy.units as u
    from astropy.coordinates import EarthLocation

    return EarthLocation.from_geodetic(lon=HERA_LON_DEG * u.deg, lat=HERA_LATITUDE_DEG * u.deg,
                                       height=HERA_HEIGHT_M * u.m)


@pytest.fixture(autouse=True)
def _offline_iers():
    """No IERS downloads (offline machines); the bundled tables cover the times used here."""
    from astropy.utils import iers

    with iers.conf.set_temp("auto_download", False), iers.conf.set_temp("auto_max_age", None):
        yield


def _times(n=4, hours=2.0):
    import astropy.units as u
    from astropy.time import Time

    return Time("2020-06-01T03:00:00", scale="utc") + np.linspace(0.0, hours, n) * u.hour


# ---------------------------------------------------------------------------- the response


@functools.lru_cache(maxsize=1)
def _register_topocentric():
    """A matvis coordinate method (registered by class name) that uses given ENU unit vectors,
    (Ntimes, 3, Nsrc): matvis then sees exactly gcrsky's directions."""
    from matvis.core.coords import CoordinateRotation

    class GcrskySourceTopocentric(CoordinateRotation):
        def __init__(self, *args, enu, **kwargs):
            super().__init__(*args, **kwargs)
            self._enu = np.asarray(enu, np.float64)

        def rotate(self, t: int) -> None:
            self.all_coords_topo[:] = self._enu[t]

    return GcrskySourceTopocentric


def _matvis(array, pairs, enu_or_none, ra, dec, times):
    """matvis' visibilities (Jy) of 1 Jy sources, one run per source: (Nf, Nt, Nbl, Ns).

    ``enu_or_none``: (Nt, Ns, 3) directions handed to matvis as they are, or None for matvis'
    own astropy transform of the ICRS ``(ra, dec)`` at ``times``."""
    matvis = pytest.importorskip("matvis")
    _register_topocentric()
    out = []
    for s in range(ra.size):
        kw = {}
        if enu_or_none is not None:
            kw = dict(coord_method="GcrskySourceTopocentric",
                      coord_method_params={"enu": np.transpose(enu_or_none[:, s:s + 1], (0, 2, 1))})
        v = matvis.simulate_vis(
            ants={i: p for i, p in enumerate(array.positions_enu_m)}, fluxes=np.ones((1, FREQS_HZ.size)),
            ra=ra[s:s + 1], dec=dec[s:s + 1], freqs=FREQS_HZ, times=times, beams=[array.beams[0]],
            telescope_loc=_site(), polarized=False, precision=2, antpairs=pairs, **kw)
        out.append(np.asarray(v))
    return np.stack(out, axis=-1)


def test_response_matches_matvis_same_directions(array):
    """Beam, fringe sign, antenna order, factor 2 and Jy: rounding-level agreement with matvis."""
    pairs = antpairs(10)
    K = np.asarray(point_source_response(array, pairs, FREQS_HZ, ra_rad=RA_RAD, dec_rad=DEC_RAD,
                                         lsts_rad=LSTS_RAD))
    assert K.shape == (2, 4, 45, 3) and K.dtype == np.complex128
    enu = source_enu(RA_RAD, DEC_RAD, latitude_rad=LAT_RAD, lsts_rad=LSTS_RAD)  # (Nt, Ns, 3)
    vm = _matvis(array, pairs, enu, RA_RAD, DEC_RAD, _times(LSTS_RAD.size))
    kj = K * kelvin_sr_to_jy(FREQS_HZ)[:, None, None, None]  # K sr per Jy -> Jy per Jy
    err = np.abs(kj - 2 * vm).max() / np.abs(kj).max()
    assert err < 1e-10, err  # measured 9e-15
    assert np.abs(np.conj(kj) - 2 * vm).max() / np.abs(kj).max() > 0.5  # the other fringe sign fails


def test_response_matches_matvis_at_real_times(array):
    """ICRS sources at real times: gcrsky's frame (aberration, precession at mid-span, then the local
    Earth rotation angle) against matvis' astropy ICRS -> AltAz at every time."""
    pairs = antpairs(10)
    times = _times(5, hours=6.0)
    era = local_sidereal_angles(times, HERA_LON_DEG)
    ra, dec = era[[1, 2, 3]] + np.deg2rad([2.0, -3.0, 1.0]), np.deg2rad([-30.0, -25.0, -36.0])  # up while observed
    K = np.asarray(point_source_response(array, pairs, FREQS_HZ, ra_rad=ra, dec_rad=dec, times=times,
                                         location=_site()))
    vm = _matvis(array, pairs, None, ra, dec, times)
    kj = K * kelvin_sr_to_jy(FREQS_HZ)[:, None, None, None]
    err = np.abs(kj - 2 * vm).max() / np.abs(kj).max()
    assert err < 2e-3, err  # geometry floor (module docstring)
    # negative control: the ICRS coordinates taken as co-rotating ones (no precession, aberration)
    K0 = np.asarray(point_source_response(array, pairs, FREQS_HZ, ra_rad=ra, dec_rad=dec, lsts_rad=era))
    assert np.abs(K0 * kelvin_sr_to_jy(FREQS_HZ)[:, None, None, None] - 2 * vm).max() / np.abs(kj).max() > 0.05


def _band_limited_delta(lmax, ra, dec):
    """Realified coefficients (Ns, n) of the delta function at each source truncated at ``lmax``:
    ``a_lm = conj(Y_lm(s0))``, i.e. ``a_k = f_k(s0) / ||f_k||^2`` (1 for m = 0, 2 for m > 0)."""
    F = np.asarray(real_basis(lmax, jnp.asarray(np.pi / 2 - dec), jnp.asarray(ra)))
    return F / np.where(mode_table(lmax).m == 0, 1.0, 2.0)


def test_response_equals_harmonic_operator_on_a_peaked_sky(array):
    """gcrsky's operator on the band-limited delta at each source reproduces its point response.

    A unit (K sr) source is the sky ``delta(s0)``; truncated at degree L it is the sharpest sky
    of that band limit centred on the source (main lobe ~ pi/L), and ``X a`` differs from the
    point response only by the baseline kernel ``A_i A_j exp(2 pi i b.s/lambda)``'s harmonic
    content above L.  For the 14.6 m baselines at 100 MHz that content is centred at the fringe
    rate l ~ 2 pi |b|/lambda = 31, spread by the beam (power FWHM 12.3 deg: ~1/sigma_P = 11 in
    l): L = 80 is 4.5 spreads out, exp(-4.5^2/2) ~ 4e-5.  Measured (nside 128): 0.42 (L = 40),
    9.8e-3 (60), 1.2e-5 (80), 9.6e-7 (100); at L = 80, nside 64: 1.1e-5.  Tolerance 1e-4.  The conjugate fringe and a
    mirrored RA both fail by O(1).  (Longer baselines need larger L: 43.8 m needs L ~ 150.)
    """
    L, nside = 80, 64  # nside 128 gives the same error (1.2e-5): the band limit dominates
    pairs = antpairs(10)
    short = np.linalg.norm(baseline_vectors(array.positions_enu_m, pairs), axis=1) < 15.0  # 19 baselines
    freqs = FREQS_HZ[:1]
    K = np.asarray(point_source_response(array, pairs[short], freqs, ra_rad=RA_RAD, dec_rad=DEC_RAD,
                                         lsts_rad=LSTS_RAD, flux_unit="K sr"))[0]  # (Nt, Nbl, Ns)
    op = VisOperator(response_matrix(array, pairs[short], freqs, L, nside), jnp.asarray(LSTS_RAD), None)
    a = _band_limited_delta(L, RA_RAD, DEC_RAD)
    V = np.stack([np.asarray(apply(op, jnp.asarray(a[s:s + 1])))[0] for s in range(RA_RAD.size)], axis=-1)
    scale = np.abs(K).max()
    err = np.abs(V - K).max() / scale
    assert err < 1e-4, err
    assert np.abs(V - np.conj(K)).max() / scale > 0.5
    K_mirror = np.asarray(point_source_response(array, pairs[short], freqs, ra_rad=-RA_RAD, dec_rad=DEC_RAD,
                                                lsts_rad=-LSTS_RAD, flux_unit="K sr"))[0]
    assert np.abs(V - K_mirror).max() / scale > 0.5


@pytest.fixture(scope="module")
def realtime_problem(array):
    """A real-time (ICRS) problem at lmax 6 (its frame map, LSTs and pairs are what is used here, so
    its responses are placeholders of the right shape, (1, 45, n_resp) and (1, 10, n_resp))."""
    times = _times(4, hours=3.0)
    zeros = (jnp.zeros((1, 45, 121), complex), jnp.zeros((1, 10, 121), complex))  # lmax 6 + pad 4
    return build_problem(array, FREQS_HZ[:1], None, 6, 16, times=times, location=_site(),
                         data=np.zeros((1, 4, 45), complex), sigma=1.0, responses=zeros), times


@pytest.fixture(scope="module")
def small():
    """``small_problem(nf=1)``: lmax 4, 11 LSTs over a day, sigma 0.05 K sr (shared)."""
    return small_problem(nf=1)


def test_real_time_sources_sit_where_the_frame_map_puts_the_sky(realtime_problem):
    """A band-limited ICRS sky ``f`` seen through the problem's frame map ``M``: ``(M a)(q) = f(p)``
    with ``q`` the co-rotating direction :func:`icrs_to_corotating` gives the ICRS point ``p``."""
    prob, times = realtime_problem
    rng = np.random.default_rng(5)
    a = rng.standard_normal(49)
    lmax_out = int(round(np.sqrt(prob.response.shape[-1]))) - 1
    ma = np.asarray(jax.jit(apply_frame)(prob.frame, jnp.asarray(a)))
    ra, dec = rng.uniform(0, 2 * np.pi, 50), np.arcsin(rng.uniform(-1, 1, 50))
    mid = times.min() + (times.max() - times.min()) / 2
    ra_c, dec_c = icrs_to_corotating(ra, dec, mid)
    f_icrs = np.asarray(real_basis(6, jnp.asarray(np.pi / 2 - dec), jnp.asarray(ra))) @ a
    seen = np.asarray(real_basis(lmax_out, jnp.asarray(np.pi / 2 - dec_c), jnp.asarray(ra_c))) @ ma
    scale = np.abs(f_icrs).max()
    # the frame map is exact up to aberration's leakage beyond lmax + 4 (~(1e-4 l)^5); measured 2.8e-14
    assert np.abs(seen - f_icrs).max() / scale < 1e-10
    # control: the ICRS coordinates taken as co-rotating ones (precession, 0.3 deg) fail (measured 5.7e-3)
    assert np.abs(np.asarray(real_basis(lmax_out, jnp.asarray(np.pi / 2 - dec), jnp.asarray(ra))) @ ma
                  - f_icrs).max() / scale > 1e-3
    # astropy's own ICRS -> CIRS differs only by the light deflection by the Sun that the frame map (and
    # so icrs_to_corotating) omits: 2 GM / (c^2 AU) cot(psi / 2) = 1.97e-8 cot(psi / 2) rad at angle psi
    # from the Sun (measured: 0.99 of it, 8.5e-7 rad for the direction 2.6 deg from the Sun)
    import astropy.units as u
    from astropy.coordinates import CIRS, ICRS, SkyCoord
    from astropy.coordinates.erfa_astrom import erfa_astrom

    c = SkyCoord(ra=ra * u.rad, dec=dec * u.rad, frame=ICRS()).transform_to(CIRS(obstime=mid))

    def unit(r, d):
        return np.stack([np.cos(d) * np.cos(r), np.cos(d) * np.sin(r), np.sin(d)], axis=1)

    ang = np.linalg.norm(np.cross(unit(ra_c, dec_c), unit(c.ra.rad, c.dec.rad)), axis=1)
    eh = np.asarray(erfa_astrom.get().apco(CIRS(obstime=mid))["eh"]).ravel()  # Sun -> observer
    psi = np.arccos(np.clip(-unit(ra, dec) @ eh, -1.0, 1.0))
    assert np.all(ang <= 1.05 * 1.97e-8 / np.tan(psi / 2) + 1e-12)


def test_problem_source_response_frames_and_errors(array, realtime_problem):
    prob, times = realtime_problem
    K = problem_source_response(prob, array, ra_rad=RA_RAD, dec_rad=DEC_RAD, times=times, location=_site())
    ref = point_source_response(array, prob.antpairs, prob.freqs_hz, ra_rad=RA_RAD, dec_rad=DEC_RAD, times=times,
                                location=_site())
    np.testing.assert_array_equal(np.asarray(K), np.asarray(ref))
    with pytest.raises(ValueError, match="real observing times"):
        problem_source_response(prob, array, ra_rad=RA_RAD, dec_rad=DEC_RAD)
    import astropy.units as u

    with pytest.raises(ValueError, match="rotation angles"):
        problem_source_response(prob, array, ra_rad=RA_RAD, dec_rad=DEC_RAD, times=times + 0.01 * u.day,
                                location=_site())
    import dataclasses

    dense = dataclasses.replace(prob, frame=jnp.eye(prob.response.shape[-1], 49))
    with pytest.raises(NotImplementedError, match="dense"):
        problem_source_response(dense, array, ra_rad=RA_RAD, dec_rad=DEC_RAD, times=times, location=_site())
    other = make_array(hex_array() * 1.01, HERA_LATITUDE_DEG, gaussian_beam(14.0))
    with pytest.raises(ValueError, match="antpos"):
        problem_source_response(prob, other, ra_rad=RA_RAD, dec_rad=DEC_RAD, times=times, location=_site())


def test_problem_source_response_idealised_and_compressed(array, small):
    prob = small
    K = np.asarray(problem_source_response(prob, array, ra_rad=RA_RAD, dec_rad=DEC_RAD))
    ref = np.asarray(point_source_response(array, antpairs(10), prob.freqs_hz, ra_rad=RA_RAD, dec_rad=DEC_RAD,
                                           lsts_rad=prob.lsts_rad))
    np.testing.assert_array_equal(K, ref)
    with pytest.raises(ValueError, match="idealised"):
        problem_source_response(prob, array, ra_rad=RA_RAD, dec_rad=DEC_RAD, times=_times(), location=_site())
    comp = compress_problem(prob)
    Kc = np.asarray(problem_source_response(comp, array, ra_rad=RA_RAD, dec_rad=DEC_RAD))
    assert Kc.shape == (1, prob.lsts_rad.size, comp.antpairs.shape[0], 3) and comp.antpairs.shape[0] < 45
    # each compressed row is its group's common row: every member's response equals the representative's
    pos = array.positions_enu_m
    for row, (i, j) in enumerate(comp.antpairs):
        same = np.flatnonzero(np.all(np.abs(baseline_vectors(pos, antpairs(10)) - (pos[j] - pos[i])) < 1e-9, axis=1))
        np.testing.assert_allclose(K[:, :, same], np.repeat(Kc[:, :, row:row + 1], same.size, axis=2),
                                   rtol=1e-12, atol=1e-15)


def test_response_units_horizon_and_bad_input(array):
    pairs = antpairs(10)
    kw = dict(lsts_rad=LSTS_RAD)
    jy = np.asarray(point_source_response(array, pairs, FREQS_HZ, ra_rad=RA_RAD, dec_rad=DEC_RAD, **kw))
    ksr = np.asarray(point_source_response(array, pairs, FREQS_HZ, ra_rad=RA_RAD, dec_rad=DEC_RAD, flux_unit="K sr",
                                           **kw))
    np.testing.assert_allclose(jy * kelvin_sr_to_jy(FREQS_HZ)[:, None, None, None], ksr, rtol=1e-14)
    # a source at zenith at LST = RA: A_i A_j = 1 (peak-normalised beam), fringe phase 0
    z = np.asarray(point_source_response(array, pairs, FREQS_HZ, ra_rad=0.3, dec_rad=LAT_RAD, lsts_rad=[0.3],
                                         flux_unit="K sr"))
    np.testing.assert_allclose(z, 1.0, atol=1e-12)
    # Dec +80 never rises at latitude -30.7: exactly zero at every time, no error
    never = np.asarray(point_source_response(array, pairs, FREQS_HZ, ra_rad=[0.0, 1.0], dec_rad=np.deg2rad([80, 85]),
                                             lsts_rad=np.linspace(0, 2 * np.pi, 7)))
    assert never.shape == (2, 7, 45, 2) and np.all(never == 0)
    for bad in (dict(ra_rad=RA_RAD, dec_rad=DEC_RAD[:2]), dict(ra_rad=RA_RAD[None], dec_rad=DEC_RAD[None]),
                dict(ra_rad=RA_RAD, dec_rad=DEC_RAD + 3.0), dict(ra_rad=[np.nan], dec_rad=[0.0])):
        with pytest.raises(ValueError):
            point_source_response(array, pairs, FREQS_HZ, **bad, **kw)
    with pytest.raises(ValueError, match="same shape"):
        point_source_response(array, pairs, FREQS_HZ, ra_rad=RA_RAD, dec_rad=DEC_RAD[:2], **kw)
    with pytest.raises(ValueError, match="flux_unit"):
        point_source_response(array, pairs, FREQS_HZ, ra_rad=RA_RAD, dec_rad=DEC_RAD, flux_unit="mJy", **kw)
    with pytest.raises(ValueError, match="lsts_rad"):
        point_source_response(array, pairs, FREQS_HZ, ra_rad=RA_RAD, dec_rad=DEC_RAD)


# ---------------------------------------------------------------------------- the flux block


def _random_block(seed=0, nf=2, nt=5, nbl=7, ns=3, flagged=0.2):
    rng = np.random.default_rng(seed)
    K = rng.standard_normal((nf, nt, nbl, ns)) + 1j * rng.standard_normal((nf, nt, nbl, ns))
    w = rng.uniform(0.5, 2.0, (nf, nt, nbl)) * (rng.uniform(size=(nf, nt, nbl)) > flagged)
    r = rng.standard_normal((nf, nt, nbl)) + 1j * rng.standard_normal((nf, nt, nbl))
    mu = rng.standard_normal((nf, ns))
    var = rng.uniform(0.5, 3.0, (nf, ns))
    return K, w, r, mu, var


def _dense_flux_posterior(K, w, r, mu, cinv):
    """Realified normal equations in NumPy: [K_r; K_i] with weights [w; w] (independent of the complex form)."""
    out_m, out_p = [], []
    for f in range(K.shape[0]):
        A = K[f].reshape(-1, K.shape[-1])
        Ar = np.concatenate([A.real, A.imag])
        wr = np.concatenate([w[f].ravel()] * 2)
        dr = np.concatenate([r[f].ravel().real, r[f].ravel().imag])
        P = Ar.T @ (wr[:, None] * Ar) + cinv[f]
        out_p.append(P)
        out_m.append(np.linalg.solve(P, Ar.T @ (wr * dr) + cinv[f] @ mu[f]))
    return np.array(out_m), np.array(out_p)


def test_sample_fluxes_is_the_dense_formula_exactly():
    K, w, r, mu, var = _random_block()
    r_garbage = np.where(w > 0, r, 1e30)  # flagged samples (w = 0) carry no information
    key = jax.random.PRNGKey(3)
    s = np.asarray(jax.jit(lambda k: sample_fluxes(k, K, w, r_garbage, mu, prior_var=var))(key))
    mean, P = _dense_flux_posterior(K, w, r, mu, np.stack([np.diag(1 / v) for v in var]))
    z = np.asarray(jax.random.normal(key, mu.shape))  # flux_step's documented standard normals
    expect = np.stack([mean[f] + np.linalg.solve(np.linalg.cholesky(P[f]).T, z[f]) for f in range(2)])
    np.testing.assert_allclose(s, expect, rtol=1e-11, atol=1e-12)
    m2, cov = jax.jit(lambda r: flux_posterior(flux_setup(K, w, mu, prior_var=var), r))(r)
    np.testing.assert_allclose(np.asarray(m2), mean, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(np.asarray(cov), np.linalg.inv(P), rtol=1e-11, atol=1e-13)
    # a full covariance equal to the diagonal one gives the same draw; a correlated one the dense answer
    s_cov = jax.jit(lambda k: sample_fluxes(k, K, w, r, mu, prior_cov=np.stack([np.diag(v) for v in var])))(key)
    np.testing.assert_allclose(np.asarray(s_cov), s, rtol=1e-11, atol=1e-12)
    rng = np.random.default_rng(1)
    B = rng.standard_normal((2, 3, 3))
    C = B @ np.swapaxes(B, 1, 2) + np.eye(3)
    m3, _ = jax.jit(lambda r: flux_posterior(flux_setup(K, w, mu, prior_cov=C), r))(r)
    np.testing.assert_allclose(np.asarray(m3), _dense_flux_posterior(K, w, r, mu, np.linalg.inv(C))[0], rtol=1e-10)


def test_sample_fluxes_covariance_from_draws():
    """20000 draws: sample mean and covariance against the analytic Gaussian (5-sigma bounds)."""
    K, w, r, mu, var = _random_block(seed=2, nf=1)
    block = jax.jit(lambda: flux_setup(K, w, mu, prior_var=var))()
    mean, cov = (np.asarray(x)[0] for x in jax.jit(flux_posterior)(block, r))
    n = 20000
    draw = jax.jit(jax.vmap(lambda k: flux_step(k, block, r)))
    s = np.asarray(draw(jax.random.split(jax.random.PRNGKey(0), n)))[:, 0]
    sd = np.sqrt(np.diag(cov))
    assert np.all(np.abs(s.mean(0) - mean) < 5 * sd / np.sqrt(n))
    emp = np.cov(s.T)
    se = np.sqrt((cov**2 + np.outer(np.diag(cov), np.diag(cov))) / n)  # sd of a Gaussian sample covariance
    assert np.all(np.abs(emp - cov) < 5 * se), (emp - cov) / se
    # a draw with the data-space noise halved (the reference code's pitfall) would be under-dispersed
    assert np.all(np.abs(0.5 * np.diag(cov) - np.diag(emp)) > 5 * np.diag(se))


def test_flux_block_bad_input():
    K, w, r, mu, var = _random_block(nf=1)
    with pytest.raises(ValueError, match="exactly one"):
        flux_setup(K, w, mu)
    with pytest.raises(ValueError, match="exactly one"):
        flux_setup(K, w, mu, prior_var=var, prior_cov=np.eye(3))
    with pytest.raises(ValueError, match="inv_noise"):
        flux_setup(K, w[:, :-1], mu, prior_var=var)
    with pytest.raises(ValueError, match="prior_var"):
        flux_setup(K, w, mu, prior_var=np.ones(4))
    with pytest.raises(ValueError, match="residual_vis"):
        flux_step(jax.random.PRNGKey(0), flux_setup(K, w, mu, prior_var=var), r[:, :-1])
    np.testing.assert_allclose(np.asarray(source_visibilities(K, mu)), np.einsum("ftbs,fs->ftb", K, mu), rtol=1e-14)


# ---------------------------------------------------------------------------- the two-block sampler


@pytest.fixture(scope="module")
def two_block(array, small):
    """small_problem(nf=1) (lmax 4, 11 LSTs over a day, sigma 0.05 K sr) plus 3 sources in the strip.

    Fluxes 40, 60, 30 Jy: source visibilities ~0.03 K sr, 2-3x the sky's (rms 0.012 K sr).
    The prior N(mu, (0.5 s_true)^2) with mu 10-20% off.  The dense joint posterior of [a; s]
    has canonical correlations 0.14, 0.13, 0.08 between the blocks: the blocks interact but
    the Gibbs chain mixes well (ESS ~ 0.9 per step)."""
    prob = small
    lst = np.asarray(prob.lsts_rad)
    ra = lst[[1, 4, 7]] + np.deg2rad([3.0, -4.0, 2.0])
    dec = LAT_RAD + np.deg2rad([2.0, -3.0, 0.5])
    K = problem_source_response(prob, array, ra_rad=ra, dec_rad=dec)
    s_true = np.array([[40.0, 60.0, 30.0]])
    system = prob.system()
    system = system._replace(data=system.data + source_visibilities(K, s_true))
    mu, var = s_true * np.array([1.2, 0.8, 1.1]), (0.5 * s_true) ** 2
    # the dense joint Gaussian of x = [a; s] (NumPy, realified)
    X = np.asarray(dense_matrix(system.op))[0]  # (Nt, Nbl, n)
    n = X.shape[-1]
    A = np.concatenate([X, np.asarray(K)[0]], axis=-1).reshape(-1, n + 3)
    w = np.asarray(system.inv_noise)[0].ravel()
    d = np.asarray(system.data)[0].ravel()
    Ar, wr, dr = np.concatenate([A.real, A.imag]), np.concatenate([w, w]), np.concatenate([d.real, d.imag])
    prec0 = np.concatenate([np.asarray(system.prior.inv_var)[0], 1.0 / var[0]])
    x0 = np.concatenate([np.asarray(system.prior.mean)[0], mu[0]])
    P = Ar.T @ (wr[:, None] * Ar) + np.diag(prec0)
    cov = np.linalg.inv(P)
    mean = cov @ (Ar.T @ (wr * dr) + prec0 * x0)
    fixed = gibbs_setup(system)  # the sky block's data term and factor, built once
    block = flux_setup(K, system.inv_noise, mu, prior_var=var)
    return dict(system=system, K=K, mu=mu, var=var, mean=mean, cov=cov, n=n, s_true=s_true, fixed=fixed, block=block)


def _chains(tb, steps, key):
    """The library's two-block chain (:func:`sky_source_step` in one jitted ``lax.scan``), (steps, n + Ns)."""
    system, fixed, block = tb["system"], tb["fixed"], tb["block"]

    @jax.jit
    def run(key):
        def body(state, k):
            state, _ = sky_source_step(k, state, fixed, block)
            return state, jnp.concatenate([state.sky[0], state.fluxes[0]])

        return jax.lax.scan(body, sky_source_init(system.prior.mean, tb["mu"]), jax.random.split(key, steps))[1]

    return np.asarray(run(key))


def _hand_chains(tb, steps, key, *, sky_sees_sources=1.0, fluxes_see_sky=1.0):
    """The same sweep written out, with each block's view of the other scaled by a traced factor
    (one compilation for the negative controls; with both factors 1 it is the library's step)."""
    system, fixed, block = tb["system"], tb["fixed"], tb["block"]

    @jax.jit
    def run(key, c_sky, c_flux):
        def body(state, k):
            k_sky, k_flux = jax.random.split(k)
            a, _ = sky_step(k_sky, fixed, state.sky,
                            data=system.data - c_sky * source_visibilities(block.response, state.fluxes))
            s = flux_step(k_flux, block, system.data - c_flux * apply(system.op, a))
            return type(state)(a, s), jnp.concatenate([a[0], s[0]])

        return jax.lax.scan(body, sky_source_init(system.prior.mean, tb["mu"]), jax.random.split(key, steps))[1]

    return np.asarray(run(key, jnp.asarray(sky_sees_sources), jnp.asarray(fluxes_see_sky)))


def _z_scores(tb, chain):
    """Means, variances and covariances of the fluxes and of 3 sky functionals vs the dense joint.

    Functionals: g_j = c_j . a with c_j = Cov(a)^-1 Cov(a, s_j), the sky functional most correlated
    with flux j.  Each estimate's Monte-Carlo error uses the ESS of its own series.  18 z-scores."""
    n, mean, cov = tb["n"], tb["mean"], tb["cov"]
    C = np.zeros((n + 3, 6))
    C[n:, :3] = np.eye(3)
    c = np.linalg.solve(cov[:n, :n], cov[:n, n:])
    C[:n, 3:] = c / np.linalg.norm(c, axis=0)
    y = chain @ C
    m, S = mean @ C, C.T @ cov @ C
    dev = y - m
    pairs = [(i, i) for i in range(6)] + [(j, j + 3) for j in range(3)] + [(0, 1), (0, 2), (1, 2)]
    series = [dev] + [dev[:, [i]] * dev[:, [j]] for i, j in pairs]
    ess = np.asarray(effective_sample_size(jnp.asarray(np.concatenate(series, axis=1))[None]))
    z_mean = (dev.mean(0)) / np.sqrt(np.diag(S) / ess[:6])
    z_mom = np.array([
        (series[k + 1].mean() - S[i, j]) / np.sqrt((S[i, i] * S[j, j] + S[i, j] ** 2) / ess[6 + k])
        for k, (i, j) in enumerate(pairs)
    ])
    return np.concatenate([z_mean, z_mom]), ess


@pytest.mark.slow
def test_two_block_gibbs_matches_the_dense_joint_gaussian(two_block):
    tb = two_block
    steps, burn = 4000, 200
    chain = _chains(tb, steps, jax.random.PRNGKey(1))[burn:]
    z, ess = _z_scores(tb, chain)
    print(f"two-block Gibbs vs dense joint: max |z| {np.abs(z).max():.2f} of 18, ESS {ess[:6].round()}")
    assert np.abs(z).max() < Z_MAX, z
    assert ess[:6].min() > 1000, ess  # measured ~3600 of 3800
    # the joint posterior is informative: the fluxes are within 4 posterior sd of the truth
    n, sd = tb["n"], np.sqrt(np.diag(tb["cov"]))
    assert np.all(np.abs(tb["mean"][n:] - tb["s_true"][0]) < 4 * sd[n:])
    # negative controls, the same check: the sky ignoring the sources; the fluxes ignoring the sky
    hand = _hand_chains(tb, steps, jax.random.PRNGKey(1))[burn:]
    np.testing.assert_allclose(hand, chain, rtol=1e-9, atol=1e-9 * np.abs(chain).max())  # the control's baseline
    for kw in (dict(sky_sees_sources=0.0), dict(fluxes_see_sky=0.0)):
        bad, _ = _z_scores(tb, _hand_chains(tb, steps, jax.random.PRNGKey(1), **kw)[burn:])
        print(f"negative control {kw}: max |z| {np.abs(bad).max():.1f}")
        assert np.abs(bad).max() > Z_MAX, (kw, bad)
