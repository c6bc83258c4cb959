"""JAX's persistent compilation cache: the CLI turns it on, the library never does; runs record compilation.

The subprocess tests run a small ``gcrsky run`` (lmax 8, nside 32, 8 draws) in fresh
processes, as a user's second run would be: the first fills the cache directory, the
second loads its programs from it (hits, less compile time), and ``--no-compile-cache``
writes nothing.  Timing checks are loose (the cores are shared).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from gcrsky.parallel import CompileStats
from gcrsky.parallel.runtime import COMPILE_CACHE_ENV, default_compile_cache_dir

ROOT = Path(__file__).resolve().parents[1]
SMALL = ["--lmax", "8", "--nside", "32", "--nsamples", "8", "--batch", "8", "--no-plots", "--no-progress"]


def _env(tmp_path, **extra) -> dict:
    """The test process's environment with the default cache directory moved into ``tmp_path``
    (``XDG_CACHE_HOME``: :func:`default_compile_cache_dir` then never looks at ``HOME``)."""
    env = dict(os.environ)
    for k in (COMPILE_CACHE_ENV, "JAX_COMPILATION_CACHE_DIR"):
        env.pop(k, None)
    env["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
    env.update(extra)
    return env


def _default_dir(tmp_path) -> Path:
    return tmp_path / "xdg" / "gcrsky" / "jax"


def _run(out, *options, env) -> dict:
    proc = subprocess.run([sys.executable, "-m", "gcrsky", "run", "--out", str(out), *SMALL, *options],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return json.loads((Path(out) / "summary.json").read_text()), proc.stdout


def _entries(d: Path) -> list:
    return sorted(p.name for p in d.iterdir() if p.name.endswith("-cache")) if d.is_dir() else []


@pytest.mark.slow
def test_second_run_loads_the_programs(tmp_path):
    cache = tmp_path / "cache"
    env = _env(tmp_path)
    first, _ = _run(tmp_path / "a", "--compile-cache", str(cache), env=env)
    written = _entries(cache)
    assert written, "the first run wrote no cache entries"
    t1 = first["timings_s"]
    assert t1["cache_misses"] > 0 and t1["compile_s"] > 0
    assert first["compile"]["cache_dir"] == str(cache.resolve())
    assert first["compile"]["cache_writes"] == len(written)  # every program is cached (no compile-time floor)

    second, stdout = _run(tmp_path / "b", "--compile-cache", str(cache), env=env)
    t2 = second["timings_s"]
    assert t2["cache_hits"] > 0
    assert t2["cache_misses"] == 0, "the same run compiled a program again: a cache key is not stable"
    assert t2["compile_s"] < t1["compile_s"]
    assert f"{t2['cache_hits']} hits" in stdout  # the printed summary says it too
    assert _entries(cache) == written  # nothing new
    assert not _default_dir(tmp_path).exists()  # --compile-cache, not the default


@pytest.mark.slow
def test_no_compile_cache_writes_nothing(tmp_path):
    env = _env(tmp_path, **{COMPILE_CACHE_ENV: str(tmp_path / "env-cache")},
               JAX_COMPILATION_CACHE_DIR=str(tmp_path / "jax-cache"))
    s, stdout = _run(tmp_path / "out", "--no-compile-cache", env=env)
    for d in (tmp_path / "env-cache", tmp_path / "jax-cache", _default_dir(tmp_path)):
        assert not d.exists(), d
    assert s["compile"]["cache_dir"] is None
    assert s["timings_s"]["cache_hits"] == s["timings_s"]["cache_misses"] == 0
    assert s["timings_s"]["compile_s"] > 0  # still recorded
    assert "compilation cache off" in stdout


@pytest.mark.slow
def test_the_command_defaults_to_the_user_cache_dir(tmp_path):
    """Without --compile-cache the command's set-up (``setup_jax``, before any computation) uses
    $GCRSKY_COMPILE_CACHE, else $XDG_CACHE_HOME/gcrsky/jax, with no compile-time floor."""
    code = textwrap.dedent(
        """
        import json
        from gcrsky import cli
        from gcrsky.cli.setup import setup_jax
        args = cli.build_parser().parse_args(["run"])
        setup_jax(args)
        import jax
        print(json.dumps([jax.config.jax_compilation_cache_dir, jax.config.jax_enable_compilation_cache,
                          jax.config.jax_persistent_cache_min_compile_time_secs]))
        """
    )
    for extra, want in (({}, _default_dir(tmp_path)),
                        ({COMPILE_CACHE_ENV: str(tmp_path / "mine")}, tmp_path / "mine")):
        out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=_env(tmp_path, **extra),
                             capture_output=True, text=True, timeout=300, check=True)
        path, enabled, min_s = json.loads(out.stdout.strip().splitlines()[-1])
        assert Path(path) == want.resolve() and enabled and min_s == 0.0
        assert want.is_dir()


@pytest.mark.slow
def test_importing_gcrsky_does_not_enable_the_cache(tmp_path):
    """The library leaves JAX's cache alone: importing gcrsky (and computing) sets no directory, writes nothing."""
    code = textwrap.dedent(
        """
        import json
        import jax
        jax.config.update("jax_enable_x64", True)
        import gcrsky
        import gcrsky.parallel, gcrsky.paper.pipeline, gcrsky.run
        prob = gcrsky.standard_case(lmax=4, nside=16)
        gcrsky.wiener_filter(prob).block_until_ready()
        print(json.dumps([jax.config.jax_compilation_cache_dir, jax.config.jax_persistent_cache_min_compile_time_secs]))
        """
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=_env(tmp_path), capture_output=True, text=True,
                         timeout=300, check=True)
    path, min_s = json.loads(out.stdout.strip().splitlines()[-1])
    assert path is None and min_s == 1.0  # JAX's defaults
    assert not _default_dir(tmp_path).exists()


