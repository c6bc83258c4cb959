"""Inference on the GCR system: posterior means, exact draws, batches and the Gibbs kernel.

- ``posterior``: the system tier: :func:`prepare_system`, :func:`draw` (optionally for new data), :func:`condition`, :func:`sample_system`, :func:`wiener_filter_system` on a chosen exact path (pure; usable inside ``jit`` and ``vmap``); the draw layout and key scheme
- ``api``: the user tier on a :class:`~gcrsky.model.Problem`: :func:`wiener_filter`, :func:`sample`, :func:`prepare` (path chosen by size, memory checked, unconverged solves logged)
- ``batches``: :func:`draw_batches`: many draws in fixed batches with a key scheme independent of the total
- ``gibbs``: :func:`gcr_init` / :func:`gcr_step`: the GCR step as a kernel for a user's Gibbs loop;
  :func:`gibbs_setup` / :func:`gibbs_init` / :func:`gibbs_step`: the hierarchical ``(a, C_l)``
  kernel that reuses the data term
- ``scalar_gibbs``: :func:`prepare_scalar`, :func:`scalar_draw`, :func:`scalar_log_evidence`,
  :func:`scalar_quadratics`: the sky and the exact evidence for any noise scale and prior
  amplitude from one eigendecomposition (O(n^2) a draw, O(n) an evidence)
- ``collapsed``: :func:`sample_hyperparameters`: NUTS (blackjax, the ``[nuts]`` extra) on
  the exact evidence, then :func:`draw_given_hyperparameters`: exact draws of ``a`` per sample
- ``diagnostics``: :func:`chain_diagnostics`: the effective sample size of every sampled scalar of a
  Markov chain against a stated floor, :func:`diagnostics_warning` its WARNING line
- ``cl``: :func:`cl_hat`, :func:`sample_cl` (``C_l | a``), :func:`sample_power_law`
  (``(A, alpha) | a``)
- ``evidence``: :func:`log_evidence`, the exact log marginal likelihood (dense, m-mode, or
  stochastic Lanczos quadrature), differentiable
- ``hyper``: :func:`fit_hyperparameters`, maximum evidence by BFGS (optimistix) with
  Laplace error bars
- ``gains``: antenna gains sampled with the sky (:func:`gain_setup`, :func:`gains_step`,
  :func:`gain_sky_step`, :func:`scale_step`, the gauge move :func:`gauge_step`, one sweep
  :func:`joint_gain_step`)
- ``beams``: per-antenna beam perturbations sampled with the sky (:func:`beam_setup`, each antenna's exact
  conditional :func:`beam_conditional`, one sweep :func:`beam_step`, the collapsed step
  :func:`beam_collapsed_step`, the block's evidence :func:`beam_log_evidence`)
- ``sources``: point-source fluxes as a linear Gaussian block (:func:`flux_setup`,
  :func:`flux_step`, :func:`sample_fluxes`) and the two-block (sky, fluxes) Gibbs step
  :func:`sky_source_step`

Every solve differentiates implicitly (``jax.grad``, ``jax.jvp``, ``vmap``, ``jit``).
A draw at a fixed key is a differentiable function of the system, but which function
depends on the path (each path reparameterises the noise differently: CG solves the
GCR equation, Cholesky multiplies by ``L^-T``, eigh by ``(P^+)^1/2``), so the gradient
of a fixed-key draw depends on ``method``; the Wiener filter's and the evidence's do
not.  C_l steps will live here too.
"""

from .api import Method, prepare, sample, wiener_filter
from .batches import BatchedDraws, draw_batches
from .beams import (
    BeamState,
    beam_collapsed_step,
    beam_conditional,
    beam_gram,
    beam_gram_sky_draw,
    beam_init,
    beam_log_evidence,
    beam_setup,
    beam_sky_step,
    beam_step,
    beam_warmup_step,
)
from .cl import cl_hat, sample_cl, sample_power_law
from .collapsed import (
    CollapsedInfo,
    CollapsedSamples,
    draw_given_hyperparameters,
    effective_sample_size,
    sample_hyperparameters,
)
from .diagnostics import chain_diagnostics, diagnostics_warning
from .evidence import EvidenceInfo, log_evidence, log_evidence_system
from .gains import (
    GainState,
    gain_init,
    gain_setup,
    gain_sky_step,
    gains_step,
    gauge_step,
    joint_gain_step,
    recentre,
    scale_step,
)
from .gibbs import (
    GCRState,
    GibbsInfo,
    GibbsState,
    gcr_init,
    gcr_step,
    gibbs_init,
    gibbs_setup,
    gibbs_setup_bytes,
    gibbs_step,
    joint_step,
    sky_step,
)
from .hyper import FitResult, fit_hyperparameters
from .posterior import (
    DRAW_BATCH,
    condition,
    draw,
    draw_exactly,
    prepare_sampler,
    prepare_system,
    sample_system,
    wiener_filter_system,
)
from .scalar_gibbs import (
    ScalarQuadratics,
    ScalarState,
    prepare_scalar,
    scalar_draw,
    scalar_log_evidence,
    scalar_quadratics,
)
from .sources import (
    SkySourceState,
    flux_setup,
    flux_step,
    sample_fluxes,
    sky_source_init,
    sky_source_step,
    source_visibilities,
)

__all__ = [
    "BeamState",
    "beam_collapsed_step",
    "beam_conditional",
    "beam_gram",
    "beam_gram_sky_draw",
    "beam_init",
    "beam_log_evidence",
    "beam_setup",
    "beam_sky_step",
    "beam_step",
    "beam_warmup_step",
    "GainState",
    "gain_init",
    "gain_setup",
    "gain_sky_step",
    "gains_step",
    "gauge_step",
    "joint_gain_step",
    "recentre",
    "scale_step",
    "DRAW_BATCH",
    "BatchedDraws",
    "CollapsedInfo",
    "CollapsedSamples",
    "EvidenceInfo",
    "FitResult",
    "GCRState",
    "GibbsInfo",
    "GibbsState",
    "Method",
    "SkySourceState",
    "cl_hat",
    "condition",
    "draw",
    "draw_batches",
    "draw_exactly",
    "chain_diagnostics",
    "diagnostics_warning",
    "draw_given_hyperparameters",
    "effective_sample_size",
    "fit_hyperparameters",
    "flux_setup",
    "flux_step",
    "gcr_init",
    "gcr_step",
    "gibbs_init",
    "gibbs_setup",
    "gibbs_setup_bytes",
    "gibbs_step",
    "joint_step",
    "log_evidence",
    "log_evidence_system",
    "prepare",
    "prepare_sampler",
    "prepare_system",
    "sample",
    "sample_cl",
    "sample_fluxes",
    "sample_hyperparameters",
    "sample_power_law",
    "sample_system",
    "sky_source_init",
    "sky_source_step",
    "sky_step",
    "source_visibilities",
    "ScalarQuadratics",
    "ScalarState",
    "prepare_scalar",
    "scalar_draw",
    "scalar_log_evidence",
    "scalar_quadratics",
    "wiener_filter",
    "wiener_filter_system",
]
