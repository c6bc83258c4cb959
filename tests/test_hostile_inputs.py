"""Hostile and careless inputs (issue 26): each gets one clear message and an exit status, before expensive work.

Tried before the fixes against ``gcrsky run`` / ``gcrsky inspect``: corrupt, empty,
truncated or bit-flipped files, a directory or another kind of file in the place of one,
absurd options and unusable output paths gave 30 raw tracebacks; unusable data (flagged
autocorrelations, zero or negative channel widths or integration times) gave prior-only
"results" with exit 0; a file run whose quadrature could not resolve its baselines' fringes
(``--lmax 8 --nside 16``) was 182 % off without a word.  Here every such input must give exit
status 2 (:data:`gcrsky.cli.EXIT_USAGE`), a message on stderr that names the cause, no
exception escaping :func:`gcrsky.cli.main` (in-process, a traceback would be an exception),
and nothing written into ``--out``.  A full disk must end with a message and leave the batches
written, which ``--resume`` completes to exactly an uninterrupted run's draws; a file-size limit
(``ulimit -f``) too small for the draws is refused before the first draw.

Also here and elsewhere: concurrent runs into one directory (``tests/test_run_lock.py``), NaN
and negative inputs to the pure tier (``tests/test_pure_checks.py``), an unreachable
coordinator (``tests/test_distributed_failfast.py``), beam files (``tests/test_beam_inputs.py``).
"""

from __future__ import annotations

import os
import random
import re
import resource
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matvis")

from gcrsky import cli  # noqa: E402
from gcrsky.checks.matvis import HERA_SITE, observing_times, random_sky, site  # noqa: E402
from gcrsky.checks.uvsim import simulate_uvdata  # noqa: E402
from gcrsky.instrument import gaussian_beam, hex_array  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
LMAX = 6
DATA_OPTS = ["--nsamples", "4", "--batch", "2", "--no-progress", "--no-plots", "--band-limit", "truncate",
             "--flux-scale", "accept", "--lmax", str(LMAX), "--nside", "32"]
