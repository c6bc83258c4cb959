"""The package's shape: layers that import one way, no circles, a lean ``import gcrsky``, a short public API.

The import graph is parsed from the source with ``ast`` (gcrsky.checks.imports); every
import counts, also those inside functions.  Negative controls feed the checker a
circle and a core module importing an application, which it must flag, so these
tests can fail.
"""

from __future__ import annotations

import importlib
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import gcrsky
from gcrsky.checks.imports import (
    APPS,
    CORE,
    LAYERS,
    find_cycles,
    floors,
    import_graph,
    layer_of,
    layer_violations,
    modules_only,
    private_imports,
)

PKG = Path(gcrsky.__file__).parent
SUBPACKAGES = ("base", "sphere", "instrument", "model", "solvers", "inference", "parallel", "io", "ingest", "run", "sim", "paper",
               "checks", "cli")


@pytest.fixture(scope="module")
def graph():
    return import_graph(PKG)


def test_every_module_is_in_a_known_layer(graph):
    layers = {layer_of(m) for m in graph}
    assert layers <= set(LAYERS) | {"facade"}, layers - set(LAYERS)
    for sub in SUBPACKAGES:
        assert (PKG / sub / "__init__.py").is_file()
    assert not [p.name for p in PKG.glob("*.py") if p.stem not in ("__init__", "__main__")], (
        "top-level modules belong in a subpackage"
    )


def test_no_import_circles(graph):
    assert find_cycles(graph) == []


def test_imports_run_one_way(graph):
    assert layer_violations(graph) == []


def test_core_never_imports_an_application(graph):
    bad = [(m, d) for m, deps in graph.items() if layer_of(m) in CORE for d in deps if layer_of(d) in APPS]
    assert bad == []


def test_checker_flags_a_circle_and_an_upward_import(tmp_path):
    """Negative control: a toy package with a circle and a core -> app import."""
    pkg = tmp_path / "gcrsky"
    for sub in ("model", "sim"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "model" / "a.py").write_text("from . import b\n")
    (pkg / "model" / "b.py").write_text("def f():\n    from .a import g  # lazy, still an edge\n")
    (pkg / "model" / "c.py").write_text("from ..sim.x import y\n")
    (pkg / "sim" / "x.py").write_text("import numpy\ny = 1\n")
    g = import_graph(pkg)
    assert find_cycles(g) == [["gcrsky.model.a", "gcrsky.model.b"]]
    vio = layer_violations(g)
    assert [(v.importer, v.imported) for v in vio] == [("gcrsky.model.c", "gcrsky.sim"), ("gcrsky.model.c", "gcrsky.sim.x")]
    assert all("core layer 'model' imports application layer 'sim'" in v.why for v in vio)


#: What the file layer may import: the foundations, and the mode layout the alm FITS files are written in.
IO_MAY_IMPORT = ("base", "sphere", "io")


def _io_physics_imports(g) -> list[tuple[str, str]]:
    return sorted((m, d) for m, deps in g.items() if layer_of(m) == "io" for d in deps
                  if layer_of(d) not in IO_MAY_IMPORT)


def test_io_is_the_file_layer_without_physics(graph):
    """gcrsky.io reads and writes files: it imports base (and sphere's mode layout), never the instrument, the
    model, the solvers, the inference or the ingest above it (a lazy import inside a function counts too)."""
    assert LAYERS.index("io") <= 2 and LAYERS.index("io") < LAYERS.index("instrument")
    assert "gcrsky.io.visdata" in graph and "gcrsky.io.results" in graph
    assert _io_physics_imports(graph) == []


def test_io_check_flags_a_physics_import(tmp_path):
    """Negative control: a lazy ``from ..model.x import y`` and an ``import gcrsky.solvers.s`` inside io are found."""
    pkg = tmp_path / "gcrsky"
    for sub in ("io", "model", "solvers", "base"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "model" / "x.py").write_text("y = 1\n")
    (pkg / "solvers" / "s.py").write_text("z = 1\n")
    (pkg / "base" / "u.py").write_text("w = 1\n")
    (pkg / "io" / "a.py").write_text("from ..base.u import w\ndef f():\n    from ..model.x import y\n    return y\n")
    (pkg / "io" / "b.py").write_text("import gcrsky.solvers.s\n")
    got = _io_physics_imports(import_graph(pkg))
    assert got == [("gcrsky.io.a", "gcrsky.model"), ("gcrsky.io.a", "gcrsky.model.x"),
                   ("gcrsky.io.b", "gcrsky.solvers"), ("gcrsky.io.b", "gcrsky.solvers.s")]


def test_no_module_uses_another_modules_private_names():
    """A module's private names are its own: a helper two modules share is public where it belongs."""
    assert [f"{p.importer}:{p.line} uses {p.owner}.{p.name}" for p in private_imports(PKG)] == []


