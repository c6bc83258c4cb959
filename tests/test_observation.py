"""What a file says: ``gcrsky.io.read_observation`` against pyuvdata read directly.

References: pyuvdata's own accessors (``get_data``, ``get_flags``, ``get_nsamples``, which
conjugate a baseline stored in the other order and reverse its product), its metadata
(``time_array``, ``lst_array``, ``freq_array``, ``telescope``), and the radiometer
equation written out by hand.  Files:

* the real HERA H1C file ``zen.2458098.45361.HH_downselected.uvh5`` (8 antennas, 10
  integrations, 64 channels, ``ee``/``nn`` with x East, ``uncalib``): it must read, and
  building a Problem in physical units from it must be refused;
* the real HERA H2C file ``zen.2458432.34569.uvh5`` (4 antennas, xx/yy/xy/yx, 24 rows
  stored as (ant_2, ant_1), nsample 0 everywhere): it must read, every sample unusable;
* a small matvis simulation written by pyuvdata (``gcrsky.checks.uvsim``): the
  radiometer noise and ``problem_from_observation`` against ``from_uvdata``.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from conftest import H1C, H2C  # noqa: E402

from gcrsky.ingest import from_uvdata
from gcrsky.io import Observation, read_observation
from gcrsky.model import problem_from_observation, radiometer_variance
from gcrsky.model.observed import raw_variance


def _uvdata(path):
    from pyuvdata import UVData

    if not path.exists():
        pytest.skip(f"{path} is not here (the shared real-data folder)")
    return UVData.from_file(str(path))


@pytest.fixture(scope="module")
def h1c():
    return _uvdata(H1C)


@pytest.fixture(scope="module")
def h1c_obs(h1c):
    return read_observation(H1C)


def _check_against_pyuvdata(obs: Observation, uvd, pols):
    """Every grid cell of ``obs`` against pyuvdata's accessors (which conjugate as needed)."""
    for b, (ai, aj) in enumerate(obs.baseline_antnums):
        for k, p in enumerate(pols):
            key = (int(ai), int(aj), p)
            np.testing.assert_array_equal(obs.vis[k, :, :, b], uvd.get_data(key).T)
            np.testing.assert_array_equal(obs.flags[k, :, :, b], uvd.get_flags(key).T)
            np.testing.assert_array_equal(obs.nsamples[k, :, :, b], uvd.get_nsamples(key).T)
    for a, num in enumerate(obs.antenna_numbers):
        for k, p in enumerate(pols):
            np.testing.assert_array_equal(obs.autos[k, :, :, a], uvd.get_data((int(num), int(num), p)).T)


def test_real_h1c_file_reads_as_pyuvdata_says(h1c, h1c_obs):
    obs, uvd = h1c_obs, h1c
    assert obs.vis.shape == (2, 64, 10, 28) and obs.autos.shape == (2, 64, 10, 8)
    assert obs.antenna_numbers.tolist() == [0, 1, 11, 12, 13, 23, 24, 25]
    assert obs.antenna_names.tolist() == [f"HH{a}" for a in obs.antenna_numbers]
    assert np.all(obs.antpairs[:, 0] < obs.antpairs[:, 1]) and obs.present.all() and obs.auto_present.all()
    np.testing.assert_array_equal(obs.times_jd, np.unique(uvd.time_array))
    lst_of_time = {t: lst for t, lst in zip(uvd.time_array, uvd.lst_array)}
    np.testing.assert_array_equal(obs.lsts_rad, [lst_of_time[t] for t in obs.times_jd])
    assert 5.70 < obs.lst_hours.min() < obs.lst_hours.max() < 5.75  # the README's LST ~5.71-5.74 h
    np.testing.assert_array_equal(obs.freqs_hz, uvd.freq_array)
    np.testing.assert_array_equal(obs.channel_width_hz, np.full(64, 97656.25))
    np.testing.assert_array_equal(obs.integration_time_s, np.full((10, 28), uvd.integration_time[0]))
    nums = list(uvd.telescope.antenna_numbers)
    np.testing.assert_array_equal(obs.antpos_enu_m,
                                  uvd.telescope.get_enu_antpos()[[nums.index(a) for a in obs.antenna_numbers]])
    loc = uvd.telescope.location
    assert obs.location.x == loc.x and obs.location.y == loc.y and obs.location.z == loc.z
    assert obs.site_lat_lon_alt[0] == loc.lat.deg
    # the file's record, not converted
    assert obs.pol_names == ("xx", "yy") and obs.file_pol_names == ("ee", "nn") and obs.x_orientation == "east"
    assert (obs.vis_units, obs.pol_convention, obs.phase_type) == ("uncalib", None, "unprojected")
    assert obs.telescope_name == "HERA" and obs.telescope_antenna_numbers.size == 52
    assert obs.history.startswith("CORR-DACQ") and obs.nblts_read == 360 and obs.flagged_fraction == 0.0
    assert obs.vis.dtype == np.complex128 and uvd.data_array.dtype == np.complex64  # widened exactly
    _check_against_pyuvdata(obs, uvd, ("ee", "nn"))
    np.testing.assert_allclose(obs.baseline_lengths_m.min(), 14.6, atol=0.05)  # HERA's 14.6 m spacing


