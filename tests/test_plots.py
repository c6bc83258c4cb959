"""Figure functions (gcrsky.paper.figures) and the slice helpers they rely on (gcrsky.paper.metrics).

Synthetic, small inputs only (random draws at lmax 6, maps at nside 16/32): every
figure function must write a PNG that reads back as a real, non-blank image.
``ring_slice`` is checked against healpy's ring geometry, ``moving_average``
against hand computations.
"""

from __future__ import annotations

import healpy as hp
import numpy as np
import pytest

from gcrsky.paper import figures as P
from gcrsky.paper import metrics as M
from gcrsky.sphere import alm_to_map, mode_table, n_params, posterior_maps

LMAX = 6
LAT = -30.7215
FWHM = 12.3


def _check_png(path, min_px=200):
    """The file exists and is a non-trivial image (size, not blank, several colours)."""
    import matplotlib.image as mpimg

    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[2] in (3, 4)
    h, w = img.shape[:2]
    assert h >= min_px and w >= min_px, (h, w)
    rgb = img[..., :3]
    assert float(rgb.std()) > 0.02
    colours = np.unique((rgb.reshape(-1, 3) * 255).round().astype(np.uint8), axis=0)
    assert colours.shape[0] > 20, colours.shape
    return img


@pytest.fixture(scope="module")
def synth():
    """Random draws around a random truth at lmax 6, and a positive sky at nside 16."""
    rng = np.random.default_rng(7)
    mt = mode_table(LMAX)
    n = n_params(LMAX)
    truth = rng.normal(size=n) * 5.0 / (1.0 + mt.ell)
    truth[0] = 100.0  # a monopole keeps the sky positive
    mix = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    draws = truth + 0.1 * np.abs(truth) * (rng.normal(size=(300, n)) @ mix.T)
    nside = 16
    truth_map = alm_to_map(truth, LMAX, nside)
    mean_map, std_map = posterior_maps(draws, LMAX, nside)
    return dict(mt=mt, truth=truth, draws=draws, nside=nside, truth_map=truth_map, mean_map=mean_map, std_map=std_map)


# ---------------------------------------------------------------- maps helpers


@pytest.mark.parametrize("nside, dec", [(16, LAT), (32, LAT), (32, 0.0), (16, 70.0), (32, -88.0)])
def test_ring_slice_matches_healpy(nside, dec):
    rng = np.random.default_rng(1)
    m = rng.normal(size=hp.nside2npix(nside))
    ra, vals = M.ring_slice(m, nside, dec)
    ring, ring_dec, pix = M.nearest_ring(nside, dec)
    start, npix_ring, costheta, _, _ = hp.ringinfo(nside, np.array([ring]))
    assert ra.shape == vals.shape == (int(npix_ring[0]),)
    # every pixel of that ring, and only those
    theta, phi = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    on_ring = np.flatnonzero(np.isclose(np.cos(theta), costheta[0], rtol=0, atol=1e-12))
    assert np.array_equal(np.sort(on_ring), np.sort(pix))
    np.testing.assert_allclose(90.0 - np.rad2deg(theta[on_ring]), ring_dec, atol=1e-9)
    # the ring is the nearest one in declination
    all_dec = 90.0 - np.rad2deg(np.arccos(hp.ringinfo(nside, np.arange(1, 4 * nside))[2]))
    assert abs(ring_dec - dec) <= np.min(np.abs(all_dec - dec)) + 1e-12
    # sorted RA in [0, 360), values are the map's at those pixels
    assert np.all(np.diff(ra) > 0) and ra.min() >= 0 and ra.max() < 360
    ipix = hp.ang2pix(nside, np.deg2rad(90.0 - ring_dec), np.deg2rad(ra))
    np.testing.assert_array_equal(vals, m[ipix])
    np.testing.assert_allclose(np.rad2deg(phi[ipix]), ra, atol=1e-9)


def test_ring_slice_rejects_wrong_size():
    with pytest.raises(ValueError):
        M.ring_slice(np.zeros(100), 16, 0.0)


def test_moving_average_by_hand():
    y = np.array([1.0, 2.0, 4.0, 8.0, 16.0])
    one = M.moving_average(y, 3, passes=1)
    hand = np.array([(16 + 1 + 2) / 3, (1 + 2 + 4) / 3, (2 + 4 + 8) / 3, (4 + 8 + 16) / 3, (8 + 16 + 1) / 3])
    np.testing.assert_allclose(one, hand)
    two = M.moving_average(y, 3)  # default: a pair of filters
    hand2 = np.array([(hand[-1] + hand[0] + hand[1]) / 3] + [hand[i - 1 : i + 2].mean() for i in range(1, 4)]
                     + [(hand[3] + hand[4] + hand[0]) / 3])
    np.testing.assert_allclose(two, hand2)
    trunc = M.moving_average(y, 3, passes=1, circular=False)
    np.testing.assert_allclose(trunc, [1.5, 7 / 3, 14 / 3, 28 / 3, 12.0])
    # identity cases, mean preserved on a circle, constant kept, axis = last
    np.testing.assert_array_equal(M.moving_average(y, 1), y)
    np.testing.assert_array_equal(M.moving_average(y, 5, passes=0), y)
    rng = np.random.default_rng(3)
    z = rng.normal(size=(2, 64))
    sm = M.moving_average(z, 7)
    np.testing.assert_allclose(sm.mean(axis=-1), z.mean(axis=-1))
    np.testing.assert_allclose(sm[1], M.moving_average(z[1], 7))
    np.testing.assert_allclose(M.moving_average(np.full(10, 3.0), 5), 3.0)
    with pytest.raises(ValueError):
        M.moving_average(y, 4)
    with pytest.raises(ValueError):
        M.moving_average(y, 0)


