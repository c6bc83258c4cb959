"""Tests of gcrsky.paper.metrics: beam-region masks, posterior maps and accuracy metrics.

All synthetic, NumPy-only and fast: masks are checked against the sphere's
geometry (ring declinations, band areas), metrics against maps with known answers.
"""

from __future__ import annotations

import healpy as hp
import numpy as np
import pytest

from gcrsky.paper import metrics as M
from gcrsky.sphere import alm_to_map, n_params, posterior_maps

LAT = -30.7215


# ---------------------------------------------------------------- geometry


def test_pixel_radec_ranges():
    ra, dec = M.pixel_radec_deg(8)
    assert ra.shape == dec.shape == (hp.nside2npix(8),)
    assert ra.min() >= 0 and ra.max() < 360
    assert -90 < dec.min() < -80 and 80 < dec.max() < 90
    # RING order: declination never increases along the pixel index
    assert np.all(np.diff(dec) <= 1e-12)


@pytest.mark.parametrize(
    "rng, inside, outside",
    [
        ((0.0, 120.0), [0.0, 60.0, 120.0], [120.5, 359.5, 200.0]),
        ((330.0, 30.0), [330.0, 359.9, 0.0, 15.0, 30.0], [31.0, 329.0, 180.0]),  # wraps through 0
        ((330.0, 390.0), [330.0, 0.0, 30.0], [31.0, 329.0]),  # same range, unwrapped
        ((-30.0, 30.0), [330.0, 0.0, 30.0], [31.0, 329.0]),
        ((0.0, 360.0), [0.0, 90.0, 359.99], []),  # whole circle
    ],
)
def test_ra_in_range(rng, inside, outside):
    assert M.ra_in_range(np.array(inside), rng).all()
    if outside:
        assert not M.ra_in_range(np.array(outside), rng).any()


@pytest.mark.parametrize("nside", [16, 64, 128])
@pytest.mark.parametrize("dec", [LAT, 0.0, 45.0, -80.0])
def test_nearest_ring_is_nearest(nside, dec):
    ring, ring_dec, pix = M.nearest_ring(nside, dec)
    _, pdec = M.pixel_radec_deg(nside)
    # every pixel of the ring sits at the ring's declination ...
    np.testing.assert_allclose(pdec[pix], ring_dec, atol=1e-10)
    # ... and no pixel anywhere is closer to the requested declination
    assert np.abs(ring_dec - dec) <= np.min(np.abs(pdec - dec)) + 1e-12
    # ... so it is within half the local ring spacing
    rings = np.unique(np.round(pdec, 10))
    k = np.searchsorted(rings, ring_dec - 1e-9)
    spacing = np.diff(rings)[min(k, rings.size - 2)]
    assert abs(ring_dec - dec) <= 0.5 * max(spacing, np.diff(rings)[max(k - 1, 0)]) + 1e-9
    assert pix.size == hp.ringinfo(nside, np.array([ring]))[1][0]


def test_centre_ring_of_the_standard_case():
    """nside 128: the ring nearest the HERA latitude is within ~0.23 deg of it."""
    reg = M.beam_region_masks(128, LAT, 12.6, (0.0, 120.0))
    assert abs(reg.centre_ring_dec_deg - LAT) < 0.5 * 0.4581  # ring spacing near dec -30 at nside 128
    ra, dec = M.pixel_radec_deg(128)
    assert np.allclose(dec[reg.centre], reg.centre_ring_dec_deg)
    # a ring of 4 nside = 512 pixels: 120 deg of it is 1/3 (+ the endpoint pixel when it lands on RA 0/120)
    assert 512 // 3 <= reg.centre.sum() <= 512 // 3 + 2
    assert np.all(ra[reg.centre] <= 120.0 + 1e-9)
    # the centre ring lies inside the band
    assert np.all(reg.fwhm[reg.centre])


@pytest.mark.parametrize(
    "centre, fwhm, rng",
    [(LAT, 12.62, (0.0, 120.0)), (LAT, 57.3, (0.0, 120.0)), (10.0, 5.0, (300.0, 60.0)), (0.0, 20.0, (0.0, 360.0))],
)
def test_band_pixel_count_matches_area(centre, fwhm, rng):
    """The band's pixel count is its solid angle / pixel area (HEALPix pixels are equal-area)."""
    nside = 128
    reg = M.beam_region_masks(nside, centre, fwhm, rng)
    lo, hi = max(centre - fwhm, -90.0), min(centre + fwhm, 90.0)
    width = 360.0 if rng[1] - rng[0] >= 360 else (rng[1] - rng[0]) % 360.0
    frac_area = (np.sin(np.deg2rad(hi)) - np.sin(np.deg2rad(lo))) / 2.0 * width / 360.0
    expected = frac_area * hp.nside2npix(nside)
    assert reg.fwhm.sum() == pytest.approx(expected, rel=0.02)
    ra, dec = M.pixel_radec_deg(nside)
    assert np.all(np.abs(dec[reg.fwhm] - centre) <= fwhm)
    # nothing just outside the band in declination (within the RA range) is selected
    assert not np.any(reg.fwhm & (np.abs(dec - centre) > fwhm))
    assert np.array_equal(reg.fwhm, reg.fwhm & reg.ra)


def test_masks_reject_bad_geometry():
    with pytest.raises(ValueError, match="fwhm"):
        M.beam_region_masks(16, LAT, 0.0, (0, 120))
    with pytest.raises(ValueError, match="centre_dec"):
        M.beam_region_masks(16, 95.0, 10.0, (0, 120))


# ---------------------------------------------------------------- metrics