def test_uncalibrated_data_read_but_make_no_problem(h1c_obs):
    from gcrsky.instrument import gaussian_beam

    with pytest.raises(ValueError, match="uncalibrated"):
        problem_from_observation(h1c_obs, gaussian_beam(14.0), lmax=4, nside=16)


def test_a_baseline_stored_in_the_other_order_is_conjugated(h1c, h1c_obs):
    """The H1C file conjugated by pyuvdata (every row as (ant_2, ant_1)) reads the same, bit for bit."""
    uvd = h1c.copy()
    uvd.conjugate_bls("ant2<ant1")
    assert np.all(uvd.ant_1_array >= uvd.ant_2_array)
    obs = read_observation(uvd)
    assert obs.source == "<UVData object>"
    for f in ("vis", "flags", "nsamples", "autos", "antpairs", "antenna_numbers", "times_jd"):
        np.testing.assert_array_equal(getattr(obs, f), getattr(h1c_obs, f), err_msg=f)


def test_flags_and_absent_samples(h1c):
    uvd = h1c.copy()
    rng = np.random.default_rng(0)
    uvd.flag_array = rng.random(uvd.flag_array.shape) < 0.1
    gone = np.flatnonzero((uvd.ant_1_array == 11) & (uvd.ant_2_array == 23))[3]  # pair (11, 23) at one time
    uvd.select(blt_inds=np.delete(np.arange(uvd.Nblts), gone))
    obs = read_observation(uvd, pol="xx", freq_chans=np.arange(10, 20))
    assert obs.pol_names == ("xx",) and obs.n_freqs == 10 and obs.selection["freq_chans"] == list(range(10, 20))
    b = [tuple(x) for x in obs.baseline_antnums.tolist()].index((11, 23))
    assert obs.present.sum() == obs.present.size - 1 and not obs.present[3, b]
    assert np.all(obs.flags[:, :, 3, b]) and np.all(obs.vis[:, :, 3, b] == 0) and np.all(obs.nsamples[:, :, 3, b] == 0)
    keep = np.ones(obs.n_times, bool)
    keep[3] = False
    np.testing.assert_array_equal(obs.flags[0, :, keep, b], uvd.get_flags((11, 23, "ee"))[:, 10:20])
    cross = uvd.ant_1_array != uvd.ant_2_array
    assert obs.flagged_fraction == (uvd.flag_array[cross, 10:20, 0].sum() + 10) / obs.flags.size  # + the absent one


def test_real_h2c_file_reads_with_nsample_zero_everywhere():
    uvd = _uvdata(H2C)
    obs = read_observation(H2C)
    assert obs.pol_names == ("xx", "yy", "xy", "yx") and obs.x_orientation is None
    assert obs.vis.shape == (4, 64, 8, 6) and obs.antenna_numbers.tolist() == [0, 1, 12, 26]
    assert np.sum(uvd.ant_1_array > uvd.ant_2_array) == 24  # rows stored as (ant_2, ant_1): xy comes from yx
    _check_against_pyuvdata(obs, uvd, obs.pol_names)
    assert not obs.usable.any() and obs.flagged_fraction == 1.0 and obs.has_autos
    assert np.all(obs.nsamples == 0) and not obs.flags.any()  # unflagged, but with no samples
    with pytest.raises(ValueError, match="as the conjugate of yx, which is not read"):
        read_observation(uvd.select(polarizations=["xy"], inplace=False))


