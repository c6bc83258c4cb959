"""The flux-scale check (:mod:`gcrsky.model.fluxscale`) against matvis autocorrelations at six LSTs.

matvis is an independent simulator (its own ICRS -> AltAz per time, its own beam
interpolation, a feed sees I/2, output in Jy); the check's model is a HEALPix quadrature of
``int P T dOmega`` at the data's times.  Given the *same* sky, the two must agree to the
quadrature's accuracy at every LST: measured on the GSM's l <= 16 sky at 120-180 MHz and
LSTs 5.7 + 4 k h, ``|data / model - 1| <= 0.003`` (nside-32 quadrature of a 14 m Gaussian
dish, FWHM 8.4 deg at 147 MHz, against matvis at nside 64); the tolerance 0.01 leaves room
for platform rounding and is 30x below the 1.3x negative control.

The second test pins the cause of the 23 % deficit reported on the H1C twin (issue 38): the
twin's sky is the GSM's l <= 16 plus a random isotropic extension to l = 160
(:func:`gcrsky.sim.sky.sky_truth`, seed 2024), structure at the beam's scale that no
nside-8 GSM carries; at the H1C LST (5.7 h) it puts a cold fluctuation in the beam.
"""

from __future__ import annotations

import dataclasses

import healpy as hp
import numpy as np
import pytest

pytest.importorskip("matvis")
pytest.importorskip("pyradiosky")

from gcrsky.base.units import kelvin_sr_to_jy  # noqa: E402
from gcrsky.instrument.beams import gaussian_beam  # noqa: E402

#: The H1C file's first time (zen.2458098.45361, LST 5.71 h) and five more 4 sidereal hours apart.
JD_H1C = 2458098.45677626
FREQS = np.array([120e6, 146.875e6, 180e6])
LMAX = 16
#: |data / model - 1| allowed per (channel, time) for a sky both sides know (module docstring).
TOL = 0.01


def _times(offsets_sidereal_hours):
    from astropy.time import Time

    return Time(JD_H1C + np.asarray(offsets_sidereal_hours) / 24 / 1.0027379, format="jd", scale="utc")


def _simulate(alm, lmax, times, freqs, dish_m=14.0, nside_matvis=64, **kw):
    """pI Observation of matvis autos (and the crosses of two antennas) of the ICRS sky ``alm``, Jy, "sum"
    unless ``kw`` (``vis_units``, ``pol_convention``) says otherwise."""
    from gcrsky.checks.matvis import HERA_SITE, site
    from gcrsky.checks.uvsim import simulate_uvdata
    from gcrsky.io.observation import read_observation

    pos = np.array([[0.0, 0.0, 0.0], [14.6, 0.0, 0.0]])
    sim = simulate_uvdata(pos, site(*HERA_SITE), times, freqs, gaussian_beam(dish_m), alm, lmax,
                          nside_matvis=nside_matvis, noise_seed=None, **kw)
    return read_observation(sim.uvdata, pol="pI")


def _maps(alm, lmax, nside=64):
    """(Nf, npix) K maps at ``nside`` of the band-limited ICRS sky ``alm`` (Nf, n): the check's ``sky``."""
    from gcrsky.sphere.maps import alm_to_map

    return np.stack([alm_to_map(a, lmax, nside) for a in np.atleast_2d(alm)])


@pytest.fixture(scope="module")
def gsm_sky():
    from gcrsky.model.skyprior import gsm_prior_mean

    return gsm_prior_mean(FREQS, LMAX)  # (Nf, (LMAX+1)^2) K: the GSM's own l <= 16


@pytest.fixture(scope="module")
def day(gsm_sky):
    """matvis autos of the GSM's l <= 16 sky at six LSTs spread over the day (5.7, 9.7, ..., 1.7 h)."""
    return _simulate(gsm_sky, LMAX, _times(4.0 * np.arange(6)), FREQS)


