"""Many files in (issue 39): a night of files read as one observation, refused when they are not of one array.

References: the real H1C file (10 integrations) split by pyuvdata into files of a few integrations each --
read together they must give the one file's Observation, Problem and posterior bit for bit, in any order;
pyuvdata's own ``UVCal.interpolate_in_time`` + ``uvcalibrate`` for solutions at other times; files made
inconsistent one field at a time (channels, products, an antenna moved, units, a shared integration) for
the refusals; a second night (the same file one day later) for the gap that no time difference may span.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax
import numpy as np
import pytest
from conftest import H1C  # noqa: E402
from conftest import H1C_CAL as CAL  # noqa: E402

pytestmark = pytest.mark.skipif(not H1C.exists(), reason="the real HERA files are not there")
CHANS = [30, 40]


@pytest.fixture(scope="module")
def h1c():
    from pyuvdata import UVData

    return UVData.from_file(str(H1C))


def _write(uvd, path, **select):
    part = uvd.select(**select, inplace=False) if select else uvd.copy()
    part.write_uvh5(str(path), clobber=True)
    return str(path)


@pytest.fixture(scope="module")
def night(h1c, tmp_path_factory):
    """The H1C file as three files of 3, 3 and 4 integrations (a night's files in miniature)."""
    d = tmp_path_factory.mktemp("night")
    t = np.unique(h1c.time_array)
    return [_write(h1c, d / f"zen.part{k}.uvh5", times=t[sl]) for k, sl in
            enumerate((slice(0, 3), slice(3, 6), slice(6, 10)))]


def _assert_same_observation(a, b):
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f.name)


def test_several_files_read_as_the_one_file_bit_for_bit(night):
    from gcrsky.io import read_observation

    one = read_observation(H1C, pol="pI", freq_chans=CHANS)
    for order in (night, night[::-1]):  # the order the files are given in does not matter
        many = read_observation(order, pol="pI", freq_chans=CHANS)
        _assert_same_observation(one, many)
        assert many.files == tuple(order)
        assert [many.files[k] for k in many.time_file] == [night[0]] * 3 + [night[1]] * 3 + [night[2]] * 4
    assert one.files == () and one.time_file == ()


def test_several_calibrated_files_give_the_one_file_s_posterior_bit_for_bit(night):
    """The Problem (every array) and the Wiener filter from three files and their one calibration file
    equal the one file's."""
    from gcrsky import wiener_filter
    from gcrsky.ingest import from_uvdata

    kw = dict(lmax=20, nside=64, dish_diameter_m=14.0, pol="pI", freq_chans=CHANS, cal=str(CAL),
              band_limit="truncate", flux_scale="off")
    one = from_uvdata(H1C, **kw)
    many = from_uvdata(night, **kw)
    la, lb = jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(many)
    assert len(la) == len(lb) and many.config.source.endswith("and 2 more file(s)")  # the configs name the files
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    np.testing.assert_array_equal(np.asarray(wiener_filter(one)), np.asarray(wiener_filter(many)))
    rec = many.config.checks["calibration"]["applied"]
    assert [r["data"] for r in rec["per_file"]] == night and rec["file"] == str(CAL)


def test_a_glob_a_directory_and_a_list_name_the_same_files(night, tmp_path):
    from gcrsky.io.files import expand_data_paths

    d = str(tmp_path.parent / night[0].split("/")[-2])
    assert expand_data_paths(night[0].rsplit("/", 1)[0] + "/zen.part*.uvh5") == night
    assert expand_data_paths(d) == night
    assert expand_data_paths([night[2], night[0]]) == [night[2], night[0]]
    with pytest.raises(ValueError, match="given twice"):
        expand_data_paths([night[0], night[1], night[0]])
    with pytest.raises(FileNotFoundError, match="no visibility file matches"):
        expand_data_paths(str(tmp_path / "nothing*.uvh5"))
    with pytest.raises(FileNotFoundError, match="holds no visibility file"):
        expand_data_paths(str(tmp_path))


