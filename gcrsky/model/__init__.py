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

from .bandlimit import (
    BAND_LIMIT_MODES,
    baseline_reach,
    cut_rows,
    marginalise_rows,
)
from .compress import (
    compress_problem,
    compress_system,
    compress_visibilities,
)
from .datachecks import find_outliers, flag_outliers, flagged_antennas, noise_excess, refuse_empty
from .fluxscale import FLUX_BOUNDS, flux_scale_check, model_autos
from .gains import (
    GainModel,
    gain_factor,
    gain_model,
    mode_basis,
    n_gain_params,
    pair_gains,
    perturbation_coefficients,
    perturbations,
    phase_gradient_directions,
    scale_profile,
    unit_gains,
)
from .noise import (
    clean_data,
    draw_noise,
    inverse_variance,
    radiometer_sigma,
    radiometer_variance,
    time_difference_variance,
    weights_from_flags,
)
from .observed import DataConfig, check_observation, problem_from_observation, raw_variance
from .operator import (
    VisOperator,
    adjoint,
    apply,
    dense_matrix,
    frame_shape,
    from_response_frame,
    n_in,
    response_at,
    to_response_frame,
)
from .prior import (
    Prior,
    flat_prior,
    isotropic_prior,
    paper_prior,
    power_law_cl,
    prior_from_cl,
)
from .problem import (
    Geometry,
    Problem,
    assemble_problem,
    build_problem,
    observation_geometry,
    problem_responses,
    simulate_data,
)
from .skyprior import GSM_CL_FIT_RANGE, check_gsm_cl_frequencies, gsm_cl, gsm_cl_range_hz, gsm_cl_source, gsm_prior
from .system import (
    LinearSystem,
    check_system,
    data_apply,
    fluctuation_rhs,
    input_faults,
    precision_apply,
    precision_data_matrix,
    precision_matrix,
    precision_matrix_by_time,
    time_terms,
    wiener_rhs,
)
from .template import (
    scale_noise,
    spectral_template_system,
    with_prior,
)

__all__ = [
    "GainModel",
    "gain_factor",
    "gain_model",
    "mode_basis",
    "n_gain_params",
    "pair_gains",
    "perturbation_coefficients",
    "perturbations",
    "phase_gradient_directions",
    "scale_profile",
    "unit_gains",
    "BAND_LIMIT_MODES",
    "DataConfig",
    "FLUX_BOUNDS",
    "GSM_CL_FIT_RANGE",
    "Geometry",
    "LinearSystem",
    "Prior",
    "Problem",
    "VisOperator",
    "adjoint",
    "apply",
    "assemble_problem",
    "baseline_reach",
    "build_problem",
    "check_gsm_cl_frequencies",
    "check_observation",
    "find_outliers",
    "flag_outliers",
    "flagged_antennas",
    "flux_scale_check",
    "model_autos",
    "noise_excess",
    "refuse_empty",
    "check_system",
    "input_faults",
    "clean_data",
    "compress_problem",
    "compress_system",
    "compress_visibilities",
    "cut_rows",
    "data_apply",
    "dense_matrix",
    "draw_noise",
    "flat_prior",
    "fluctuation_rhs",
    "frame_shape",
    "gsm_cl",
    "gsm_cl_range_hz",
    "gsm_cl_source",
    "gsm_prior",
    "from_response_frame",
    "inverse_variance",
    "isotropic_prior",
    "marginalise_rows",
    "n_in",
    "observation_geometry",
    "paper_prior",
    "power_law_cl",
    "precision_apply",
    "precision_data_matrix",
    "precision_matrix",
    "precision_matrix_by_time",
    "prior_from_cl",
    "problem_from_observation",
    "problem_responses",
    "radiometer_sigma",
    "radiometer_variance",
    "raw_variance",
    "response_at",
    "scale_noise",
    "simulate_data",
    "spectral_template_system",
    "time_difference_variance",
    "time_terms",
    "to_response_frame",
    "weights_from_flags",
    "wiener_rhs",
    "with_prior",
]
