"""``gcrsky run --data F --beams sample`` on a twin of the H1C file whose dishes each point their own way (issue 41).

The twin (:func:`gcrsky.checks.twin.make_twin`) has H1C's 8 antennas, site, 10 integrations and one channel
(162.5 MHz), as the real file is: uncalibrated (``vis_units`` "uncalib", the bandpass q = 0.003: the run infers
the overall amplitude with the beams and the sky), unit gains (the gains sampled with the beams:
tests/test_beam_gains_cli.py), radiometer noise from its autos, and a sky that is not the prior's (the GSM brightened and modulated,
with small-scale structure, to l = 18, the run's lmax: the beam block's exact marginal needs a dense problem).
matvis simulates each dish with its own beam (:class:`gcrsky.checks.beamsim.PerturbedDishBeam`: pointings
scattered by 6 mrad rms).  The run reads it as a user would, with the nominal 14 m dish.

Measured (2-core CPU): the nominal beams' fit chi2/dof 5.75 (rejected: the negative control, computed by the
run as ``beams.fit_nominal`` at the nominal beams' amplitude mode nearest the block's), with the block 1.00; log
Bayes factor +700 for the block (the nominal evidence integrates the amplitude over its whole range, including
a mode at u = 874, where the prior no longer constrains the sky, u^2 S far above the data's scale, and an
unconstrained sky absorbs the beams' misfit); the posterior-mean
tilts correlate with the true pointing offsets (East 0.88, North 0.97 measured); the independence move accepted
57 %; the run 3 min, its kill and resume 1.3 min more (the marginal from the data-space Grams).

What the amplitude is *not* checked against: the truth.  At lmax 18 H1C's baselines (the shortest 14.6 m: l ~ 50
at 162 MHz) see the sky only through their beams' tails, along directions where the GSM prior's mean is small
against its spread, so the amplitude is set by the data's variance, not by the sky model's mean: the
amplitude-only run (``--beams off --gains off``) on the same twin with nominal dishes gives q = 0.0004 [0.00028,
0.00079] (truth 0.003), and the beam run 0.0005 [0.00032, 0.00075]: the block does not move it.  The amplitude
twins at lmax 100 (``tests/test_amplitude_twin.py``) recover it; the beam block's dense marginal stops at lmax 49.
"""

from __future__ import annotations

import json
import warnings

import h5py
import numpy as np
import pytest

pytest.importorskip("matvis")

from conftest import REAL  # noqa: E402

from gcrsky import cli  # noqa: E402
from gcrsky.checks.beamsim import scattered_beams  # noqa: E402
from gcrsky.checks.twin import make_twin  # noqa: E402
from gcrsky.instrument.beammodes import beam_modes, disc_radius, mode_maps  # noqa: E402
from gcrsky.instrument.beams import beam_amplitude, gaussian_beam  # noqa: E402

H1C = REAL / "zen.2458098.45361.HH_downselected.uvh5"
LMAX = 18
AMPLITUDE = 0.003  # the twin's bandpass q (the real file's scale)