SIM_OPTS = ["--nsamples", "4", "--batch", "2", "--no-progress", "--no-plots", "--lmax", "8", "--nside", "32"]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A valid UVH5 file and what a careless user might pass instead (module docstring)."""
    from astropy.io import fits
    from pyuvdata import UVData

    d = tmp_path_factory.mktemp("hostile")
    good = d / "obs.uvh5"
    sim = simulate_uvdata(hex_array((2, 3, 2)), site(*HERA_SITE), observing_times("2025-03-21T18:00:00", 3.0, 6),
                          np.array([100e6, 101e6]), gaussian_beam(14.0), random_sky(LMAX, 3), LMAX, nside_matvis=32)
    sim.uvdata.write_uvh5(str(good))
    raw = good.read_bytes()
    (d / "empty.uvh5").write_bytes(b"")
    (d / "corrupt.uvh5").write_bytes(random.Random(0).randbytes(len(raw)))
    (d / "truncated.uvh5").write_bytes(raw[: len(raw) // 2])
    flipped = bytearray(raw)
    for i in random.Random(1).sample(range(2048, len(raw)), 200):
        flipped[i] ^= 0xFF
    (d / "flipped.uvh5").write_bytes(bytes(flipped))
    (d / "adir").mkdir()
    fits.HDUList([fits.PrimaryHDU(np.ones((8, 8)))]).writeto(d / "image.fits")  # a FITS file, not a beam or map
    (d / "truncated.fits").write_bytes((d / "image.fits").read_bytes()[:3000])
    (d / "empty.fits").write_bytes(b"")
    (d / "afile").write_text("x")
    os.symlink(d / "nowhere" / "x", d / "dangling")

    def variant(name, edit):
        u = UVData.from_file(str(good))
        edit(u)
        u.write_uvh5(str(d / f"{name}.uvh5"), run_check=False)

    autos = lambda u: u.ant_1_array == u.ant_2_array  # noqa: E731
    variant("autoflag", lambda u: u.flag_array.__setitem__(autos(u), True))
    variant("zerowidth", lambda u: setattr(u, "channel_width", 0 * u.channel_width))
    variant("negwidth", lambda u: setattr(u, "channel_width", -np.abs(u.channel_width)))
    variant("zerotime", lambda u: u.integration_time.__setitem__(slice(None), 0.0))
    variant("allflag", lambda u: u.flag_array.__setitem__(slice(None), True))
    variant("zeronsample", lambda u: u.nsample_array.__setitem__(slice(None), 0.0))
    return d


def _data(d, name, *extra, beam=("--dish-diameter", "14")):
    return ["run", "--data", str(d / name), *beam, "--out", str(d / "out" / name.replace(".", "_")), *DATA_OPTS,
            *extra]


def _sim(d, out, *extra):
    return ["run", *SIM_OPTS, "--out", str(out), *extra]


# (id, argv from the files' directory, the message's words (regex))
CASES = [
    ("data-corrupt", lambda d: _data(d, "corrupt.uvh5"), r"corrupt\.uvh5 cannot be read as a visibility file"),
    ("data-empty", lambda d: _data(d, "empty.uvh5"), r"empty\.uvh5 is empty \(0 bytes\)"),
    ("data-truncated", lambda d: _data(d, "truncated.uvh5"), r"cannot be read as a visibility file.*truncated file"),
    ("data-bitflipped", lambda d: _data(d, "flipped.uvh5"), r"flipped\.uvh5 cannot be read as a visibility file"),
    ("data-directory", lambda d: _data(d, "adir"), r"adir holds no visibility file"),
    ("data-missing", lambda d: _data(d, "nope.uvh5"), r"no visibility file at .*nope\.uvh5"),
    ("data-is-a-fits-image", lambda d: _data(d, "image.fits"), r"image\.fits cannot be read as a visibility file"),
    ("beam-empty", lambda d: _data(d, "obs.uvh5", beam=("--beam", str(d / "empty.fits"))),
     r"--beam: beam file .*empty\.fits is empty"),
    ("beam-truncated", lambda d: _data(d, "obs.uvh5", beam=("--beam", str(d / "truncated.fits"))),
     r"truncated\.fits"),
    ("beam-is-visibilities", lambda d: _data(d, "obs.uvh5", beam=("--beam", str(d / "obs.uvh5"))),
     r"obs\.uvh5.*beam"),
    ("prior-directory", lambda d: _data(d, "obs.uvh5", "--prior", str(d / "adir")),
     r"--prior: .*adir is a directory, not a prior file"),
    ("prior-not-a-map", lambda d: _data(d, "obs.uvh5", "--prior", str(d / "image.fits")),
     r"image\.fits cannot be read as a prior"),
    ("quadrature-too-coarse", lambda d: _data(d, "obs.uvh5", "--nside", "16"),
     r"nside 16 cannot resolve the response: .* reach l = \d+ .*use --nside 32"),
    ("autos-flagged", lambda d: _data(d, "autoflag.uvh5"),
     r"no unflagged sample has a noise estimate .* autocorrelations are flagged or missing"),
    ("zero-channel-width", lambda d: _data(d, "zerowidth.uvh5"), r"the channel width is 0 Hz"),
    ("negative-channel-width", lambda d: _data(d, "negwidth.uvh5"), r"the channel width is -\d+ Hz"),
    ("zero-integration-time", lambda d: _data(d, "zerotime.uvh5"), r"the integration time is 0 s"),
    ("all-flagged", lambda d: _data(d, "allflag.uvh5"), r"every cross-correlation sample .* is flagged"),
    ("zero-nsample", lambda d: _data(d, "zeronsample.uvh5"), r"nsample of every unflagged sample is zero"),
    ("inspect-corrupt", lambda d: ["inspect", str(d / "corrupt.uvh5")], r"cannot be read as a visibility file"),
    ("inspect-empty", lambda d: ["inspect", str(d / "empty.uvh5")], r"is empty \(0 bytes\)"),
    ("inspect-truncated", lambda d: ["inspect", str(d / "truncated.uvh5")], r"truncated file"),
    ("inspect-directory", lambda d: ["inspect", str(d / "adir")], r"adir holds no visibility file"),
    ("lmax-beyond-nside", lambda d: ["run", "--lmax", "3000", "--out", str(d / "out" / "l3000")],
     r"nside=128 cannot resolve lmax=3000"),
    ("response-beyond-memory", lambda d: _sim(d, d / "out" / "l5000", "--lmax", "5000", "--nside", "2048"),
     r"the response .* needs ~[\d.]+ [GT]iB but only"),
    ("nside-65536", lambda d: _sim(d, d / "out" / "n65536", "--nside", "65536"), r"nside 65536 grid .* needs"),
    ("draws-beyond-disk", lambda d: ["run", "--nsamples", "1000000000000", "--lmax", "8", "--nside", "32",
                                     "--no-progress", "--no-plots", "--out", str(d / "out" / "many")],
     r"the draws need [\d.]+ [A-Z]iB but the disk of .* has"),
    ("seed-23-digits", lambda d: _sim(d, d / "out" / "seed", "--seed", "12345678901234567890123"),
     r"seed must be >= 0 and <= 9223372036854775807"),
    ("dish-1e-9", lambda d: _sim(d, d / "out" / "dish-", "--dish-diameter", "1e-9"),
     r"dish_diameter 1e-09 m gives a beam FWHM .* wider than the sky"),
    ("dish-1e9", lambda d: _sim(d, d / "out" / "dish+", "--dish-diameter", "1e9"),
     r"narrower than a pixel of the nside 32 grid"),
    ("noise-1e-300", lambda d: _sim(d, d / "out" / "noise", "--noise-scale", "1e-300"),
     r"noise_scale 1e-300 is outside"),
    ("out-is-a-file", lambda d: _sim(d, d / "afile"), r"--out .*afile is a file, not a directory"),
    ("out-under-a-file", lambda d: _sim(d, d / "afile" / "sub"), r"cannot be created: .*afile is a file"),
    ("out-dangling-symlink", lambda d: _sim(d, d / "dangling"), r"dangling is a symbolic link to .*does not exist"),
]


def _main(argv) -> int:
    """``gcrsky.cli.main``'s exit status, argparse's own exits included (an exception escaping is a failure)."""
    try:
        return cli.main(argv)
    except SystemExit as e:
        return e.code


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_gives_one_clear_message(case, files, capsys):
    name, argv, words = case
    args = argv(files)
    rc = _main(args)
    err = capsys.readouterr().err
    assert rc == cli.EXIT_USAGE, (rc, err[-2000:])
    assert "Traceback" not in err
    assert re.search(words, err, flags=re.S), err[-2000:]
    if "--out" in args:  # refused before anything was written there
        out = Path(args[args.index("--out") + 1])
        assert not out.is_dir() or not any(p.name in ("results.h5", "summary.json") for p in out.iterdir())


def test_verbose_adds_the_traceback(files, capsys):
    assert cli.main([*_data(files, "corrupt.uvh5"), "-v"]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "Traceback" in err and "cannot be read as a visibility file" in err


def test_valid_file_still_runs(files, capsys):
    """Negative control: the same options on the valid file run to the end (exit 0)."""
    assert cli.main(_data(files, "obs.uvh5")) == 0, capsys.readouterr().err[-2000:]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_read_only_out(tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        assert cli.main(_sim(tmp_path, ro / "run")) == cli.EXIT_USAGE
        err = capsys.readouterr().err
        assert "cannot be written" in err and "Traceback" not in err
    finally:
        ro.chmod(0o755)


def test_file_size_limit_refused_up_front(tmp_path):
    """``ulimit -f`` smaller than the draws: refused before the first draw, naming the limit (exit 2)."""
    out = tmp_path / "run"
    limit = 200_000

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    p = subprocess.run([sys.executable, "-m", "gcrsky", "run", "--out", str(out), *SIM_OPTS, "--nsamples", "400"],
                       env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=600,
                       preexec_fn=small_files)
    assert p.returncode == cli.EXIT_USAGE, (p.returncode, p.stderr[-3000:])
    assert "ulimit -f" in p.stderr and "Traceback" not in p.stderr
    assert not (out / "results.h5").exists()


def test_a_tight_address_space_limit_is_the_memory_message(tmp_path, monkeypatch):
    """``ulimit -v 1000000`` aborted the run in XLA's thread creation (SIGABRT, rc -6: no Python handler runs);
    at ~2 GB (here) a shared library failed to load later ("Could not find/load shared object file").  Now a
    child process tries XLA's start-up first, and a load or allocation failure under a limit names it: one
    message naming the limit and the remedy, exit 2.  The controls: no limit is every other run of the suite,
    and the same OSError without a limit keeps its own message."""
    from gcrsky.cli import errors

    limit = 2**30

    def tight():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    out = tmp_path / "run"
    p = subprocess.run([sys.executable, "-m", "gcrsky", "run", "--out", str(out), *SIM_OPTS],
                       env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=600,
                       preexec_fn=tight)
    assert p.returncode == cli.EXIT_USAGE, (p.returncode, p.stderr[-3000:])
    assert re.search(r"address-space limit \(ulimit -v \d+ KiB = 1\.\d GiB\).*raise the limit", p.stderr), p.stderr[-3000:]
    assert "Traceback" not in p.stderr and "Check failure stack trace" not in p.stderr
    # the later failure (the limit set by the shell, ~2 GB), and the control without a limit
    lib = OSError("Could not find/load shared object file")
    assert errors.error_message(lib) == "Could not find/load shared object file"
    monkeypatch.setattr(errors, "address_space_limit", lambda: 2 * 10**9)
    assert re.match(r"OSError: Could not find/load shared object file under this shell's address-space limit "
                    r"\(ulimit -v 1953125 KiB = 1\.9 GiB\).*ulimit -v unlimited", errors.error_message(lib))


def test_disk_full_mid_run_then_resume(tmp_path, capsys, monkeypatch):
    """The disk fills after two batches (the free space the next append sees is 1 kB): exit 2 with a message,
    the two batches kept; with space again, ``--resume`` ends with exactly an uninterrupted run's draws."""
    import shutil
    from collections import namedtuple

    import gcrsky.io.results as results
    from gcrsky.io import read_draws, read_results_state

    argv = ["run", *SIM_OPTS, "--nsamples", "8"]
    assert cli.main([*argv, "--out", str(tmp_path / "ref")]) == 0
    real = shutil.disk_usage
    usage = namedtuple("usage", "total used free")
    h5 = tmp_path / "run" / "results.h5"

    def filling(path):  # room for two batches, then none
        if h5.exists() and read_results_state(h5).batches_complete >= 2:
            return usage(10**9, 10**9 - 1000, 1000)
        return real(path)

    monkeypatch.setattr(results.shutil, "disk_usage", filling)
    out = tmp_path / "run"
    assert cli.main([*argv, "--out", str(out)]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "no space left" in err and "--resume" in err and "Traceback" not in err, err[-2000:]
    assert read_results_state(out / "results.h5").batches_complete == 2
    monkeypatch.undo()
    assert cli.main([*argv, "--out", str(out), "--resume"]) == 0
    a, b = read_draws(out / "results.h5").draws, read_draws(tmp_path / "ref" / "results.h5").draws
    assert a.tobytes() == b.tobytes()


def test_hdf5_s_runtime_error_is_a_read_error_naming_the_file(tmp_path):
    """HDF5 raises RuntimeError for a damaged symbol table (a held-out bit-flipped UVH5 ended ``run`` and
    ``inspect`` in a traceback): the reader's context turns it into a ValueError naming the file."""
    from gcrsky.io.files import reading

    with pytest.raises(ValueError, match=r"x\.uvh5 cannot be read as a visibility file \(RuntimeError: Unable to get "
                                         r"group info \(bad symbol table node signature\)\)"):
        with reading(tmp_path / "x.uvh5", "a visibility file", "UVH5"):
            raise RuntimeError("Unable to get group info (bad symbol table node signature)")


def test_a_nan_in_a_prior_cl_file_names_the_file_and_l(tmp_path):
    from gcrsky.ingest.prior import read_cl_file

    cl = np.column_stack([np.arange(11), 1.0 / (1.0 + np.arange(11)) ** 2])
    cl[7, 1] = np.nan
    path = tmp_path / "cl.txt"
    np.savetxt(path, cl)
    with pytest.raises(ValueError, match=r"cl\.txt: C_l must be finite and >= 0; spectrum 0 holds nan at l = 7"):
        read_cl_file(path, 1, 10)
    assert read_cl_file(path, 1, 6).shape == (1, 7)  # the control: the NaN above lmax is not read