def test_a_sample_stored_twice_is_refused(h1c):
    uvd = h1c.copy()
    r1, r2 = np.flatnonzero((uvd.time_array == uvd.time_array[0]) & (uvd.ant_1_array != uvd.ant_2_array))[:2]
    uvd.ant_1_array[r2], uvd.ant_2_array[r2] = uvd.ant_2_array[r1], uvd.ant_1_array[r1]  # r1's pair, reversed
    with pytest.raises(ValueError, match=r"holds the baseline .* more than once \(stored in both orders\?\)"):
        read_observation(uvd)


# ---------------------------------------------------------------- a simulated file: noise and the Problem

LMAX, NSIDE = 4, 32  # nside 32: the quadrature resolves the fringes (reach ~93 <= 3 nside - 1)
FREQS = np.array([100e6, 101e6])


@pytest.fixture(scope="module")
def sim():
    pytest.importorskip("matvis")
    from gcrsky.checks.matvis import HERA_SITE, observing_times, random_sky, site
    from gcrsky.checks.uvsim import simulate_uvdata
    from gcrsky.instrument import gaussian_beam, hex_array

    times = observing_times("2025-03-21T18:00:00", 1.0, 3)
    return simulate_uvdata(hex_array((2, 3, 2)), site(*HERA_SITE), times, FREQS, gaussian_beam(14.0),
                           random_sky(LMAX, 1), LMAX, nside_matvis=NSIDE, dt_s=10.0, dnu_hz=1e5, noise_seed=0,
                           antenna_numbers=[4, 2, 9, 0, 7, 3, 1])


@pytest.fixture(scope="module")
def sim_file(sim, tmp_path_factory):
    uvd = sim.uvdata.copy()
    uvd.nsample_array = np.where(np.arange(uvd.Nblts)[:, None, None] % 3 == 0, 2.0, 1.0) * uvd.nsample_array
    path = tmp_path_factory.mktemp("obs") / "sim.uvh5"
    uvd.write_uvh5(str(path))
    return path, uvd


def test_simulated_file_reads_as_written(sim_file):
    path, uvd = sim_file
    obs = read_observation(path)
    assert obs.antenna_numbers.tolist() == [0, 1, 2, 3, 4, 7, 9] and obs.n_baselines == 21
    assert (obs.vis_units, obs.pol_convention, obs.telescope_name) == ("Jy", "sum", "gcrsky-sim")
    _check_against_pyuvdata(obs, uvd, ("xx", "yy"))
    assert obs.source == str(path) and "matvis" in obs.history


def test_radiometer_noise_is_the_hand_formula(sim_file):
    """sigma^2 = |V_ii,pp V_jj,pp| / (2 dt dnu N) per sample, from pyuvdata's accessors."""
    path, uvd = sim_file
    obs = read_observation(path, pol="xx")
    var = raw_variance(obs, "xx")
    for b, (ai, aj) in enumerate(obs.baseline_antnums):
        vi, vj = (np.abs(uvd.get_data((int(a), int(a), "xx")).real) for a in (ai, aj))
        n = uvd.get_nsamples((int(ai), int(aj), "xx"))
        np.testing.assert_allclose(var[:, :, b], (vi * vj / (2 * 10.0 * 1e5 * n)).T, rtol=1e-15, atol=0)
    assert np.any(obs.nsamples == 2.0)
    np.testing.assert_array_equal(radiometer_variance(4.0, 9.0, 10.0, 1e5, 2.0), 36.0 / (2 * 10.0 * 1e5 * 2.0))


