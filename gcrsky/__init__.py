"""gcrsky: full-sky maps with honest uncertainties from drift-scan visibilities.

Gaussian constrained realisations of the sky's spherical-harmonic coefficients
(Glasscock et al. 2024), as pure JAX functions.  Conventions: README.md.
"""

from .api import choose_path, prepare, sample, wiener_filter
from .layout import ModeTable, alm_to_map, mode_table, n_params, realify, unrealify
from .frames import FrameMap, observing_geometry
from .noise import weights_from_flags
from .normal import LinearSystem, precision_apply, precision_matrix
from .operator import VisOperator, adjoint, apply, dense_matrix
from .plan import InsufficientMemoryError, SamplerPlan, plan_sampler
from .prior import Prior, flat_prior, isotropic_prior, paper_prior
from .problem import Config, Problem, build_problem, standard_case
from .redundancy import (
    RedundantGroups,
    compress_problem,
    compress_system,
    groups_for_array,
    redundant_groups,
    redundant_responses,
)
from .rotation import rotate, rotate_euler, wigner_blocks
from .sampler import (
    GCRState,
    PreparedSampler,
    SolveInfo,
    draw,
    gcr_init,
    gcr_step,
    prepare_sampler,
    sample_system,
    wiener_filter_system,
)

__all__ = [
    "Config",
    "FrameMap",
    "GCRState",
    "InsufficientMemoryError",
    "LinearSystem",
    "PreparedSampler",
    "ModeTable",
    "Prior",
    "Problem",
    "RedundantGroups",
    "SamplerPlan",
    "SolveInfo",
    "VisOperator",
    "adjoint",
    "alm_to_map",
    "apply",
    "build_problem",
    "choose_path",
    "compress_problem",
    "compress_system",
    "dense_matrix",
    "draw",
    "flat_prior",
    "gcr_init",
    "gcr_step",
    "groups_for_array",
    "isotropic_prior",
    "mode_table",
    "n_params",
    "observing_geometry",
    "paper_prior",
    "plan_sampler",
    "precision_apply",
    "prepare",
    "prepare_sampler",
    "precision_matrix",
    "realify",
    "redundant_groups",
    "redundant_responses",
    "rotate",
    "rotate_euler",
    "sample",
    "sample_system",
    "standard_case",
    "unrealify",
    "weights_from_flags",
    "wiener_filter",
    "wiener_filter_system",
    "wigner_blocks",
]

__version__ = "0.1.0"