def test_checker_flags_private_names_used_across_modules(tmp_path):
    """Negative control: ``from .a import _x``, ``a._y`` (module bound by ``from . import a``) and a lazy
    ``from ..model.a import _z`` are flagged; a module's own ``_x`` and dunders are not."""
    pkg = tmp_path / "gcrsky"
    for sub in ("model", "sim"):
        (pkg / sub).mkdir(parents=True)
        (pkg / sub / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "model" / "a.py").write_text("_x = 1\n_y = 2\n_z = 3\n__all__ = []\nprint(_x)\n")
    (pkg / "model" / "b.py").write_text("from .a import _x, __all__\nfrom . import a\nv = a._y + a.__name__\n")
    (pkg / "sim" / "c.py").write_text("def f():\n    from ..model.a import _z\n    return _z\n")
    got = [(p.importer, p.owner, p.name) for p in private_imports(pkg)]
    assert got == [("gcrsky.model.b", "gcrsky.model.a", "_x"), ("gcrsky.model.b", "gcrsky.model.a", "_y"),
                   ("gcrsky.sim.c", "gcrsky.model.a", "_z")]


def test_floors_are_finite_and_the_core_is_below_the_apps(graph):
    fl = floors(modules_only(graph))
    assert min(fl.values()) == 0
    core_top = max(f for m, f in fl.items() if layer_of(m) in CORE)
    assert max(f for m, f in fl.items() if layer_of(m) == "cli") > core_top


def test_the_run_layer_imports_only_the_core_below_it(graph):
    """gcrsky.run (one run to disk) sits on ingest: it imports base .. ingest and itself, no application."""
    assert CORE[-2:] == ("ingest", "run") and APPS[0] == "sim"
    below = set(CORE)
    mods = [m for m in graph if layer_of(m) == "run"]
    assert "gcrsky.run.runner" in mods and "gcrsky.run.spec" in mods
    bad = [(m, d) for m in mods for d in graph[m] if layer_of(d) not in below]
    assert bad == []
    assert not [(m, d) for m in mods for d in graph[m] if layer_of(d) in ("sim", "checks", "paper", "cli")]


def _reach(graph, start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(graph.get(m, ()))
    return seen


def test_a_run_on_a_file_reaches_the_paper_only_through_its_hook(graph):
    """``gcrsky run --data``'s code (gcrsky.cli.cmd_data and all it imports) never imports gcrsky.sim, and of
    gcrsky.paper only the report hook it passes (with the metrics and figures that hook draws on)."""
    reached = _reach(graph, "gcrsky.cli.cmd_data")
    assert "gcrsky.run.runner" in reached and "gcrsky.paper.report" in reached
    assert not [m for m in reached if layer_of(m) == "sim"]
    assert {m for m in reached if layer_of(m) == "paper"} <= {
        "gcrsky.paper", "gcrsky.paper.report", "gcrsky.paper.metrics", "gcrsky.paper.figures"}
    assert not _reach(graph, "gcrsky.paper.report") & {"gcrsky.paper.pipeline", "gcrsky.paper.scenarios"}


def test_import_gcrsky_stays_lean():
    """``import gcrsky`` loads none of the application dependencies (nor healpy, which pulls in matplotlib),
    nor ducc0, nor SciPy's LAPACK: its OpenBLAS reads its thread count when it loads, and the LAPACK that JAX
    calls must load after ``use_safe_cpu_threading`` (a threaded ``dpotrf`` crashed above n = 14000; the
    HERA lmax 150 Cholesky segfaulted when a new module imported ``scipy.linalg`` at import time)."""
    code = textwrap.dedent(
        """
        import sys
        import gcrsky
        heavy = ('matplotlib', 'matvis', 'pygdsm', 'pyradiosky', 'healpy', 'tqdm', 'ducc0', 'scipy.linalg')
        print(sorted(m for m in heavy if m in sys.modules))
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


KEPT = ("standard_case", "build_problem", "Problem", "LinearSystem", "Prior", "wiener_filter", "sample", "prepare",
        "draw", "wiener_filter_system", "sample_system", "gcr_init", "gcr_step", "realify", "unrealify",
        "mode_table", "alm_to_map", "dense_matrix", "compress_problem", "isotropic_prior", "paper_prior",
        "flat_prior", "from_uvdata")


def test_public_api_is_short_sorted_and_complete():
    names = gcrsky.__all__
    assert names == sorted(names, key=lambda s: (not s[0].isupper(), s))
    # the user tier stays short: simulate or read a file, sample, map (41 before the solver registry; +2 for
    # choose_path, which fixes a path on concrete inputs for jit/vmap, and DataSpaceOptions beside the other
    # options; prepare_sampler became prepare_system, the old name resolves with a DeprecationWarning)
    assert len(names) <= 43
    assert "prepare_sampler" not in names
    assert set(KEPT) <= set(names)
    for n in names:
        assert getattr(gcrsky, n) is not None


@pytest.mark.parametrize("sub", SUBPACKAGES)
def test_subpackage_exports_resolve(sub):
    mod = importlib.import_module(f"gcrsky.{sub}")
    assert mod.__doc__ and len(mod.__doc__) > 40, f"gcrsky.{sub} needs a docstring saying what it holds"
    names = mod.__all__
    assert len(set(names)) == len(names)
    for n in names:
        if sub in ("paper", "checks"):  # submodules, imported on use
            importlib.import_module(f"gcrsky.{sub}.{n}")
        else:
            assert hasattr(mod, n), f"gcrsky.{sub}.__all__ names {n} but it is not defined"


def test_missing_extra_names_the_extra(monkeypatch):
    from gcrsky.base import require

    monkeypatch.setitem(sys.modules, "matvis", None)  # an import of it now fails
    with pytest.raises(ImportError, match=r"pip install 'gcrsky\[validate\]'"):
        require("matvis", "validate", "the matvis comparison")