def test_default_dir_precedence(tmp_path):
    home = str(tmp_path / "h")
    assert default_compile_cache_dir({"HOME": home}) == Path(home) / ".cache" / "gcrsky" / "jax"
    assert default_compile_cache_dir({"HOME": home, "XDG_CACHE_HOME": "/x"}) == Path("/x/gcrsky/jax")
    assert default_compile_cache_dir({"HOME": home, "XDG_CACHE_HOME": "/x", "JAX_COMPILATION_CACHE_DIR": "/j"}) \
        == Path("/j")
    both = {"HOME": home, "JAX_COMPILATION_CACHE_DIR": "/j", COMPILE_CACHE_ENV: "/g"}
    assert default_compile_cache_dir(both) == Path("/g")
    for off in ("off", "0", "None", "false", "no"):
        assert default_compile_cache_dir({**both, COMPILE_CACHE_ENV: off}) is None
    assert default_compile_cache_dir({"HOME": home, COMPILE_CACHE_ENV: "  "}) == Path(home) / ".cache/gcrsky/jax"


def test_compile_stats_span():
    a = CompileStats(1.0, 0.25, 0.5, 3, 1, 2, 2)
    b = CompileStats(4.0, 0.5, 0.75, 10, 5, 4, 4)
    assert b.since(a) == CompileStats(3.0, 0.25, 0.25, 7, 4, 2, 2)


def test_cli_options(tmp_path):
    from gcrsky import cli

    p = cli.build_parser()
    for cmd in (["run"], ["scenarios"]):
        a = p.parse_args([*cmd, "--compile-cache", str(tmp_path)])
        assert a.compile_cache == str(tmp_path) and not a.no_compile_cache
        assert p.parse_args([*cmd, "--no-compile-cache"]).no_compile_cache
        assert p.parse_args(cmd).compile_cache is None
        with pytest.raises(SystemExit):
            p.parse_args([*cmd, "--compile-cache", "x", "--no-compile-cache"])