def test_problem_from_observation_is_from_uvdata(sim_file):
    from gcrsky.instrument import gaussian_beam

    path, _ = sim_file
    beam = gaussian_beam(14.0)
    for kw in ({"pol": "pI"}, {"pol": ("xx", "yy"), "noise": "diff", "compress": False}):
        ref = from_uvdata(path, lmax=LMAX, nside=NSIDE, beam=beam, **kw)
        assert {"beam", "prior", "flags"} <= set(ref.config.checks)  # what from_uvdata checked besides: recorded
        assert not ref.config.checks["flags"]["outliers"]["channels"]  # nothing flagged: the same data
        ref = dataclasses.replace(ref, config=dataclasses.replace(ref.config, checks={}))
        pol = kw.get("pol")
        obs = read_observation(path, pol=pol, autos=kw.get("noise", "autos") == "autos")
        prob = problem_from_observation(obs, beam, lmax=LMAX, nside=NSIDE, **kw)
        prob = dataclasses.replace(prob, config=dataclasses.replace(prob.config, checks={}))  # band_limit's record
        la, ta = jax.tree_util.tree_flatten(ref)
        lb, tb = jax.tree_util.tree_flatten(prob)
        assert ta == tb and len(la) == len(lb)
        for x, y in zip(la, lb):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        assert prob.config == ref.config and prob.pols == ref.pols and prob.sky_note == ref.sky_note


def test_an_observation_checks_its_fields(sim_file):
    path, _ = sim_file
    obs = read_observation(path, pol="yy", antennas=[0, 1, 2])
    assert obs.n_antennas == 3 and obs.pol_names == ("yy",) and obs.nblts_read == 3 * 6
    with pytest.raises(ValueError, match="read-only"):
        obs.vis[0, 0, 0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        obs.vis_units = "Jy"
    with pytest.raises(ValueError, match=r"Observation.flags has shape .* axis 3 \(Nbl\) must be 3"):
        dataclasses.replace(obs, flags=obs.flags[..., :2])
    with pytest.raises(ValueError, match="i < j"):
        dataclasses.replace(obs, antpairs=obs.antpairs[:, ::-1])
    with pytest.raises(ValueError, match="holds products"):
        obs.pol_index("xx")
    assert "3 antennas, 3 baselines" in repr(obs)


def test_malformed_antenna_positions_and_site_are_named(h1c, tmp_path):
    """A NaN position of a used antenna, or a site off the Earth, is refused naming the file, the antennas and
    the header field (astropy's own message names neither)."""
    import warnings

    bad = h1c.copy()
    bad.telescope.antenna_positions = bad.telescope.antenna_positions.copy()
    bad.telescope.antenna_positions[list(bad.telescope.antenna_numbers).index(12)] = np.nan
    path = tmp_path / "nanpos.uvh5"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pyuvdata: the uvws no longer match the positions
        bad.write_uvh5(str(path), run_check=False)
    with pytest.raises(ValueError, match=r"nanpos.uvh5: the positions of antennas \[12\] are not finite"):
        read_observation(path, pol="pI", freq_chans=[30])
    read_observation(path, pol="pI", freq_chans=[30], antennas=[1, 11, 13])  # the control: antenna 12 left out
    # a NaN latitude in the header ("cannot convert float NaN to integer" before issue 40)
    import shutil

    import h5py

    nanlat = tmp_path / "nanlat.uvh5"
    shutil.copy(H1C, nanlat)
    with h5py.File(nanlat, "r+") as f:
        f["Header"]["latitude"][...] = np.nan
    with pytest.raises(ValueError, match=r"nanlat.uvh5: the telescope's location \(telescope_location, ECEF \[nan, "
                                         r"nan, nan\] m\) is not a place on the Earth's surface"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pyuvdata: the LSTs and uvws no longer match the location
            read_observation(nanlat, pol="pI", freq_chans=[30])


def test_a_channel_named_twice_is_refused_not_read_as_every_channel(sim_file):
    """``freq_chans=[0, 0]`` on a two-channel file selected every channel (the count matched); now refused."""
    path, _ = sim_file
    with pytest.raises(ValueError, match="names a channel more than once"):
        read_observation(path, freq_chans=[0, 0])
    assert read_observation(path, freq_chans=[1, 0]).n_freqs == 2  # the control: both, in the file's order
    assert read_observation(path, freq_chans=[1]).freqs_hz.tolist() == [FREQS[1]]