@pytest.fixture(scope="module")
def pointed_twin(tmp_path_factory):
    scatter = scattered_beams(8, width_rms=0.0, offset_rms_rad=0.006, seed=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        twin = make_twin(H1C, None, channels=[40], lmax_sky=LMAX, nside_matvis=64, amplitude=AMPLITUDE, slope=0.0,
                         gain_amp=0.0, gain_phase_deg=0.0, beams=scatter.beams)
    assert twin.uvdata.vis_units == "uncalib"  # as the real file: the run infers the amplitude
    path = tmp_path_factory.mktemp("beams_twin") / "twin.uvh5"
    twin.uvdata.write_uvh5(str(path))
    return path, scatter


def _args(path, out, cache):
    return ["run", "--data", str(path), "--dish-diameter", "14", "--lmax", str(LMAX), "--pol", "xx",
            "--band-limit", "truncate", "--beams", "sample", "--beam-modes", "1", "--beam-burn", "10",
            "--nsamples", "40", "--batch", "20", "--out", str(out), "--no-plots", "--no-progress",
            "--compile-cache", str(cache)]


@pytest.fixture(scope="module")
def beam_run(pointed_twin, tmp_path_factory):
    """The uninterrupted run (its compiled programs cached for the killed one)."""
    base = tmp_path_factory.mktemp("beams_run")
    out = base / "run"
    assert cli.main(_args(pointed_twin[0], out, base / "cache")) == 0
    return out, base / "cache"


@pytest.mark.slow
def test_beams_sample_fits_dishes_that_point_their_own_way(pointed_twin, beam_run):
    path, scatter = pointed_twin
    out, _ = beam_run
    s = json.loads((out / "summary.json").read_text())
    b = s["beams"]
    # the negative control: the nominal beams are rejected by the same test ...
    assert b["fit_nominal"]["rejected"] and b["fit_nominal"]["chi2_per_dof"][0] > 2.0
    # ... and the block fits
    assert not s["goodness_of_fit"]["rejected"], s["goodness_of_fit"]["chi2_per_dof"]
    assert b["evidence"]["converged"] and b["evidence"]["log_bayes_factor"] > 100
    # the amplitude inferred with them: a Markov chain's draws, on the data's scale (not 1)
    q = s["flux_scale"]["per_channel"][0]
    assert s["flux_scale"]["source"] == "inferred" and not s["amplitude"]["independent_draws"]
    assert 1e-5 < q["lo95"] < q["median"] < q["hi95"] < 0.1, q
    east = np.array([c["tilt_east"]["mean"] for c in b["coefficients"]])
    north = np.array([c["tilt_north"]["mean"] for c in b["coefficients"]])
    assert np.corrcoef(east, scatter.offset_east_rad)[0, 1] > 0.7
    assert np.corrcoef(north, scatter.offset_north_rad)[0, 1] > 0.9
    assert 0.0 < b["acceptance"] <= 1.0
    with h5py.File(out / "results.h5", "r") as h:
        theta = h["beam_theta"][()]
        assert theta.shape == (40, 8, 2, 1) and np.all(np.isfinite(theta))
        assert h["draws"].shape[1] == 40
        q_draws, u, c = h["amplitude_q"][()], h["amplitude_u"][()], h["amplitude_c"][()]
        assert q_draws.shape == (40, 1) and np.allclose(q_draws * c[:, None], u)
    # the posterior-mean beams, one UVBeam per antenna, read back by pyuvdata: the model's A0 (1 + c . f)
    from pyuvdata import UVBeam

    files = sorted((out / "beams").glob("ant*.beamfits"))
    assert len(files) == 8
    mean = theta.mean(axis=0)[:, :, 0]  # (Nant, M)
    nums = [c["antenna"] for c in b["coefficients"]]
    uvb = UVBeam.from_file(str(out / "beams" / f"ant{nums[3]}.beamfits"))
    freqs = np.asarray(uvb.freq_array).reshape(-1)
    az, za = np.array([0.2, 1.7, 4.0]), np.array([0.03, 0.06, 0.09])
    nominal = gaussian_beam(14.0)
    modes = beam_modes(1)
    f = mode_maps(modes, az, za, disc_radius(nominal, freqs, modes))[0]
    expect = beam_amplitude(nominal, az, za, freqs)[0] * (1 + mean[3] @ f)
    assert np.allclose(beam_amplitude(uvb, az, za, freqs)[0], expect, rtol=1e-3)  # the 0.5 deg grid's interpolation


@pytest.mark.parametrize("extra, says", [
    (["--by-channel"], "one chain over all channels"),
])
def test_beams_sample_refuses_what_it_does_not_combine_with(extra, says, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["run", "--data", str(H1C), "--dish-diameter", "14", "--beams", "sample", *extra])
    assert e.value.code == 2 and says in capsys.readouterr().err


def test_beam_options_need_beams_sample_and_a_file(capsys):
    with pytest.raises(SystemExit):
        cli.main(["run", "--data", str(H1C), "--dish-diameter", "14", "--beam-sigma", "0.1"])
    assert "add --beams sample" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli.main(["run", "--beams", "sample"])
    assert "give --data FILE" in capsys.readouterr().err


def test_a_problem_too_large_for_both_forms_of_the_exact_marginal_is_refused_naming_them():
    """The marginal's dense matrix is the smaller of the sky's precision (n) and the data space's (N_d = 2 Nt Nbl):
    lmax 60 on H1C's 10 integrations takes the data space (N_d 560), and both large are refused."""
    from types import SimpleNamespace

    from gcrsky.run.beams import BEAM_DENSE_MAX_N, check_beam_problem, marginal_options
    from gcrsky.solvers import CholeskyOptions, DataSpaceOptions

    def prob(lmax, nt):
        return SimpleNamespace(config=SimpleNamespace(compressed=False), antpos_enu_m=np.zeros((8, 3)),
                               antpairs=np.array([[0, 1], [0, 2]]), n=(lmax + 1) ** 2, lmax=lmax,
                               data=np.zeros((1, nt, 28)))

    check_beam_problem(prob(60, 10), None)
    assert isinstance(marginal_options(prob(60, 10)), DataSpaceOptions)
    assert isinstance(marginal_options(prob(18, 10)), CholeskyOptions)
    with pytest.raises(ValueError, match="give --lmax 49 or less, or fewer times"):
        check_beam_problem(prob(60, 1 + BEAM_DENSE_MAX_N // 56), None)


@pytest.mark.slow
def test_a_killed_beam_run_resumes_to_the_uninterrupted_draws(pointed_twin, beam_run, tmp_path):
    """Killed after its first batch (the test hook: SIGKILL once batch 1 is in results.h5), the run resumes from the
    recorded proposal, chain state and amplitude (no new set-up) to the uninterrupted run's draws, bit for bit."""
    import os
    import subprocess
    import sys

    ref, cache = beam_run
    out = tmp_path / "killed"
    args = _args(pointed_twin[0], out, cache)
    env = {**os.environ, "GCRSKY_TEST_KILL_AFTER_BATCH": "1", "JAX_ENABLE_X64": "1"}
    p = subprocess.run([sys.executable, "-m", "gcrsky", *args], env=env, capture_output=True, text=True, timeout=900)
    assert p.returncode != 0, p.stdout[-2000:]  # killed by the hook after the first batch
    with h5py.File(out / "results.h5", "r") as h:
        assert int(h.attrs["batches_complete"]) == 1 and h["beam_theta"].shape[0] == 20
    assert cli.main([*args, "--resume"]) == 0
    with h5py.File(ref / "results.h5", "r") as a, h5py.File(out / "results.h5", "r") as b:
        for name in ("draws", "beam_theta", "beam_info/accept", "amplitude_q", "amplitude_u", "amplitude_c",
                     "wiener_filter", "beams/proposal_chol"):
            np.testing.assert_array_equal(a[name][()], b[name][()], err_msg=name)
