"""gcrsky: full-sky maps with honest uncertainties from drift-scan visibilities.

Gaussian constrained realisations of the sky's spherical-harmonic coefficients
(Glasscock et al. 2024), as pure JAX functions.  This namespace holds the user
tier; every primitive is reachable from its subpackage, which follow the data flow:

- :mod:`gcrsky.base`: dtype policy, memory budgets, units;
- :mod:`gcrsky.sphere`: the realified mode layout, harmonics, rotations, frames, maps;
- :mod:`gcrsky.instrument`: antenna arrays, beams, the response, redundancy;
- :mod:`gcrsky.model`: visibility operator, noise, priors, the linear system, problems;
- :mod:`gcrsky.solvers`: the exact paths (CG, Cholesky / eigh, m-mode) and the planner;
- :mod:`gcrsky.inference`: Wiener filter, draws, batches, the Gibbs kernel;
- :mod:`gcrsky.parallel`: sharding over devices; :mod:`gcrsky.io`: results on disk;
- applications: :mod:`gcrsky.sim` (truth skies, the standard case),
  :mod:`gcrsky.paper` (scenarios, metrics, figures, the run pipeline),
  :mod:`gcrsky.checks` (matvis validation, simulation-based calibration) and the
  ``gcrsky`` command line (:mod:`gcrsky.cli`).

Conventions: ``docs/conventions.md``.  ``import gcrsky`` does not import matplotlib,
matvis, pygdsm or pyradiosky (nor healpy, which would import matplotlib).
"""

from .inference.api import prepare, sample, wiener_filter
from .inference.cl import cl_hat, sample_cl
from .inference.evidence import log_evidence
from .inference.gibbs import GCRState, gcr_init, gcr_step
from .inference.hyper import fit_hyperparameters
from .inference.posterior import draw, prepare_system, sample_system, wiener_filter_system
from .ingest.uvdata import from_uvdata
from .model.compress import compress_problem, compress_system
from .model.operator import VisOperator, dense_matrix
from .model.prior import Prior, flat_prior, isotropic_prior, paper_prior, power_law_cl, prior_from_cl
from .model.problem import Problem, build_problem
from .model.system import LinearSystem, check_system
from .model.template import spectral_template_system
from .sim.config import Config
from .sim.standard import standard_case
from .solvers.info import SolveInfo
from .solvers.options import CGOptions, CholeskyOptions, DataSpaceOptions, EighOptions, MModeOptions
from .solvers.plan import choose_path
from .sphere.maps import alm_to_map
from .sphere.modes import mode_table, realify, unrealify

__all__ = [
    "CGOptions",
    "CholeskyOptions",
    "Config",
    "DataSpaceOptions",
    "EighOptions",
    "GCRState",
    "LinearSystem",
    "MModeOptions",
    "Prior",
    "Problem",
    "SolveInfo",
    "VisOperator",
    "alm_to_map",
    "build_problem",
    "check_system",
    "choose_path",
    "cl_hat",
    "compress_problem",
    "compress_system",
    "dense_matrix",
    "draw",
    "fit_hyperparameters",
    "flat_prior",
    "from_uvdata",
    "gcr_init",
    "gcr_step",
    "isotropic_prior",
    "log_evidence",
    "mode_table",
    "paper_prior",
    "power_law_cl",
    "prepare",
    "prepare_system",
    "prior_from_cl",
    "realify",
    "sample",
    "sample_cl",
    "sample_system",
    "spectral_template_system",
    "standard_case",
    "unrealify",
    "wiener_filter",
    "wiener_filter_system",
]

__version__ = "0.1.0"


#: Subpackages reachable as attributes (``gcrsky.parallel.use_safe_cpu_threading()`` right after ``import gcrsky``),
#: imported on first use so that ``import gcrsky`` stays light.
SUBPACKAGES = ("base", "checks", "cli", "inference", "instrument", "io", "model", "paper", "parallel", "run", "sim",
               "solvers", "sphere")


def __getattr__(name):
    """A subpackage on first use (:data:`SUBPACKAGES`); ``gcrsky.prepare_sampler``: the old name of
    :func:`prepare_system` (deprecated; not in ``__all__``)."""
    if name in SUBPACKAGES:
        import importlib

        return importlib.import_module(f"{__name__}.{name}")
    if name == "prepare_sampler":
        from .inference.posterior import prepare_sampler

        return prepare_sampler
    raise AttributeError(f"module 'gcrsky' has no attribute {name!r}")
