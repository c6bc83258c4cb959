"""A prior for the whole band: the GSM C_l table over 30-250 MHz, its accuracy, and the GSM prior mean.

References are independent of the table: C_l recomputed from the GSM map at held-out
frequencies (``gcrsky.sim.sky.gsm_cl_table(freqs_hz=...)``), the map's power-law extension
fitted without the map's end channels against those channels, and the GSM map itself for
the prior mean.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyradiosky")

from gcrsky.model.gsmsky import gsm_maps, gsm_source_maps, powerlaw_extrapolate  # noqa: E402
from gcrsky.model.skyprior import (  # noqa: E402
    check_gsm_cl_frequencies,
    gsm_cl,
    gsm_cl_range_hz,
    gsm_prior_mean,
)
from gcrsky.sim.sky import GSM_CL_TABLE_FREQS_HZ, _map_to_alm, gsm_cl_table  # noqa: E402


def test_table_covers_30_to_250_mhz_and_is_the_maps_spectrum():
    lo, hi = gsm_cl_range_hz()
    assert lo <= 30e6 and hi >= 250e6
    f = np.array(GSM_CL_TABLE_FREQS_HZ)[[0, 6, -1]]  # 30 MHz, a map channel (72 MHz), 250 MHz
    _, cl = gsm_cl_table(16, f)  # recomputed from the map now, not read from the shipped file
    np.testing.assert_allclose(gsm_cl(f, 16), cl, rtol=1e-10)
    for bad in (25e6, 260e6):
        with pytest.raises(ValueError, match="GSM C_l table covers 30-250 MHz.*--freq-range"):
            check_gsm_cl_frequencies([100e6, bad])


@pytest.mark.parametrize("f_mhz", [37.4, 47.4, 66.4, 133.2, 154.9, 175.0, 245.0])
def test_interpolation_between_table_channels(f_mhz):
    """Log-log interpolation between table channels vs the map's C_l at that frequency: < 1.5 % (measured 1.2 %
    at 47.4 MHz and 0.9 % at 154.9 MHz, where the interpolated map's spectrum bends into the fitted power law;
    < 1e-4 elsewhere)."""
    f = np.array([f_mhz * 1e6])
    assert not np.any(np.isclose(f[0], GSM_CL_TABLE_FREQS_HZ, rtol=1e-3))  # held out: not a table channel
    _, ref = gsm_cl_table(16, f)
    err = np.abs(gsm_cl(f, 16) / ref - 1).max()
    assert err < 0.015


@pytest.mark.parametrize("hold, bound", [([9], 0.03), ([0], 0.05), ([8, 9], 0.04), ([0, 1], 0.07)])
def test_extension_predicts_held_out_end_channels(hold, bound):
    """The extension beyond 50-150 MHz (per-pixel power laws) fitted without the map's end channels predicts their
    C_l (l <= 16) to the measured 2.7 % (150 MHz), 4.3 % (50 MHz), 2.4/3.5 % (139/150 MHz), 2.8/6.1 % (61/50 MHz),
    bounds a little above; the error grows with the distance extrapolated (~10 % expected at 250 MHz), which a
    prior variance (an order of magnitude) tolerates."""
    import healpy as hp

    f, maps, _, _ = gsm_source_maps()
    keep = [i for i in range(f.size) if i not in hold]
    pred = powerlaw_extrapolate(f[keep], maps[keep], f[hold])
    for k, h in enumerate(hold):
        cp, ct = hp.alm2cl(_map_to_alm(pred[k], 16)), hp.alm2cl(_map_to_alm(maps[h], 16))
        assert np.abs(cp / ct - 1).max() < bound


def test_table_is_steep_in_frequency_negative_control():
    """A flat extension (the 150 MHz spectrum reused at 250 MHz) would be wrong by ~(250/150)^-5: the table is not."""
    c150, c250 = gsm_cl([150e6, 250e6], 4)
    ratio = c250[0] / c150[0]
    assert 0.02 < ratio < 0.2  # synchrotron, T ~ nu^-2.5, C_l ~ nu^-5: 0.078
    assert np.all(gsm_cl([30e6], 4) > gsm_cl([50e6], 4))


def test_gsm_prior_mean_is_the_gsm_map():
    """The mean's map at l <= 16 is the GSM smoothed: positive everywhere, exact monopole, correlated > 0.95 with the
    map; a zero mean (the negative control) leaves the unobserved sky at 0 +- the prior, i.e. half negative."""
    import healpy as hp

    from gcrsky.sphere.modes import unrealify

    freqs = np.array([60e6, 180e6])
    lmax = 20
    a = gsm_prior_mean(freqs, lmax)
    assert a.shape == (2, (lmax + 1) ** 2)
    maps, nside = gsm_maps(freqs)
    alm = unrealify(a, lmax)
    ell = hp.Alm.getlm(lmax)[0]
    assert np.all(alm[:, ell > 16] == 0)
    for k in range(2):
        np.testing.assert_allclose(alm[k, 0].real, np.sqrt(4 * np.pi) * maps[k].mean(), rtol=1e-12)
        m = hp.alm2map(alm[k], nside)
        assert np.all(m > 0)
        assert np.corrcoef(m, maps[k])[0, 1] > 0.95
    rng = np.random.default_rng(0)
    cl = gsm_cl(freqs[:1], lmax)[0]
    draw = hp.alm2map(_zero_mean_draw(cl, lmax, rng), nside)
    assert np.mean(draw < 0) > 0.3


def _zero_mean_draw(cl, lmax, rng):
    """A draw of the zero-mean isotropic prior (complex healpy alm)."""
    import healpy as hp

    ell, m = hp.Alm.getlm(lmax)
    z = rng.standard_normal(ell.size) + 1j * np.where(m > 0, rng.standard_normal(ell.size), 0.0)
    return z * np.sqrt(cl[ell] / np.where(m > 0, 2.0, 1.0))


def test_prior_mean_out_of_band_refused():
    with pytest.raises(ValueError, match="30-250 MHz"):
        gsm_prior_mean([300e6], 4)