# ---------------------------------------------------------------- figures


def test_plot_alm_residuals(synth, tmp_path):
    mt = synth["mt"]
    z = M.mode_z_scores(synth["draws"], synth["truth"])
    z[3] = 40.0  # one outlier beyond the 15 sigma clip
    out = P.plot_alm_residuals(z, mt.ell, mt.m, mt.is_imag, tmp_path / "fig3.png", title="t")
    assert out == str(tmp_path / "fig3.png")
    _check_png(out)


def test_plot_sky_maps(synth, tmp_path):
    out = P.plot_sky_maps(synth["truth_map"], synth["mean_map"], synth["std_map"], tmp_path / "sub" / "fig4.png",
                          region=(LAT, FWHM, (0.0, 120.0)), title="t")
    _check_png(out, min_px=400)


def test_plot_beam_region(synth, tmp_path):
    frac = M.frac_diff_map(synth["mean_map"], synth["truth_map"])
    out = P.plot_beam_region(frac, tmp_path / "fig5.png", centre_dec_deg=LAT, fwhm_deg=FWHM, ra_range_deg=(240, 360))
    _check_png(out)


def test_plot_frac_slices(synth, tmp_path):
    nside = 32
    ra, dec = M.pixel_radec_deg(nside)
    rng = np.random.default_rng(5)

    def fake(start, width):
        ring_ra, _ = M.ring_slice(np.zeros(ra.size), nside, LAT)
        inside = M.ra_in_range(ring_ra, (start, start + width))
        return ring_ra, np.where(inside, 0.03, 0.3) * (1 + 0.3 * rng.random(ring_ra.size))

    # Fig. 8: runs with their own RA ranges (C2; C3 up to 360; C5 wider than the reference)
    curves = [("standard", *fake(0, 120)), ("A1", *fake(0, 120)), ("C2", *fake(120, 120), (120, 240)),
              ("C3", *fake(240, 120), (240, 360)), ("C5", *fake(0, 240), (0, 240))]
    out = P.plot_frac_slices(curves, tmp_path / "fig8.png", fwhm_deg=FWHM, ra_range_deg=(0, 120), window=3,
                             title="t", dec_deg=LAT)
    _check_png(out)
    # a reference range that ends at RA 360 (LST 16-24 h), log scale
    out = P.plot_frac_slices([("C3", *fake(240, 120))], tmp_path / "wrap.png", fwhm_deg=FWHM,
                             ra_range_deg=(240, 360), ra_limits=(200, 400), yscale="log")
    _check_png(out)
    with pytest.raises(ValueError):
        P.plot_frac_slices([("bad", np.zeros(3))], tmp_path / "bad.png", fwhm_deg=FWHM, ra_range_deg=(0, 120))


def test_plot_correlation_matrix(synth, tmp_path):
    mt = synth["mt"]
    draws = synth["draws"].copy()
    draws[:, 1] = 2.0  # a mode with no spread: drawn grey, no crash
    out = P.plot_correlation_matrix(draws, mt.ell, mt.m, mt.is_imag, tmp_path / "fig7_corr.png", zoom_lmax=3)
    _check_png(out)
    # a large lmax shows l <= max_lmax only (H1C's lmax 145: 10^4 rows, 3.6 GB for the whole matrix)
    out = P.plot_correlation_matrix(draws, mt.ell, mt.m, mt.is_imag, tmp_path / "fig7_cut.png", zoom_lmax=2,
                                    max_lmax=4)
    _check_png(out)


def test_plot_corner(synth, tmp_path):
    mt = synth["mt"]
    out = P.plot_corner(synth["draws"], synth["truth"], mt.ell, mt.m, mt.is_imag, tmp_path / "fig7_corner.png")
    _check_png(out)  # default ells clipped to lmax 6: (2, 5, 6)
    out = P.plot_corner(synth["draws"][:20], synth["truth"], mt.ell, mt.m, mt.is_imag, tmp_path / "c0.png",
                        m_value=0, ells=[1, 3], title="t")
    _check_png(out)
    with pytest.raises(ValueError):
        P.plot_corner(synth["draws"], synth["truth"], mt.ell, mt.m, mt.is_imag, tmp_path / "x.png", ells=[1])
