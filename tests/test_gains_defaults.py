"""``gcrsky run --data F --gains sample`` with its defaults, ``--strict``, and the recipes of docs/gains.md (issue 38).

The file: a small matvis simulation (7 antennas, 2 channels at 100 and 101 MHz, 6 times over 3 h, a
sky band-limited at lmax 6, radiometer noise) corrupted by ``gcrsky.checks.gainsim.corrupt_with_gains``
with its defaults (5 % / 5 deg per antenna and feed, linear in frequency and time: Legendre
modes).  Checks:

* the default gain modes follow the selection (:func:`gcrsky.run.gains.default_gain_modes`, against
  its rule written out here);
* the command of docs/gains.md's "From the command line" (parsed from the page, its optional parts
  left out, at this file's size) with the default modes is not rejected by the fit, exit 0 under
  ``--strict``, and its summary carries the chain's ESS block (every sampled scalar);
* the former default (one constant DPSS gain per antenna) on the same file is rejected: under
  ``--strict`` the command exits 6 with everything written, the terminal names the rejected channels
  in one WARNING line; without ``--strict`` the same summary exits 0;
* the H1C recipe of the same page (``### From the command line, with the sky above lmax through the
  gains``) runs as written at 2 draws on the real file (skipped where it is absent).
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import h5py
import numpy as np
import pytest

pytest.importorskip("matvis")
pytest.importorskip("blackjax")

from conftest import H1C, H1C_CAL  # noqa: E402

from gcrsky import cli  # noqa: E402
from gcrsky.checks.gainsim import corrupt_with_gains  # noqa: E402
from gcrsky.checks.matvis import HERA_SITE, observing_times, random_sky, site  # noqa: E402
from gcrsky.checks.uvsim import simulate_uvdata  # noqa: E402
from gcrsky.cli.runs import EXIT_REJECTED, report_run  # noqa: E402
from gcrsky.instrument import gaussian_beam, hex_array  # noqa: E402
from gcrsky.run import read_summary  # noqa: E402
from gcrsky.run.gains import default_gain_modes  # noqa: E402

DOC = Path(__file__).resolve().parents[1] / "docs" / "gains.md"
LMAX = 6
#: This file's size (the template leaves lmax and nside to the data's reach) and a short chain.
SIZE = ["--lmax", str(LMAX), "--nside", "32", "--band-limit", "truncate", "--nsamples", "40", "--batch", "20",
        "--gain-burn", "100", "--no-progress", "--no-plots"]


def _doc_commands() -> dict:
    """The ``gcrsky run`` commands of docs/gains.md, by the heading above each: continuation lines joined."""
    out, heading, lines = {}, None, DOC.read_text().splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
        if line.startswith("    gcrsky run"):
            cmd = line.strip()
            while cmd.endswith("\\"):
                i += 1
                cmd = cmd[:-1].rstrip() + " " + lines[i].strip()
            out[heading] = cmd
        i += 1
    return out


def _without_optional_parts(cmd: str) -> str:
    """The command with its ``[...]`` parts (nested ones too) left out."""
    while "[" in cmd:
        cmd = re.sub(r"\s*\[[^\[\]]*\]", "", cmd)
    return cmd


@pytest.fixture(scope="module")
def corrupted(tmp_path_factory):
    d = tmp_path_factory.mktemp("gainsim_defaults")
    sim = simulate_uvdata(hex_array((2, 3, 2)), site(*HERA_SITE), observing_times("2025-03-21T18:00:00", 3.0, 6),
                          np.array([100e6, 101e6]), gaussian_beam(14.0), random_sky(LMAX, 3), LMAX, nside_matvis=32)
    cor, _ = corrupt_with_gains(sim.uvdata)  # gainsim's defaults
    path = d / "corrupted.uvh5"
    cor.write_uvh5(str(path))
    return path


@pytest.fixture(scope="module")
def default_run(corrupted, tmp_path_factory):
    """The page's template command with its optional parts left out, on the corrupted file, ``--strict``."""
    cmd = _without_optional_parts(_doc_commands()["From the command line"])
    argv = shlex.split(cmd.replace("FILE", str(corrupted)))
    assert argv[:2] == ["gcrsky", "run"] and "--gain-modes" not in argv and "--gain-basis" not in argv
    out = tmp_path_factory.mktemp("default_run")
    rc = cli.main([*argv[1:], "--out", str(out), *SIZE, "--strict"])
    return out, rc


