"""``gcrsky inspect`` and ``gcrsky run --data`` with the data checks: the real HERA files, small and fast.

H1C with its omnical solutions end to end (3 channels, lmax 4, nside 64 -- the quadrature must
resolve the kept baselines' fringes, which reach l ~164 -- 10 draws): the solutions apply offline,
the ORBCOMM channel is flagged, and with the amplitude held fixed (``--amplitude fixed --gains off``: the
check's own path; by default the amplitude is inferred, tests/test_amplitude*.py) the flux scale (~0.004:
redundant solutions leave the amplitude free) is refused, then accepted with ``--flux-scale accept``.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import H1C, H2C  # noqa: E402
from conftest import H1C_CAL as CAL  # noqa: E402

from gcrsky import cli

pytestmark = pytest.mark.skipif(not H1C.exists(), reason="the real HERA files are not there")
RUN = ["run", "--data", str(H1C), "--cal", str(CAL), "--dish-diameter", "14", "--chans", "20,24,30", "--lmax", "4",
       "--band-limit", "marginalise",  # every baseline reaches l > 80: the sky above lmax 4 as noise
       "--nside", "64", "--nsamples", "10", "--batch", "5", "--no-progress", "--no-plots",
       "--amplitude", "fixed", "--gains", "off"]


def test_h1c_with_its_solutions_end_to_end(tmp_path, capsys):
    assert cli.main([*RUN, "--out", str(tmp_path / "refused")]) == 2
    err = capsys.readouterr().err
    assert "0.00" in err and "--flux-scale accept" in err
    out = tmp_path / "run"
    assert cli.main([*RUN, "--flux-scale", "accept", "--out", str(out)]) == 0
    checks = json.loads((out / "summary.json").read_text())["data_checks"]
    assert checks["flags"]["outliers"]["channels_mhz"] == [137.5]  # ORBCOMM, the middle channel
    assert checks["flags"]["fully_flagged_antennas"] == [0]  # flagged in the solutions
    assert 0.003 < checks["flux_scale"]["ratio"] < 0.005 and checks["flux_scale"]["mode"] == "accept"
    assert checks["calibration"]["applied"]["renamed_antennas"]["0"] == ["ant0", "HH0"]
    # accepted ~300x below the GSM prior's scale, the data vary far less than the model expects: the posterior
    # predictive check rejects the fit in its lower tail (the flagged channel has no degree of freedom: None)
    gof = json.loads((out / "summary.json").read_text())["goodness_of_fit"]
    assert gof["rejected"] and gof["rejected_channels"] == [0, 2] and gof["chi2_per_dof"][1] is None
    printed = capsys.readouterr()
    assert max(gof["chi2_per_dof"][k] for k in (0, 2)) < 1e-4 and "lower p" in printed.out + printed.err


def test_an_uncalibrated_file_is_refused_naming_cal(tmp_path, capsys):
    """Held at a fixed amplitude an uncalibrated file is refused naming --cal; by default its amplitude is
    inferred instead (said before any work; lmax 4 then reaches no baseline, refused cheaply before set-up)."""
    args = ["run", "--data", str(H1C), "--dish-diameter", "14", "--chans", "20", "--lmax", "4", "--nside", "16",
            "--out", str(tmp_path / "x")]
    rc = cli.main([*args, "--amplitude", "fixed"])
    assert rc == 2 and "--cal FILE" in capsys.readouterr().err
    rc = cli.main(args)
    printed = capsys.readouterr()
    assert rc == 2 and "amplitude per channel is inferred" in printed.out and "--cal FILE" not in printed.err
    assert "reaches no baseline" in printed.err


def test_inspect_reports_everything_then_problems(capsys):
    assert cli.main(["inspect", str(H1C), "--dish-diameter", "14"]) == 0
    text = capsys.readouterr().out
    assert "11 unique within 0.5 m" in text
    assert "137.50 MHz" in text and "dead channels [0, 1, 2]" in text
    # the band limit a run would choose: H1C's 38.7 m baselines with 14 m dishes reach l ~ 2 pi 52.7 m / 1.51 m
    # ~ 219 at 198.4 MHz (driftscan's form from the east/north components: 246); all 64 channels cap it by memory
    band = next(line for line in text.splitlines() if line.strip().startswith("band limit"))
    assert "reach l = 246" in band and "models lmax" in band
    lines = text.splitlines()
    problems = [k for k, line in enumerate(lines) if line.startswith("PROBLEM")]
    assert len(problems) == 2 and problems[0] == len(lines) - 2  # last: uncalibrated; flux scale
    assert "--cal FILE" in lines[-2] and "flux scale" in lines[-1]
    assert cli.main(["inspect", str(H2C), "--json", "--pol", "xx"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert any("nsample of every unflagged sample is zero" in p for p in info["problems"])
    assert info["data_checks"]["flags"]["fully_flagged_antennas"] == info["antennas"]
    assert cli.main(["inspect", str(H1C), "--redundancy-tol", "1e-9", "--chans", "30", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["n_unique_baselines"] == 28


def test_injected_rfi_in_a_file_is_flagged_and_reported(tmp_path, capsys):
    """Clean H1C channels 10-20 with a strong time-varying signal added to channel 15 (index 5 of the selection)."""
    from pyuvdata import UVData

    uvd = UVData.from_file(str(H1C), freq_chans=list(range(10, 21)))
    rng = np.random.default_rng(0)
    cross = uvd.ant_1_array != uvd.ant_2_array
    amp = 30 * np.median(np.abs(uvd.data_array[cross, 5]))
    uvd.data_array[cross, 5] += amp * (rng.normal(size=(cross.sum(), uvd.Npols))
                                       + 1j * rng.normal(size=(cross.sum(), uvd.Npols)))
    path = tmp_path / "rfi.uvh5"
    uvd.write_uvh5(str(path))
    assert cli.main(["inspect", str(path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)["data_checks"]["flags"]["outliers"]
    assert out["channels"] == [5] and out["baselines"] == [] and out["times"] == []
    assert cli.main(["inspect", str(path), "--no-flag-outliers"]) == 0
    assert "outliers (not flagged: --no-flag-outliers): channels 5" in capsys.readouterr().out


def test_zero_nsample_file_is_refused_by_a_run(tmp_path, capsys):
    """H2C (nsample 0 everywhere): exit 2 with the reason, before any response (it used to give prior-only results)."""
    rc = cli.main(["run", "--data", str(H2C), "--pol", "xx", "--dish-diameter", "14", "--lmax", "4", "--nside", "16",
                   "--out", str(tmp_path / "h2c")])
    assert rc == 2 and "nsample of every unflagged sample is zero" in capsys.readouterr().err
    assert not (tmp_path / "h2c" / "summary.json").exists()


def test_flagging_that_leaves_nothing_is_refused_with_the_reason(tmp_path, capsys):
    """Only H1C's zeroed edge channels 0-2 (dead, unflagged in the file; units set to Jy): nothing is left."""
    from pyuvdata import UVData

    uvd = UVData.from_file(str(H1C), freq_chans=[0, 1, 2])
    uvd.vis_units = "Jy"
    path = tmp_path / "edge.uvh5"
    uvd.write_uvh5(str(path))
    rc = cli.main(["run", "--data", str(path), "--dish-diameter", "14", "--lmax", "4", "--nside", "16",
                   "--flux-scale", "off", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and "dead channels [0, 1, 2]" in err and "--no-flag-outliers" in err


def test_inspect_separates_the_flags_and_never_prints_a_nan_noise(capsys):
    """Issue 39: 'flagged 11 %' mixed the file's flags (0 % on H1C) with gcrsky's own; a file with nothing
    usable printed a NaN noise; x_orientation was never shown."""
    assert cli.main(["inspect", str(H1C), "--chans", "20,21,22,23,24,25"]) == 0
    text = capsys.readouterr().out
    flag = next(line for line in text.splitlines() if line.strip().startswith("flagged"))
    assert "the file's (and its calibration's) flags 0.00%" in flag and "zero nsample 0.00%" in flag
    assert "gcrsky's checks 0.00%" not in flag  # channel 24's noise-excess outliers and antenna 0: gcrsky's own
    assert "feed x points east" in text and "nan" not in text.lower().replace("nanosec", "")
    assert cli.main(["inspect", str(H2C), "--pol", "xx"]) == 0
    text = capsys.readouterr().out
    assert "zero nsample 100.00%" in text and "no radiometer noise estimate" in text and "nan" not in text
    assert "x_orientation absent" in text
