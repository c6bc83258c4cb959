"""Inference on the GCR system: posterior means, exact draws, batches and the Gibbs kernel.

- ``posterior``: the system tier: :func:`prepare_sampler`, :func:`draw`, :func:`sample_system`, :func:`wiener_filter_system` on a chosen exact path (pure; usable inside ``jit``)
- ``api``: the user tier on a :class:`~gcrsky.model.Problem`: :func:`wiener_filter`, :func:`sample`, :func:`prepare` (path chosen by size, memory checked, unconverged solves logged)
- ``batches``: :func:`draw_batches`: many draws in fixed batches with a key scheme independent of the total
- ``gibbs``: :func:`gcr_init` / :func:`gcr_step`: the GCR step as a kernel for a user's Gibbs loop

Evidence, hyperparameter fits and C_l steps will live here too.
"""

from .api import Method, as_system, prepare, sample, warn_unconverged, wiener_filter
from .batches import KEY_SCHEME, BatchedDraws, batch_key, draw_batches
from .gibbs import GCRState, gcr_init, gcr_step
from .posterior import SamplerState, draw, prepare_sampler, sample_system, wiener_filter_system

__all__ = [
    "KEY_SCHEME",
    "BatchedDraws",
    "GCRState",
    "Method",
    "SamplerState",
    "as_system",
    "batch_key",
    "draw",
    "draw_batches",
    "gcr_init",
    "gcr_step",
    "prepare",
    "prepare_sampler",
    "sample",
    "sample_system",
    "warn_unconverged",
    "wiener_filter",
    "wiener_filter_system",
]