def test_default_gain_modes_follow_the_channels_and_the_time_span():
    hours = np.pi / 12  # radians of LST per sidereal hour
    t3 = np.linspace(0, 3 * hours, 6)
    assert default_gain_modes([100e6, 101e6], t3) == (2, 2)  # narrow band, 3 h: constant and slope in each
    assert default_gain_modes([150e6], t3) == (1, 2)  # one channel: one frequency mode
    assert default_gain_modes([100e6, 101e6], [0.3]) == (2, 1)  # one time
    assert default_gain_modes(np.linspace(100e6, 110e6, 2), t3) == (2, 2)  # two channels: at most 2
    # 133-194 MHz (37 % of its centre): one more for the curvature; 100-200 MHz (67 %): 5 capped at 4
    assert default_gain_modes(np.linspace(133e6, 194e6, 60), t3) == (3, 2)
    assert default_gain_modes(np.linspace(100e6, 200e6, 60), t3) == (4, 2)
    # 12 h or more: a third time mode; LSTs through 0 h are unwrapped (23 h -> 12 h is 13 h)
    assert default_gain_modes([100e6, 101e6], np.linspace(0, 13 * hours, 30)) == (2, 3)
    wrap = np.mod(np.linspace(23 * hours, 36 * hours, 30), 2 * np.pi)
    assert default_gain_modes([100e6, 101e6], wrap) == (2, 3)
    assert default_gain_modes([100e6, 101e6], np.mod(np.linspace(23 * hours, 25 * hours, 9), 2 * np.pi)) == (2, 2)


@pytest.mark.slow
def test_the_documented_command_with_default_modes_passes_on_gainsims_defaults(default_run, capsys):
    out, rc = default_run
    s = json.loads((out / "summary.json").read_text())
    gof, g = s["goodness_of_fit"], s["gains"]
    assert rc == 0, gof["chi2_per_dof"]  # --strict: a rejected fit would exit 6
    assert not gof["rejected"], gof["chi2_per_dof"]
    assert g["settings"]["modes"] == [2, 2] and g["settings"]["basis"] == "legendre"
    # every sampled scalar's ESS: q per channel, its 2 modes, every gain coefficient; 40 draws < the floor 100
    chain = g["chain"]
    assert chain["ndraws"] == 40 and chain["floor"] == 100
    assert chain["groups"]["flux_scale"]["size"] == 2 and chain["groups"]["scale_modes"]["size"] == 2
    assert chain["groups"]["gain_theta"]["size"] == g["parameters"]
    assert chain["n_scalars"] == 4 + g["parameters"] and chain["n_below_floor"] == chain["n_scalars"]
    assert chain["ok"] is False and len(chain["below_floor"]) == 10
    assert g["chain"]["groups"]["flux_scale"]["ess"][0] == pytest.approx(g["flux_scale_ess"], rel=1e-9)
    assert any(w.startswith("WARNING: the gain chain has not mixed") for w in s["warnings"])
    assert g["warnings"] == [w for w in s["warnings"] if "has not mixed" in w]


@pytest.mark.slow
def test_the_former_default_is_rejected_and_strict_exits_6_with_everything_written(corrupted, tmp_path, capsys):
    out = tmp_path / "constant"
    argv = ["run", "--data", str(corrupted), "--dish-diameter", "14", "--gains", "sample", "--gain-modes", "1,1",
            "--gain-basis", "dpss", "--out", str(out), *SIZE]
    capsys.readouterr()
    assert cli.main([*argv, "--strict"]) == EXIT_REJECTED
    err = capsys.readouterr().err
    s = read_summary(out / "summary.json")
    gof = s.goodness_of_fit
    assert gof["rejected"] and gof["rejected_channels"]
    for name in ("results.h5", "posterior_mean.fits", "gains.calh5"):
        assert (out / name).exists(), name
    with h5py.File(out / "results.h5", "r") as h:
        assert h["draws"].shape[1] == 40
    # one line names each rejected channel, its chi2/dof and tail
    lines = [x for x in err.splitlines() if x.startswith("WARNING: the model does not fit the data")]
    assert len(lines) == 1
    for k in gof["rejected_channels"]:
        assert f"{100 + k:.3f} MHz chi2/dof {gof['chi2_per_dof'][k]:.3g}" in lines[0]
    assert "upper p" in lines[0] or "lower p" in lines[0]
    assert f"status {EXIT_REJECTED}" in err
    # without --strict the same completed run exits 0 (the line is still printed)

    class Done:
        already_complete, written = False, []

    assert report_run(s, Done(), out) == 0
    assert "does not fit the data in" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.skipif(not H1C.exists(), reason="the real H1C file is absent (../shared/data/real)")
def test_the_h1c_recipe_runs_as_written(tmp_path):
    cmd = _doc_commands()["From the command line, with the sky above lmax through the gains"]
    argv = shlex.split(cmd)[1:]
    argv[argv.index("--data") + 1] = str(H1C)
    argv[argv.index("--cal") + 1] = str(H1C_CAL)
    for opt, small in (("--nsamples", "2"), ("--batch", "2"), ("--gain-burn", "2")):  # the size reduced
        argv[argv.index(opt) + 1] = small
    out = tmp_path / "h1c"
    rc = cli.main([*argv, "--out", str(out), "--no-plots", "--no-progress"])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["config"]["nside"] == 64 and s["config"]["lmax"] == 24
    # redundant solutions without a gain_scale: the amplitude is inferred with the gains (docs/amplitude.md)
    assert s["flux_scale"]["source"] == "inferred" and len(s["flux_scale"]["per_channel"]) == 2
    assert s["amplitude"]["settings"]["gains"]["modes"] == [1, 1]
