"""The README's snippets run as written (issue 26 item 6).

Before: the README told users to call ``gcrsky.parallel.use_safe_cpu_threading()`` right
after ``import gcrsky``, which raised ``AttributeError`` (the subpackage was not loaded).
Checked here, each in a fresh process where it matters:

* every ```` ```python ```` block, in order, as one script: ``test_readme_python_examples_run``
  (at a smaller nside, with checks of what the blocks make; here, not in tests/test_notebooks.py, so
  that pytest-xdist's ``--dist loadfile`` puts its ~2 minutes and the notebooks' on different workers);
* every ``gcrsky.NAME...`` the prose names in backticks resolves by attribute access from
  ``import gcrsky``, and the no-argument calls it names (``gcrsky.x.y()``) run;
* every ``gcrsky COMMAND ...`` line of the README parses with the command's own parser.

Negative controls: a name that does not exist, and a command with an option that does not
exist, fail the same checks.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from gcrsky.cli import build_parser

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()


def python_blocks(text: str) -> list[str]:  # run by test_readme_python_examples_run
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def named_attributes(text: str) -> list[str]:
    """``gcrsky.a.b`` in backticks (with or without ``()``), outside code blocks."""
    prose = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return sorted(set(re.findall(r"`(gcrsky(?:\.[A-Za-z_]\w*)+(?:\(\))?)`", prose)))


def command_lines(text: str) -> list[list[str]]:
    """``gcrsky run ...`` / ``gcrsky inspect ...`` lines: indented code lines and backticked spans."""
    lines = re.findall(r"^ {4}(gcrsky [a-z].*)$", text, flags=re.M)
    spans = re.findall(r"`(gcrsky (?:run|inspect|scenarios)(?: [^`|]*)?)`", text)
    # a span ending in a valued option (`gcrsky run --data`) names the option, it is not a command
    lines += [x for x in spans if not (x.split()[-1].startswith("--") and x.split()[-1] != "--help")]
    return [shlex.split(x)[1:] for x in lines]


def _run(code: str, cwd: Path, timeout: float = 1500) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=dict(os.environ, PYTHONPATH=str(REPO)))


def test_the_readme_has_what_these_tests_check():
    assert len(python_blocks(README)) >= 6
    assert "gcrsky.parallel.use_safe_cpu_threading()" in named_attributes(README)
    assert any(c[:1] == ["run"] and "--data" in c for c in command_lines(README))


RESOLVE = """
import functools, importlib, sys
import gcrsky

def resolve(name):  # a module path as users import it, then attributes
    parts = name.split(".")
    for k in range(len(parts), 0, -1):
        try:
            mod = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        return functools.reduce(getattr, parts[k:], mod)
    raise ImportError(name)

for name in sys.argv[1:]:
    if name.endswith("()"):  # a call the prose tells users to make right after `import gcrsky`: as written
        functools.reduce(getattr, name[:-2].split(".")[1:], gcrsky)()
    else:
        resolve(name)
print("ok")
"""


def test_named_attributes_resolve_and_calls_run(tmp_path):
    """In a fresh process: each name the prose gives resolves; the ``()`` ones are called as written, right after
    ``import gcrsky`` (``gcrsky.parallel.use_safe_cpu_threading()`` raised AttributeError before)."""
    env = dict(os.environ, PYTHONPATH=str(REPO), XDG_CACHE_HOME=str(tmp_path / "cache"))
    env.pop("GCRSKY_COMPILE_CACHE", None)
    proc = subprocess.run([sys.executable, "-c", RESOLVE, *named_attributes(README)], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stderr[-3000:]
    bad = _run("import gcrsky\ngcrsky.parallel.no_such_function()\n", tmp_path, timeout=300)  # control
    assert bad.returncode != 0 and "AttributeError" in bad.stderr


@pytest.mark.parametrize("argv", command_lines(README), ids=lambda a: " ".join(a)[:60])
def test_commands_parse(argv, capsys):
    if "--help" in argv:
        with pytest.raises(SystemExit) as e:
            build_parser().parse_args(argv)
        assert e.value.code == 0
        return
    build_parser().parse_args(argv)


def test_a_wrong_command_does_not_parse(capsys):
    with pytest.raises(SystemExit):
        build_parser().parse_args(["run", "--no-such-option"])


@pytest.mark.slow
def test_readme_python_examples_run(tmp_path, monkeypatch):
    """The README's Python blocks run as written (smaller nside/chain for speed; files into a temporary directory)."""
    import numpy as np

    blocks = python_blocks(README)
    assert len(blocks) >= 4
    code = "\n".join(blocks).replace("nside=128", "nside=32").replace("split(key, 1000)", "split(key, 20)")
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    exec(compile(code, "README.md", "exec"), ns)
    from pyuvdata import UVData

    uvd = UVData.from_file(str(tmp_path / "obs.uvh5"))  # the "your own data" example's file
    assert uvd.Nants_data == 10 and uvd.Ntimes == 10 and uvd.vis_units == "Jy"
    assert ns["draws"].shape == (2, 200, 441)
    assert ns["chain"].shape == (20, 2, 441)
    assert ns["real"].response.shape[-1] == (20 + 4 + 1) ** 2  # ICRS lmax 20 -> CIRS lmax 24
    assert ns["real"].data.shape == (2, 10, 45)
    assert np.all(np.isfinite(np.asarray(ns["chain"])))
    assert ns["fit"].converged and abs(float(ns["fit"].theta)) < 4 * float(ns["fit"].std)
    assert ns["cls"].shape == (200, 2, 21) and np.all(np.isfinite(np.asarray(ns["cls"])))
    assert np.all((np.asarray(ns["alphas"]) > 0) & (np.asarray(ns["alphas"]) < 6))
