"""The statistical model: visibility operator, noise, prior, the linear system, problems.

- ``operator``: :class:`VisOperator`: ``X`` and its adjoint as jitted functions
- ``noise``: the radiometer equation (:func:`radiometer_variance`) and time-difference
  noise, flags as weights, data cleaning
- ``prior``: Gaussian priors (the paper's, isotropic from C_l, flat)
- ``skyprior``: a prior for real data: the GSM's angular power spectrum (a shipped table)
- ``system``: :class:`LinearSystem`: precision operator, Wiener and GCR right-hand sides;
  :func:`check_system`, what is wrong with a hand-edited system (:func:`input_faults`, its
  traceable value checks)
- ``problem``: :class:`Problem` and :func:`build_problem` (geometry, responses, simulation, assembly)
- ``compress``: exact redundant-baseline compression of data, systems, problems
- ``observed``: :func:`problem_from_observation`: an :class:`~gcrsky.io.Observation` (what a
  visibility file says, :func:`gcrsky.io.read_observation`) plus beams as a
  :class:`Problem` (modelled products, units, radiometer noise, weights, responses)
- ``bandlimit``: the reach of a baseline, the lmax that models every baseline, and what to
  do with those beyond it (cut, marginalise the sky above lmax, truncate)
- ``datachecks``: pre-fit checks of an Observation (noise excess, outlier flags, nothing to fit)
- ``fluxscale``: the data's autos against the GSM's through the beam
- ``template``: hyperparameter families: the paper's spectral template (one coefficient
  set for all channels, scaled by ``(nu/nu0)^beta``), noise and prior scales
"""

from .compress import compress_problem, compress_system
from .fluxscale import flux_scale_check
from .gains import (
    GainModel,
    gain_factor,
    gain_model,
    n_gain_params,
    perturbation_coefficients,
    perturbations,
    phase_gradient_directions,
)
from .noise import draw_noise, radiometer_variance
from .observed import DataConfig, check_observation, problem_from_observation
from .operator import VisOperator, adjoint, apply, dense_matrix
from .prior import Prior, flat_prior, isotropic_prior, paper_prior, power_law_cl, prior_from_cl
from .problem import Geometry, Problem, build_problem, simulate_data
from .skyprior import gsm_cl, gsm_prior
from .system import LinearSystem, check_system, input_faults
from .template import scale_noise, spectral_template_system, with_prior

__all__ = [
    "GainModel",
    "gain_factor",
    "gain_model",
    "n_gain_params",
    "perturbation_coefficients",
    "perturbations",
    "phase_gradient_directions",
    "DataConfig",
    "Geometry",
    "LinearSystem",
    "Prior",
    "Problem",
    "VisOperator",
    "adjoint",
    "apply",
    "build_problem",
    "check_observation",
    "flux_scale_check",
    "check_system",
    "input_faults",
    "compress_problem",
    "compress_system",
    "dense_matrix",
    "draw_noise",
    "flat_prior",
    "gsm_cl",
    "gsm_prior",
    "isotropic_prior",
    "paper_prior",
    "power_law_cl",
    "prior_from_cl",
    "problem_from_observation",
    "radiometer_variance",
    "scale_noise",
    "simulate_data",
    "spectral_template_system",
    "with_prior",
]
