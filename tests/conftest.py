"""Shared pytest configuration and fixtures for gcrsky's tests.

* float64 everywhere: x64 is enabled at import, before any array is created
  (gcrsky's normal matrices reach condition numbers ~1e9).
* one persistent JAX compilation cache per test session, for the command line's runs (a fresh directory; see
  ``_session_compile_cache``), and
  JAX's compiled programs dropped after each test file (``_release_compiled_programs``).
* XLA's backend optimisation off (``JAX_DISABLE_MOST_OPTIMIZATIONS=1``; see ``_cheap_compiles``): most of the
  suite's time is compilation of programs that then run once or a few times.
* ``getkey``: a function returning fresh PRNG keys from a fixed seed (lineax
  style), so every test is reproducible and independent of test order.
* Session-scoped small problem (10-antenna hexagon, lmax 6, nside 32,
  100 and 102 MHz) shared by several test modules: ``small_array`` and
  ``small_response``.  nside 32, not 16: the longest baselines (43.8 m, ~15
  wavelengths) alias at nside 16 (the response then disagrees with its own
  rotation by ~75%, see ``test_operator.py::test_rotation_equals_recomputed_response``);
  at nside 32 the quadrature is good to ~2e-8 and costs the same (<1 s).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import NamedTuple

#: The real telescope files (../shared/data/real next to the repository, see its README): tests that
#: read them skip where they are absent.
REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
H1C = REAL / "zen.2458098.45361.HH_downselected.uvh5"
H1C_CAL = REAL / "zen.2458098.45361.HH.omni_downselected.calfits"
H2C = REAL / "zen.2458432.34569.uvh5"
HERABEAM = REAL / "HERABEAM.FITS"


def _safe_threading():
    """gcrsky.parallel.runtime.use_safe_cpu_threading, loaded from its file (standard library only) so
    that it runs before NumPy and JAX load: the Eigen-pool flag, and XLA's CPU pool sized so batched
    LAPACK cannot deadlock (see that module)."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "gcrsky" / "parallel" / "runtime.py"
    spec = importlib.util.spec_from_file_location("_gcrsky_runtime", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.use_safe_cpu_threading()


_safe_threading()


#: Environment variable naming the test session's compilation cache directory (``off``: none); set by the
#: controlling pytest process (:func:`_session_compile_cache`) and inherited by its workers and subprocesses.
TEST_CACHE_ENV = "GCRSKY_TEST_COMPILE_CACHE"


def _session_compile_cache():
    """One persistent JAX compilation cache for the whole test session, in a fresh temporary directory removed at
    its end: ``GCRSKY_COMPILE_CACHE`` names it, inherited by the xdist workers and the subprocess tests.

    The command line turns JAX's persistent cache on for its process (``gcrsky.parallel.use_compile_cache``), and
    the suite runs ``gcrsky run`` in ~100 subprocesses that compile the same programs: sharing them cut
    tests/test_gains_cli.py from 151 to 108 s.  The tests never read or fill the user's cache (a fresh directory
    per session; ``GCRSKY_TEST_COMPILE_CACHE=off`` turns it off; tests/test_compile_cache.py sets its own).
    (The worker crashes first blamed on the cache, inside JAX's cache read and write, recurred with the cache
    off: they were the exhaustion of memory mappings that ``_release_compiled_programs`` prevents.)
    """
    import atexit
    import os
    import shutil
    import tempfile

    if TEST_CACHE_ENV not in os.environ:  # the controlling process (or a single one): make the session's
        if os.environ.get("PYTEST_XDIST_WORKER"):
            os.environ[TEST_CACHE_ENV] = "off"
        else:
            path = tempfile.mkdtemp(prefix="gcrsky-test-jax-cache-")
            os.environ[TEST_CACHE_ENV] = path
            atexit.register(shutil.rmtree, path, True)
    os.environ["GCRSKY_COMPILE_CACHE"] = os.environ[TEST_CACHE_ENV]


_session_compile_cache()


def _cheap_compiles():
    """``JAX_DISABLE_MOST_OPTIMIZATIONS=1`` unless set (``=0`` restores XLA's defaults), inherited by the
    subprocess tests: LLVM at -O0 without its expensive passes (``xla_backend_optimization_level=0``,
    ``xla_llvm_disable_expensive_passes``).  The HLO passes (fusion, buffer assignment: what the memory tests
    read from XLA's analysis) are unchanged and there is no fast-math either way; only where LLVM contracts
    ``a * b + c`` into an FMA may differ, i.e. results in the last bits.
    Measured (user + sys CPU seconds of ``pytest -n 0``, default -> this, run side by side on the shared
    2-core machine, all passing both ways): tests/test_gradients.py 198.8 -> 126.0; test_dataspace.py -k
    "estimate_bounds or wiener_filter_equals or rows_formed" 141.8 -> 85.6; test_dataspace_proxy.py -k
    "memory_estimate or differentiates or equal_the_general" 254.7 -> 147.9; test_notebooks.py -k "gibbs or
    point_sources" (chains of 1500 steps: run time, not compilation) 70.6 -> 56.0; 666 -> 416 in all (-38 %).
    On a quiet machine, back to back: tests/test_dataspace.py 175.1 -> 102.4; test_notebooks.py -k "hyper or
    standard or quick" 134.2 -> 101.3.
    """
    import os

    os.environ.setdefault("JAX_DISABLE_MOST_OPTIMIZATIONS", "1")


_cheap_compiles()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

try:
    import gcrsky  # noqa: F401
except ImportError:  # running from a checkout without an install
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import pytest

from gcrsky.instrument import (
    HERA_LATITUDE_DEG,
    AntennaArray,
    antpairs,
    gaussian_beam,
    hex_array,
    make_array,
    response_matrix,
)

#: The small shared problem (cheap: the response builds in well under a second).
SMALL_LMAX = 6
SMALL_NSIDE = 32
SMALL_FREQS_HZ = (100e6, 102e6)
SMALL_DISH_M = 14.0


def _map_count() -> int:
    """Memory mappings of this process (Linux; 0 elsewhere)."""
    try:
        with open("/proc/self/maps") as fh:
            return sum(1 for _ in fh)
    except OSError:
        return 0


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test file (``jax.clear_caches``).

    Every XLA:CPU program JIT-links its code into ~27 memory mappings of its own, kept as long as the
    program is cached, and a worker process compiles thousands over the suite.  Linux refuses a process
    more than ``vm.max_map_count`` mappings (65530 by default): LLVM's section allocation then fails
    (``report_fatal_error`` in ``RuntimeDyldImpl::emitSection``, an abort) or a ``malloc`` does (a
    segmentation fault), inside ``backend_compile_and_load``.  That was the worker crash of three suite
    runs (the core file of one held 65531 mappings).  Clearing per file bounds the live programs by one
    file's; the shared session fixtures are arrays, not programs, and stay.
    """
    yield
    jax.clear_caches()
    import gc

    gc.collect()
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return
    if _map_count() > limit // 2:
        import warnings

        warnings.warn(f"this test process still holds {_map_count()} memory mappings after clearing JAX's caches "
                      f"(the kernel's limit is {limit}): something keeps compiled programs alive", stacklevel=1)


@pytest.fixture
def getkey():
    """Return a function giving a fresh PRNG key on every call, from a fixed seed."""
    state = {"key": jax.random.PRNGKey(20240611)}

    def _getkey() -> jax.Array:
        state["key"], sub = jax.random.split(state["key"])
        return sub

    return _getkey


@pytest.fixture(scope="session")
def small_array() -> AntennaArray:
    """The paper's 10-antenna hexagon (rows 3-4-3, 14.6 m) of 14 m Gaussian dishes at HERA."""
    return make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(SMALL_DISH_M))