def test_model_autos_match_matvis_at_six_lsts(day, gsm_sky):
    """Per channel and time, data / model = 1 within TOL; the data converted here independently of the check."""
    from gcrsky.model.fluxscale import flux_scale_check, model_autos

    lst_h = np.rad2deg(np.unwrap(day.lsts_rad)) / 15 % 24
    assert day.n_times == 6 and np.ptp(np.sort(lst_h)) > 18  # spread over the day
    sky, beam = _maps(gsm_sky, LMAX), gaussian_beam(14.0)
    k = [day.pol_index(p) for p in ("xx", "yy")]
    # "sum": V_xx + V_yy = int P I dOmega (each feed sees I/2), Jy -> K sr by 2 k nu^2 / c^2
    data = (day.autos[k[0]].real + day.autos[k[1]].real) / kelvin_sr_to_jy(day.freqs_hz)[:, None, None]
    ratio = data / model_autos(day, beam, sky=sky)[:, :, None]  # (Nf, Nt, Nant)
    np.testing.assert_allclose(ratio, 1.0, atol=TOL)
    rec = flux_scale_check(day, beam, sky=sky)
    assert abs(rec["ratio"] - 1) < TOL and rec["within"] and rec["units"] == "Jy"
    # data x 0.003 and stored as uncalibrated (taken as Jy): the check reads 0.003
    scaled = dataclasses.replace(day, autos=0.003 * day.autos, vis=0.003 * np.asarray(day.vis), vis_units="uncalib")
    rec = flux_scale_check(scaled, beam, sky=sky)
    assert abs(rec["ratio"] / 0.003 - 1) < TOL and rec["units"] == "uncalib (taken as Jy)" and not rec["within"]
    # negative control: a calibration 1.3x off is caught per channel
    off = flux_scale_check(dataclasses.replace(day, autos=1.3 * day.autos), beam, sky=sky)
    assert all(abs(r - 1.3) < 1.3 * TOL for r in off["ratio_per_channel"])


@pytest.mark.parametrize("units, convention", [("K str", "sum"), ("Jy", "avg"), ("K str", "avg")])
def test_units_and_pol_conventions(gsm_sky, units, convention):
    """Files in K str and/or with pol_convention "avg" (products doubled: I-equivalent) read 1 as well."""
    from gcrsky.model.fluxscale import flux_scale_check

    obs = _simulate(gsm_sky[1:2], LMAX, _times([8.0]), FREQS[1:2], nside_matvis=32, vis_units=units,
                    pol_convention=convention)
    assert (obs.vis_units, obs.pol_convention) == (units, convention)
    assert abs(flux_scale_check(obs, gaussian_beam(14.0), sky=_maps(gsm_sky[1:2], LMAX))["ratio"] - 1) < TOL


def test_a_beam_twice_as_wide_is_caught(gsm_sky):
    """Data through a 7 m dish (beam twice as wide) checked with the 14 m beam: far outside the tolerance."""
    from gcrsky.model.fluxscale import flux_scale_check

    obs = _simulate(gsm_sky[1:2], LMAX, _times([0.0, 12.0]), FREQS[1:2], dish_m=7.0, nside_matvis=32)
    sky = _maps(gsm_sky[1:2], LMAX)
    rec = flux_scale_check(obs, gaussian_beam(14.0), sky=sky)
    assert rec["ratio"] > 3  # measured 3.85: ~4x the solid angle, less the sky's fall-off away from the zenith
    assert abs(flux_scale_check(obs, gaussian_beam(7.0), sky=sky)["ratio"] - 1) < TOL  # the right beam: 1 again


def test_the_default_sky_is_the_gsm_and_a_wrong_shape_is_refused(day):
    """``sky=None`` is the GSM's maps given explicitly, to the bit; a sky of the wrong shape is refused."""
    from gcrsky.model.fluxscale import model_autos
    from gcrsky.model.gsmsky import gsm_maps

    beam = gaussian_beam(14.0)
    assert np.array_equal(model_autos(day, beam), model_autos(day, beam, sky=gsm_maps(day.freqs_hz)[0]))
    with pytest.raises(ValueError, match="sky must be HEALPix maps"):
        model_autos(day, beam, sky=np.ones((day.n_freqs + 1, 768)))