def _truth_map(nside=64, seed=1):
    """A positive, structured sky (K): 1000 K + a smooth random field."""
    rng = np.random.default_rng(seed)
    lmax = 10
    a = rng.normal(size=n_params(lmax)) * 50.0
    a[0] = 1000.0 * np.sqrt(4 * np.pi)
    m = alm_to_map(a, lmax, nside)
    assert m.min() > 0
    return m


def test_metrics_uniform_five_percent():
    truth = _truth_map()
    mean = truth * 1.05
    out = M.summary_metrics(mean, truth, LAT, 12.6, (0.0, 120.0))
    for region in ("centre", "fwhm", "sky"):
        assert out[f"frac_diff_{region}_median"] == pytest.approx(0.05, rel=1e-12)
        assert out[f"frac_diff_{region}_p90"] == pytest.approx(0.05, rel=1e-12)
        assert out[f"frac_diff_{region}_max"] == pytest.approx(0.05, rel=1e-12)
        assert out[f"frac_diff_{region}_within_10pct"] == 1.0
    assert out["frac_diff_centre_npix"] == M.beam_region_masks(64, LAT, 12.6, (0.0, 120.0)).centre.sum()


def test_metrics_distinguish_regions():
    """Centre ring 1%, rest of the band 3%, outside the band 50%: each summary sees its own."""
    nside = 64
    truth = _truth_map(nside)
    reg = M.beam_region_masks(nside, LAT, 12.6, (0.0, 120.0))
    frac = np.full(truth.size, 0.5)
    frac[reg.fwhm] = -0.03  # sign must not matter
    frac[reg.centre] = 0.01
    out = M.summary_metrics(truth * (1 + frac), truth, LAT, 12.6, (0.0, 120.0))
    assert out["frac_diff_centre_median"] == pytest.approx(0.01)
    assert out["frac_diff_centre_max"] == pytest.approx(0.01)
    assert out["frac_diff_fwhm_median"] == pytest.approx(0.03)
    assert out["frac_diff_fwhm_max"] == pytest.approx(0.03)
    assert out["frac_diff_fwhm_within_5pct"] == 1.0
    assert out["frac_diff_sky_max"] == pytest.approx(0.5)
    assert out["frac_diff_sky_within_10pct"] == pytest.approx(reg.fwhm.mean())


def test_metrics_percentiles_and_fractions():
    """Band values 0..0.198 in equal steps: median, p90 and within-x fractions are known."""
    nside = 64
    truth = _truth_map(nside)
    reg = M.beam_region_masks(nside, LAT, 12.6, (0.0, 120.0))
    idx = np.flatnonzero(reg.fwhm)
    vals = np.linspace(0.0, 0.198, idx.size)
    frac = np.zeros(truth.size)
    frac[idx] = vals
    out = M.summary_metrics(truth * (1 + frac), truth, LAT, 12.6, (0.0, 120.0))
    assert out["frac_diff_fwhm_median"] == pytest.approx(np.median(vals), rel=1e-9)
    assert out["frac_diff_fwhm_p90"] == pytest.approx(np.percentile(vals, 90), rel=1e-9)
    assert out["frac_diff_fwhm_within_10pct"] == pytest.approx(np.mean(vals <= 0.1), abs=2 / idx.size)
    assert out["frac_diff_fwhm_within_5pct"] == pytest.approx(np.mean(vals <= 0.05), abs=2 / idx.size)


def test_metrics_with_std_map_and_zero_truth():
    truth = _truth_map(32)
    mean = truth + 2.0
    std = np.full(truth.size, 4.0)
    out = M.summary_metrics(mean, truth, LAT, 12.6, (0.0, 120.0), std_map=std)
    assert out["zmap_fwhm_rms"] == pytest.approx(0.5)
    assert out["zmap_fwhm_max_abs"] == pytest.approx(0.5)
    fd = M.frac_diff_map(np.ones(3), np.array([1.0, 0.0, 2.0]))
    assert np.isnan(fd[1]) and fd[0] == 0.0 and fd[2] == -0.5


def test_posterior_maps_mean_and_std():
    """Chunked std map equals the std of the draws' maps computed directly."""
    rng = np.random.default_rng(3)
    lmax, nside, nd = 4, 8, 7
    draws = rng.normal(size=(2, nd, n_params(lmax)))
    mean_map, std_map = posterior_maps(draws, lmax, nside, chunk=3)
    direct = alm_to_map(draws, lmax, nside)  # (2, nd, npix)
    np.testing.assert_allclose(mean_map, direct.mean(axis=1), atol=1e-12)
    np.testing.assert_allclose(std_map, direct.std(axis=1, ddof=1), atol=1e-12)
    assert mean_map.shape == std_map.shape == (2, hp.nside2npix(nside))
    # lmax inferred from n
    m2, s2 = posterior_maps(draws[0], nside=nside)
    np.testing.assert_allclose(m2, mean_map[0], atol=1e-12)


def test_mode_z_scores():
    truth = np.array([[1.0, 2.0, 0.0, -1.0]])
    draws = np.stack([truth + 1.0, truth + 3.0], axis=1)  # mean = truth + 2, std (ddof 1) = sqrt(2)
    z = M.mode_z_scores(draws, truth)
    np.testing.assert_allclose(z, 2.0 / np.sqrt(2.0))
    # zero spread -> NaN, not inf
    z0 = M.mode_z_scores(np.stack([truth, truth], axis=1), truth + 1)
    assert np.isnan(z0).all()
    st = M.z_score_stats(np.array([0.5, -1.5, 2.5, np.nan]))
    assert st["n"] == 3 and st["max_abs"] == 2.5
    assert st["within_1"] == pytest.approx(1 / 3) and st["within_2"] == pytest.approx(2 / 3)