@pytest.mark.parametrize("what", ["channels", "products", "antenna", "units", "shared time"])
def test_files_that_are_not_of_one_array_and_band_are_refused(h1c, night, tmp_path, what):
    from gcrsky.io import read_observation

    t = np.unique(h1c.time_array)
    if what == "channels":
        other = _write(h1c, tmp_path / "x.uvh5", times=t[3:6], freq_chans=np.arange(32))
        match = "the channels differ"
    elif what == "products":
        other = _write(h1c, tmp_path / "x.uvh5", times=t[3:6], polarizations=["ee"])
        match = "the feed products differ"
    elif what == "antenna":
        moved = h1c.select(times=t[3:6], inplace=False)
        moved.telescope.antenna_positions = moved.telescope.antenna_positions.copy()
        moved.telescope.antenna_positions[list(moved.telescope.antenna_numbers).index(12)] += [0.0, 0.5, 0.0]
        other = _write(moved, tmp_path / "x.uvh5")
        match = "antenna 12 is 0.5 m from its position"
    elif what == "units":
        k = h1c.select(times=t[3:6], inplace=False)
        k.vis_units = "Jy"
        other = _write(k, tmp_path / "x.uvh5")
        match = "the units differ"
    else:
        other = _write(h1c, tmp_path / "x.uvh5", times=t[2:6])  # its first integration is also in night[0]
        match = "both hold the integration at JD"
    with pytest.raises(ValueError, match=match) as err:
        read_observation([night[0], other, night[2]], pol="pI", freq_chans=CHANS)
    assert str(tmp_path / "x.uvh5") in str(err.value)


def test_an_lst_range_reads_only_the_files_it_touches(night, h1c):
    from gcrsky.io import read_observation

    lst_h = np.degrees(np.unique(h1c.lst_array)) / 15.0
    obs = read_observation(night, pol="pI", freq_chans=CHANS, lst_range_hours=(lst_h[0] - 1e-4, lst_h[4] + 1e-4))
    assert obs.n_times == 5 and obs.files == tuple(night[:2])  # the third file is not read (and the log says so)
    with pytest.raises(ValueError, match="in none of the 3 files"):
        read_observation(night, pol="pI", times_jd=[2400000.5])


def test_two_nights_no_time_difference_spans_the_day_between(h1c, tmp_path, monkeypatch):
    """The same integrations one day later are a second night: their LSTs ~4 min earlier, the noise-excess
    terms and the ``diff`` noise never pair an integration of one night with one of the other."""
    from gcrsky.io import read_observation
    from gcrsky.model.datachecks import noise_excess
    from gcrsky.model.noise import adjacent_times

    later = h1c.copy()
    later.time_array = later.time_array + 1.0
    later.set_lsts_from_time_array()
    second = _write(later, tmp_path / "zen.next.uvh5")
    obs = read_observation([H1C, second], pol="pI", freq_chans=CHANS)
    assert obs.n_times == 20
    adj = adjacent_times(obs.times_jd, obs.integration_time_s)
    assert adj.tolist() == [True] * 9 + [False] + [True] * 9
    ex = noise_excess(obs)
    one = noise_excess(read_observation(H1C, pol="pI", freq_chans=CHANS))
    assert np.all(np.isnan(ex.z[:, :, 9]))  # the pair across the gap is not a term
    # each night's excess equals the one file's (the same data one day later), and the joint excess with them
    assert ex.per_file[0] == pytest.approx(ex.per_file[1], rel=1e-12)
    np.testing.assert_allclose(ex.excess, one.excess, rtol=1e-12)
    # the control: were a day a step, the pair across it (LSTs 5.5 min apart) would read as a large excess
    monkeypatch.setattr("gcrsky.model.noise.ADJACENT_GAP", 1e9)
    spanned = noise_excess(obs)
    assert np.isfinite(spanned.z[:, :, 9]).any()
    assert np.nanmax(spanned.excess / one.excess) > 1.5


