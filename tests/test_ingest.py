"""Reading visibility files: conventions, selections, noise, flags and errors (gcrsky.ingest.uvdata).

Every file here is written by pyuvdata from a matvis simulation (gcrsky.checks.uvsim), then
rewritten in the variants the ingest must read the same: another conjugation of every
baseline, a projected phase centre, K str instead of Jy, the "avg" instead of the "sum"
polarisation convention.  Each variant must give the *same* Problem as the original (data
and noise to rounding: these are exact conversions), which pins the conventions without
any tolerance for the simulators' disagreement.  The forward model against the file's
noiseless visibilities, the posterior against the truth, and the polarisation products are
checked in ``tests/test_ingest_physics.py``.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

pytest.importorskip("matvis")

from gcrsky.base.units import kelvin_sr_to_jy  # noqa: E402
from gcrsky.checks.matvis import HERA_SITE, observing_times, random_sky, site  # noqa: E402
from gcrsky.checks.uvsim import simulate_uvdata  # noqa: E402
from gcrsky.ingest import from_uvdata, inspect_uvdata  # noqa: E402
from gcrsky.instrument import gaussian_beam, hex_array  # noqa: E402
from gcrsky.model import gsm_cl  # noqa: E402

LMAX, NSIDE = 6, 32
FREQS = np.array([100e6, 101e6])


@pytest.fixture(scope="module")
def sim():
    """7-antenna hexagon, 14 m Gaussian dishes, 6 integrations over 3 h, 2 channels, xx and yy."""
    loc = site(*HERA_SITE)
    times = observing_times("2025-03-21T18:00:00", 3.0, 6)
    return simulate_uvdata(hex_array((2, 3, 2)), loc, times, FREQS, gaussian_beam(14.0), random_sky(LMAX, 1),
                           LMAX, nside_matvis=NSIDE, dt_s=10.0, dnu_hz=1e5, noise_seed=0)


def _problem(uvd, **kw):
    kw.setdefault("pol", "pI")
    return from_uvdata(uvd, lmax=LMAX, nside=NSIDE, beam=gaussian_beam(14.0), compress=False, **kw)


@pytest.fixture(scope="module")
def base(sim):
    return _problem(sim.uvdata)


def _same(p, q, rtol=1e-12):
    np.testing.assert_array_equal(np.asarray(p.antpairs), np.asarray(q.antpairs))
    np.testing.assert_allclose(np.asarray(p.data), np.asarray(q.data), rtol=rtol, atol=rtol * float(
        np.abs(np.asarray(q.data)).max()))
    np.testing.assert_allclose(np.asarray(p.sigma), np.asarray(q.sigma), rtol=rtol)
    np.testing.assert_array_equal(np.asarray(p.weights), np.asarray(q.weights))


def test_conversions_and_shapes(sim, base):
    """pI = V_xx + V_yy (sum convention, I-equivalent), Jy -> K sr, canonical pairs i < j, noise from autos."""
    uvd = sim.uvdata
    assert base.data.shape == (2, 6, 21) and base.pols == ("pI",) * 21
    assert np.all(np.asarray(base.antpairs)[:, 0] < np.asarray(base.antpairs)[:, 1])
    i, j = (int(x) for x in np.asarray(base.antpairs)[4])
    want = (uvd.get_data((i, j, "xx")) + uvd.get_data((i, j, "yy"))) / kelvin_sr_to_jy(FREQS)[None, :]
    np.testing.assert_allclose(np.asarray(base.data)[:, :, 4], want.T, rtol=1e-12)
    # radiometer noise from the file's own autos: sigma^2 = sum_p |V_ii,pp V_jj,pp| / (2 dt dnu N)
    var = sum(np.abs(uvd.get_data((i, i, p)).real * uvd.get_data((j, j, p)).real) for p in ("xx", "yy")) / (2 * 10.0 * 1e5)
    np.testing.assert_allclose(np.asarray(base.sigma)[:, :, 4], np.sqrt(var).T / kelvin_sr_to_jy(FREQS)[:, None],
                               rtol=1e-12)
    assert np.all(np.asarray(base.weights) == 1.0)
    assert base.config.conventions["vis_units"] == "Jy" and base.config.noise == "autos"
    json.dumps(base.config.to_dict())  # the record is JSON-friendly


def test_single_products_carry_the_sum_conventions_factor(sim, base):
    xx = _problem(sim.uvdata, pol="xx")
    i, j = (int(x) for x in np.asarray(xx.antpairs)[3])
    want = 2 * sim.uvdata.get_data((i, j, "xx")) / kelvin_sr_to_jy(FREQS)[None, :]  # a feed sees I/2
    np.testing.assert_allclose(np.asarray(xx.data)[:, :, 3], want.T, rtol=1e-12)
    joint = _problem(sim.uvdata, pol=("xx", "yy"))
    assert joint.pols == ("xx",) * 21 + ("yy",) * 21 and joint.data.shape[-1] == 42
    np.testing.assert_allclose(np.asarray(joint.data)[:, :, :21], np.asarray(xx.data), rtol=1e-12)


@pytest.mark.parametrize("how", ["ant2<ant1", "ant1<ant2"])
def test_any_conjugation_reads_the_same(sim, base, how):
    uvd = sim.uvdata.copy()
    uvd.conjugate_bls(how)
    _same(_problem(uvd), base)


def test_a_projected_file_is_unprojected(sim, base, caplog):
    uvd = sim.uvdata.copy()
    uvd.phase(ra=1.0, dec=-0.5, cat_name="target", phase_frame="icrs")
    assert not np.allclose(uvd.data_array, sim.uvdata.data_array)  # the phasing changed the data
    with caplog.at_level("WARNING", logger="gcrsky.ingest.uvdata"):
        p = _problem(uvd)
    assert "unprojected" in caplog.text
    _same(p, base, rtol=1e-9)  # pyuvdata's phase / unphase round trip: 1e-9 relative (uvw rounding)
    assert "unprojected by pyuvdata" in p.config.conventions["phase"]


def test_k_str_and_avg_convention_read_the_same(sim, base):
    uvd = sim.uvdata.copy()
    uvd.data_array = uvd.data_array / kelvin_sr_to_jy(FREQS)[None, :, None]
    uvd.vis_units = "K str"
    _same(_problem(uvd), base)
    avg = sim.uvdata.copy()
    avg.data_array = 2.0 * avg.data_array  # I-equivalent products: pI = (xx + yy) / 2
    avg.pol_convention = "avg"
    _same(_problem(avg), base)


def test_flags_nsamples_and_missing_baselines(sim, base):
    uvd = sim.uvdata.copy()
    rng = np.random.default_rng(3)
    cross = uvd.ant_1_array != uvd.ant_2_array
    flags = (rng.random(uvd.flag_array.shape) < 0.2) & cross[:, None, None]
    uvd.flag_array = flags
    uvd.data_array = np.where(flags, np.nan, uvd.data_array)  # flagged NaNs must not poison anything
    ns = np.where(rng.random(uvd.nsample_array.shape) < 0.5, 2.0, 1.0)
    ns[5, 0, 0] = 0.0
    uvd.nsample_array = ns
    p = _problem(uvd, pol="xx")
    ref = _problem(sim.uvdata, pol="xx")
    w = np.asarray(p.weights)
    assert np.all(np.isfinite(np.asarray(p.data))) and 0.7 < w.mean() < 0.9
    # a flagged sample (or nsample 0) has weight 0; nsample N divides the variance by N
    i, j = (int(x) for x in np.asarray(p.antpairs)[2])
    rows = np.flatnonzero((uvd.ant_1_array == i) & (uvd.ant_2_array == j))
    bad = uvd.flag_array[rows, :, 0] | (uvd.nsample_array[rows, :, 0] == 0)
    np.testing.assert_array_equal(w[:, :, 2], (~bad).T.astype(float))
    good = ~bad.T
    ratio = np.asarray(p.sigma)[:, :, 2][good] / np.asarray(ref.sigma)[:, :, 2][good]
    np.testing.assert_allclose(ratio, 1.0 / np.sqrt(uvd.nsample_array[rows, :, 0].T[good]), rtol=1e-12)
    # missing baselines: only the pairs in the file become rows
    sub = sim.uvdata.select(bls=[(0, 1), (2, 5), (1, 6), (0, 0), (1, 1), (2, 2), (5, 5), (6, 6)], inplace=False)
    q = _problem(sub)
    assert [tuple(int(v) for v in x) for x in np.asarray(q.antpairs)] == [(0, 1), (1, 4), (2, 3)]  # antennas 0,1,2,5,6


def test_selections_read_only_what_is_asked(sim, tmp_path, base):
    path = tmp_path / "obs.uvh5"
    sim.uvdata.write_uvh5(str(path))
    p = from_uvdata(path, lmax=LMAX, nside=NSIDE, beam=gaussian_beam(14.0), compress=False, freq_chans=[1],
                    antennas=[0, 1, 2, 3], times_jd=np.unique(sim.uvdata.time_array)[:4])
    assert p.data.shape == (1, 4, 6) and float(p.freqs_hz[0]) == 101e6
    sel = from_uvdata(path, lmax=LMAX, nside=NSIDE, beam=gaussian_beam(14.0), compress=False,
                      bls=[(0, 1), (3, 4)])
    assert sel.data.shape[-1] == 2
    info = inspect_uvdata(path, lmax=LMAX)
    assert info["n_antennas"] == 7 and info["n_baselines"] == 21 and info["n_unique_baselines"] == 9
    assert info["has_autos"] and info["flagged_fraction"] == 0.0 and info["noise_sigma_median_k_sr"] > 0
    json.dumps(info)
    with pytest.raises(ValueError, match="channel"):
        from_uvdata(path, lmax=LMAX, nside=NSIDE, beam=gaussian_beam(14.0), freq_range_hz=(120e6, 130e6))


def test_redundant_compression_is_automatic_and_exact(sim, base):
    comp = from_uvdata(sim.uvdata, lmax=LMAX, nside=NSIDE, beam=gaussian_beam(14.0))
    assert comp.config.compressed and comp.data.shape[-1] == 9 < base.data.shape[-1]
    import gcrsky

    a = np.asarray(gcrsky.wiener_filter(base, method="cholesky"))
    b = np.asarray(gcrsky.wiener_filter(comp, method="cholesky"))
    np.testing.assert_allclose(np.asarray(comp.precision_matrix()), np.asarray(base.precision_matrix()), rtol=1e-12,
                               atol=1e-12 * float(np.abs(np.asarray(base.precision_matrix())).max()))
    # the same posterior: Wiener filters equal in posterior-sigma units (measured 3e-8: P's condition number
    # is 4e10 with the GSM prior, so the two factorisations round differently)
    sd = np.sqrt(np.stack([np.diag(np.linalg.inv(P)) for P in np.asarray(base.precision_matrix())]))
    assert np.max(np.abs(a - b) / sd) < 1e-6


def test_noise_from_time_differences(sim):
    """noise='diff' estimates a constant sigma per (channel, baseline) from the 5 time-adjacent pairs.

    On pure-noise data of known sigma each estimate has 10 degrees of freedom, so its median
    over the 42 (channel, baseline) estimates is sigma * sqrt(median(chi2_10) / 10) = 0.97 sigma
    (binomial spread of a 42-sample median: ~4%); 10% is the tolerance.
    """
    uvd = sim.uvdata.copy()
    rng = np.random.default_rng(5)
    s = 0.3  # Jy, per component
    uvd.data_array = s * (rng.standard_normal(uvd.data_array.shape) + 1j * rng.standard_normal(uvd.data_array.shape))
    p = from_uvdata(uvd, lmax=LMAX, nside=NSIDE, beam=gaussian_beam(14.0), pol="xx", noise="diff", compress=False)
    est = np.asarray(p.sigma) * kelvin_sr_to_jy(FREQS)[:, None, None] / 2.0  # back to one raw xx component, Jy
    assert abs(np.median(est) / s - 0.97) < 0.1, np.median(est) / s
    assert p.config.noise == "diff"
    with pytest.raises(ValueError, match="no autocorrelations"):
        from_uvdata(sim.uvdata.select(ant_str="cross", inplace=False), lmax=LMAX, nside=NSIDE,
                    beam=gaussian_beam(14.0))


def test_bad_input_is_refused_with_a_message(sim, tmp_path):
    uvd = sim.uvdata.copy()
    uvd.vis_units = "uncalib"
    uvd.pol_convention = None
    with pytest.raises(ValueError, match="uncalibrated"):
        _problem(uvd)
    with pytest.raises(ValueError, match="pol must be"):
        _problem(sim.uvdata, pol="I")
    with pytest.raises(ValueError, match="missing"):
        _problem(sim.uvdata.select(polarizations=["xx"], inplace=False), pol="pI")
    with pytest.raises(ValueError, match="dish_diameter_m"):
        from_uvdata(sim.uvdata, lmax=LMAX, nside=NSIDE)
    with pytest.raises(FileNotFoundError):
        from_uvdata(tmp_path / "nope.uvh5", lmax=LMAX, nside=NSIDE, dish_diameter_m=14.0)
    bad = sim.uvdata.copy()
    bad.data_array[3, 0, 0] = np.nan  # unflagged NaN: refused before anything is built, naming where
    with pytest.raises(ValueError, match=r"1 unflagged visibilities are not finite \(1 NaN, 0 Inf\), first xx at "
                                         r"channel 0 \(100.0000 MHz\), time 0, baseline 0-3"):
        _problem(bad, pol="xx")


def test_priors(sim, tmp_path):
    import healpy as hp

    from gcrsky.sim.sky import gsm_cl_table

    freqs, cl = gsm_cl_table()
    np.testing.assert_allclose(gsm_cl(freqs, 16), cl, rtol=1e-12)  # the shipped table is the map's spectrum
    p = _problem(sim.uvdata)
    np.testing.assert_allclose(1.0 / np.asarray(p.prior.inv_var)[:, 0], gsm_cl(FREQS, LMAX)[:, 0], rtol=1e-12)
    assert np.all(np.asarray(p.prior.mean) == 0.0) and "GSM" in p.config.prior
    clf = tmp_path / "cl.txt"
    np.savetxt(clf, np.stack([np.arange(LMAX + 1), 1.0 / (1.0 + np.arange(LMAX + 1)) ** 2], 1))
    q = _problem(sim.uvdata, prior=str(clf), prior_scale=4.0)
    np.testing.assert_allclose(1.0 / np.asarray(q.prior.inv_var)[0, 0], 4.0, rtol=1e-12)
    m = hp.alm2map(np.zeros(hp.Alm.getsize(LMAX), complex) + 0j, 16) + 7.0
    mf = tmp_path / "mean.fits"
    hp.write_map(str(mf), m)
    r = _problem(sim.uvdata, prior=str(mf))
    np.testing.assert_allclose(np.asarray(r.prior.mean)[:, 0], 7.0 * np.sqrt(4 * np.pi), rtol=1e-6)
    assert _problem(sim.uvdata, prior="flat").prior.inv_var.max() == 0.0
    with pytest.raises(ValueError, match="GSM C_l table covers"):
        gsm_cl([260e6], 4)


def test_ingest_is_jax_x64_only():
    from gcrsky.ingest import uvdata

    assert uvdata.from_uvdata.__module__ == "gcrsky.ingest.uvdata" and jax.config.jax_enable_x64