class SmallResponse(NamedTuple):
    """A response matrix together with everything it was built from.

    Attributes:
        response: (Nf, Nbl, n) complex response at ``lst_ref_rad = 0``.
        array: the :class:`gcrsky.instrument.AntennaArray`.
        pairs: (Nbl, 2) cross-correlation antenna pairs (45 for 10 antennas).
        freqs_hz: (Nf,) frequencies in Hz.
        lmax, nside: degree and HEALPix nside of the quadrature.
    """

    response: jax.Array
    array: AntennaArray
    pairs: np.ndarray
    freqs_hz: np.ndarray
    lmax: int
    nside: int


@pytest.fixture(scope="session")
def small_response(small_array) -> SmallResponse:
    """Cross-correlation response of ``small_array`` at lmax 6, nside 32, 100 and 102 MHz."""
    pairs = antpairs(small_array.positions_enu_m.shape[0])
    freqs = np.asarray(SMALL_FREQS_HZ)
    resp = response_matrix(small_array, pairs, freqs, SMALL_LMAX, SMALL_NSIDE)
    return SmallResponse(resp, small_array, pairs, freqs, SMALL_LMAX, SMALL_NSIDE)


def isotropic_problem(small_array, small_response, lsts, seed: int, *, cl_scale: float = 50.0):
    """A Problem on ``small_array`` at ``lsts`` (radians): an isotropic prior ``C_l = cl_scale / (1 + l)^2``,
    a truth drawn from it with ``seed``, noise sigma 0.05, simulated data (the tests' small posterior)."""
    from gcrsky.model import build_problem, isotropic_prior

    lmax, nside, freqs = small_response.lmax, small_response.nside, small_response.freqs_hz
    n, nf = (lmax + 1) ** 2, freqs.size
    cl = np.tile(cl_scale / (1.0 + np.arange(lmax + 1)) ** 2, (nf, 1))
    prior = isotropic_prior(cl, n)
    truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(seed).standard_normal((nf, n))
    return build_problem(small_array, freqs, lsts, lmax, nside, a_true=truth, sigma=0.05, prior=prior,
                         key=jax.random.PRNGKey(seed))