def test_calibration_per_file_and_interpolated_in_time_as_pyuvdata_does(h1c, night, tmp_path):
    from pyuvdata.utils import uvcalibrate

    from gcrsky.io.calibration import read_calibrated_observation, read_calibration
    from gcrsky.io.observation import read_observation

    uvc, _ = read_calibration(CAL, location=h1c.telescope.location)
    t = np.unique(uvc.time_array)
    cals = []
    for k, path in enumerate(night):  # one solutions file per data file: the solutions of its times
        from pyuvdata import UVData

        times = np.unique(UVData.from_file(path, read_data=False).time_array)
        part = uvc.select(times=times, inplace=False)
        cals.append(str(tmp_path / f"cal{k}.calh5"))
        part.write_calh5(cals[-1])
    one, _ = read_calibrated_observation(H1C, str(CAL), pol="pI", freq_chans=CHANS)
    per, rec = read_calibrated_observation(night, cals, pol="pI", freq_chans=CHANS)
    _assert_same_observation(one, per)
    assert rec["file"] == cals and not rec["interpolated_in_time"]
    with pytest.raises(ValueError, match="2 calibration files for 3 visibility files"):
        read_calibrated_observation(night, cals[:2], pol="pI", freq_chans=CHANS)

    # solutions at every other time: interpolated (linear in amplitude and phase) by pyuvdata
    sparse = uvc.select(times=t[::3], inplace=False)  # 0, 3, 6, 9: spans every data time
    path = str(tmp_path / "sparse.calh5")
    sparse.write_calh5(path)
    got, rec = read_calibrated_observation(H1C, path, pol="pI", freq_chans=CHANS)
    assert rec["interpolated_in_time"]
    ref = h1c.select(freq_chans=CHANS, polarizations=["ee", "nn"], inplace=False)
    interp = sparse.interpolate_in_time(np.unique(ref.time_array), kind="linear", inplace=False)
    interp.telescope.antenna_names = ref.telescope.antenna_names[
        [list(ref.telescope.antenna_numbers).index(a) for a in interp.telescope.antenna_numbers]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pyuvdata: no gain_scale, no pol_convention (the file's own quirks)
        uvcalibrate(ref, interp, inplace=True, prop_flags=True)
    ref.vis_units = "Jy"
    want = read_observation(ref, pol="pI")
    np.testing.assert_array_equal(got.flags, want.flags)
    np.testing.assert_allclose(got.vis, want.vis, rtol=1e-12, atol=0)
    # solutions at one time (a bandpass) apply to every data time (pyuvdata's time_check=False)
    one = uvc.select(times=t[:1], inplace=False)
    path = str(tmp_path / "one.calh5")
    one.write_calh5(path)
    got, rec = read_calibrated_observation(H1C, path, pol="pI", freq_chans=CHANS)
    assert rec["one_time_for_all"] and not rec["interpolated_in_time"]
    ref = h1c.select(freq_chans=CHANS, polarizations=["ee", "nn"], inplace=False)
    one.telescope.antenna_names = ref.telescope.antenna_names[
        [list(ref.telescope.antenna_numbers).index(a) for a in one.telescope.antenna_numbers]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        uvcalibrate(ref, one, inplace=True, prop_flags=True, time_check=False)
    ref.vis_units = "Jy"
    np.testing.assert_allclose(got.vis, read_observation(ref, pol="pI").vis, rtol=1e-12, atol=0)
    # the control: solutions that do not reach the last times are refused, naming them
    short = uvc.select(times=t[:6], inplace=False)
    path = str(tmp_path / "short.calh5")
    short.write_calh5(path)
    with pytest.raises(ValueError, match="4 of the data's 10 times are not covered"):
        read_calibrated_observation(H1C, path, pol="pI", freq_chans=CHANS)


def test_inspect_reports_each_file(night, capsys):
    from gcrsky.cli import main

    rc = main(["inspect", *night, "--cal", str(CAL), "--chans", "30,40", "--dish-diameter", "14"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "and 2 more file(s)" in out and "times         10" in out
    assert "per file      noise excess: 3 files" in out and "per file      flux scale: 3 files" in out
    for p in night:
        assert p.rsplit("/", 1)[1] in out


def test_a_run_on_several_files_records_them_and_resumes(night, tmp_path, capsys):
    """``gcrsky run --data DIR``: the files and their digests in the run's settings; a finished run resumes
    (nothing to do), overlapping files are refused, and so is a resume after one file's content changed."""
    import json
    import shutil

    from gcrsky.cli import main

    d = tmp_path / "night"
    d.mkdir()
    for p in night:
        shutil.copy(p, d)
    out = tmp_path / "run"
    args = ["run", "--data", str(d), "--cal", str(CAL), "--dish-diameter", "14", "--chans", "30", "--lmax", "20",
            "--nside", "64", "--band-limit", "truncate", "--gains", "off", "--nsamples", "4", "--batch", "4",
            "--no-progress", "--out", str(out)]
    assert main(args) in (0, 6)  # 6: a rejected fit (a run on 1 channel of real data at lmax 20 may be)
    s = json.loads((out / "summary.json").read_text())
    assert s["config"]["source"].endswith("and 2 more file(s)")
    assert "and 2 more file(s): 8 antennas" in capsys.readouterr().out
    assert main([*args, "--resume"]) in (0, 6)
    capsys.readouterr()
    shutil.copy(night[0], d / "zen.part1.uvh5")  # two files now hold the same integrations
    assert main([*args, "--resume"]) == 2
    assert "both hold the integration at JD" in capsys.readouterr().err
    from pyuvdata import UVData

    changed = UVData.from_file(night[1])
    changed.data_array = changed.data_array * 1.001  # one file's content changes
    changed.write_uvh5(str(d / "zen.part1.uvh5"), clobber=True)
    assert main([*args, "--resume"]) == 3  # refused: the recorded digests differ
    assert "data_sha256" in capsys.readouterr().err


@pytest.mark.parametrize("what", ["flagged", "zero"])
def test_solutions_that_flag_or_zero_everything_are_named(h1c, tmp_path, what):
    from gcrsky.io.calibration import read_calibrated_observation, read_calibration

    uvc, _ = read_calibration(CAL, location=h1c.telescope.location)
    if what == "flagged":
        uvc.flag_array[:] = True
    else:
        uvc.gain_array[:] = 0.0  # pyuvdata flags the samples of zero gains
    match = "its solutions flag every one of the 1120 unflagged cross-correlation samples"
    path = str(tmp_path / "bad.calh5")
    uvc.write_calh5(path)
    with pytest.raises(ValueError, match=r"bad\.calh5: " + match):
        read_calibrated_observation(H1C, path, pol="pI", freq_chans=CHANS)


def test_inspect_names_unflagged_non_finite_visibilities(h1c, tmp_path):
    """A run refuses unflagged NaN visibilities; inspect said nothing (issue 40): now a PROBLEM naming where."""
    from gcrsky.ingest import inspect_uvdata

    bad = h1c.copy()
    rows = np.flatnonzero((bad.ant_1_array == 11) & (bad.ant_2_array == 12))
    bad.data_array[rows[2], 30, 0] = np.nan
    path = _write(bad, tmp_path / "nan.uvh5")
    problems = inspect_uvdata(path, freq_chans=CHANS, pol="pI")["problems"]
    assert any("1 unflagged visibilities are not finite (1 NaN, 0 Inf), first xx at channel 0" in p and
               "baseline 11-12" in p for p in problems), problems
    clean = inspect_uvdata(str(H1C), freq_chans=CHANS, pol="pI")["problems"]  # the control
    assert not any("not finite" in p for p in clean)


@pytest.mark.parametrize("where", ["cross", "auto"])
def test_an_inf_visibility_is_named_as_inf_by_run_and_inspect(h1c, tmp_path, where, capsys):
    """An unflagged Inf visibility was reported by ``run`` as "1 NaN ... (nan+nanj)" (pseudo-Stokes I had made it
    NaN), and an unflagged Inf autocorrelation was accepted without a word (it made that antenna's noise
    infinite, dropping its baselines silently) (issue 40).  Now one check, on the file's values: run refuses
    and inspect reports the same message; the control, the file itself, passes both (test above)."""
    from gcrsky.cli import main
    from gcrsky.ingest import inspect_uvdata

    bad = h1c.copy()
    ants = (11, 12) if where == "cross" else (11, 11)
    rows = np.flatnonzero((bad.ant_1_array == ants[0]) & (bad.ant_2_array == ants[1]))
    bad.data_array[rows[2], 30, 0] = np.inf
    bad.flag_array[rows[2], 30, 0] = False
    path = _write(bad, tmp_path / "inf.uvh5")
    what = "visibilities" if where == "cross" else "autocorrelations"
    want = (f"1 unflagged {what} are not finite (0 NaN, 1 Inf), first xx at channel 0 (146.8750 MHz), time 2, "
            f"baseline {ants[0]}-{ants[1]} (value (inf+0j))")
    problems = inspect_uvdata(path, freq_chans=CHANS, pol="pI")["problems"]
    assert any(want in p for p in problems), problems
    out = tmp_path / "run"
    assert main(["run", "--data", path, "--chans", ",".join(map(str, CHANS)), "--dish-diameter", "14", "--lmax", "8",
                 "--nside", "64", "--nsamples", "2", "--no-plots", "--no-progress", "--band-limit", "truncate",
                 "--flux-scale", "accept", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert want in err and "a run refuses them; flag them in the file" in err, err[-2000:]
    assert not (out / "results.h5").exists()