def test_the_twins_deficit_is_its_sky_beyond_the_gsms_resolution():
    """The H1C twin's 0.77 (issue 38) reproduced and explained, against the unpatched check (the shipped GSM).

    The twin's sky (:func:`gcrsky.sim.sky.sky_truth` at l = 160, seed 2024) is the GSM's
    l <= 16 plus an isotropic Gaussian extension; at the H1C LST the extension is cold in the
    beam: 0.74 at 147 MHz (measured 0.741; the twin's four channels gave 0.769).  The same
    sky cut at l = 16 reads 0.93 (the nside-8 GSM's l <= 16 expansion against its bilinear
    interpolation, the check's model); the extension's own l <= 16 part is nil, so the
    difference is structure at 17 <= l <= 160, which no nside-8 map carries.
    """
    from gcrsky.model.fluxscale import flux_scale_check
    from gcrsky.sim.sky import sky_truth

    f = FREQS[1:2]
    twin = sky_truth(f, 160, source="pyradiosky", extend_seed=2024)
    obs = _simulate(twin.alm, 160, _times([0.0]), f, nside_matvis=128)
    assert abs(flux_scale_check(obs, gaussian_beam(14.0))["ratio"] - 0.741) < 0.01
    truth = _maps(twin.alm, 160, nside=128)  # the check against the twin's own sky: its true scale, 1
    assert abs(flux_scale_check(obs, gaussian_beam(14.0), sky=truth, nside=64)["ratio"] - 1) < TOL
    from gcrsky.sphere.modes import realify, unrealify

    full = np.atleast_2d(unrealify(twin.alm, 160))  # healpy order, m-major
    ell, m = hp.Alm.getlm(LMAX)
    cut = realify(np.ascontiguousarray(full[:, hp.Alm.getidx(160, ell, m)]), LMAX)
    obs16 = _simulate(cut, LMAX, _times([0.0]), f, nside_matvis=64)
    assert abs(flux_scale_check(obs16, gaussian_beam(14.0))["ratio"] - 0.925) < 0.01


def test_the_predicted_spread_of_one_times_ratio_matches_twin_like_skies():
    """``model_rel_sd`` (:func:`gcrsky.model.fluxscale.unresolved_variance`) against 12 skies made as the twins' are.

    Each sky is the GSM's l <= 16 plus ``sky_truth``'s isotropic extension to l = 160 (seeds
    1-12); at six LSTs 4 h apart (independent patches) the extension's share of the autos over
    the check's GSM model, divided by the predicted relative sd, has unit sd over the 72
    samples (their rms: the expectation is 0): measured 0.92 (+-0.08 expected from 72
    samples; tolerance 3 sigma), per LST 0.80-1.05 over 12 seeds (tolerance 0.5-1.6; the
    control below: 0.12-1.43).  The spread depends on the LST (0.016 with the Galactic centre
    in the beam, 0.22 at the H1C LST): the negative control, one LST-independent sd (their
    mean), is caught per LST, an extension twice as bright overall.
    """
    import types

    from gcrsky.checks.matvis import HERA_SITE, site
    from gcrsky.model.fluxscale import model_autos, unresolved_variance
    from gcrsky.sim.sky import sky_truth
    from gcrsky.sphere.modes import realify, unrealify

    f, beam = FREQS[1:2], gaussian_beam(14.0)
    t = _times(4.0 * np.arange(6))
    obs = types.SimpleNamespace(freqs_hz=f, times_jd=t.jd, n_times=t.size, n_freqs=1, location=site(*HERA_SITE))
    gsm = model_autos(obs, beam)[0]
    rel_sd = np.sqrt(unresolved_variance(f, beam))[0] / gsm  # (Nt,)
    ell = hp.Alm.getlm(160)[0]
    z = []
    for seed in range(1, 13):
        full = np.atleast_2d(unrealify(sky_truth(f, 160, source="pyradiosky", extend_seed=seed).alm, 160))
        ext = realify(np.where(ell > LMAX, full, 0), 160)  # the extension alone
        z.append(model_autos(obs, beam, sky=_maps(ext, 160, 128), nside=64)[0] / gsm / rel_sd)
    z = np.array(z)  # (seeds, Nt), expectation 0 (no monopole above l = 16)

    def rms(x, axis=None):
        return np.sqrt(np.mean(x**2, axis=axis))

    assert abs(rms(z) - 1) < 0.25 and np.all((rms(z, 0) > 0.5) & (rms(z, 0) < 1.6))
    assert abs(rms(2 * z) - 1) > 0.25  # an extension twice as bright
    one = z * rel_sd / rel_sd.mean()  # one sd for every LST
    assert not np.all((rms(one, 0) > 0.5) & (rms(one, 0) < 1.6))
