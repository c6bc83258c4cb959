"""Many draws in fixed-size batches, with a key scheme that does not depend on the total.

Batch ``b`` uses the key ``jax.random.fold_in(key, b)`` and always draws a *full*
batch of ``batch`` draws (the last one is truncated to ``nsamples``).  So for the same
key and batch size, draw ``i`` is the same whatever ``nsamples`` is (20 draws are the
first 20 of 200), and one compiled program serves every batch.  Changing ``batch``
changes the draws (not their distribution).  ``gcrsky run`` uses this scheme with
``key = jax.random.PRNGKey(seed)``.
"""

from __future__ import annotations

import time
from typing import Callable, Iterable, NamedTuple

import jax
import numpy as np

from ..solvers.info import SolveInfo
from .posterior import SamplerState, draw_exactly

__all__ = ["BatchedDraws", "KEY_SCHEME", "batch_key", "draw_batches"]

#: The key scheme in words (stored with results, e.g. ``results.h5``'s ``key_scheme``).
KEY_SCHEME = "batch b: jax.random.fold_in(jax.random.PRNGKey(seed), b); full batches, last truncated"


class BatchedDraws(NamedTuple):
    """Draws gathered from batches (host NumPy arrays).

    Attributes:
        draws: (Nf, nsamples, n) realified draws.
        info: :class:`~gcrsky.solvers.SolveInfo` over (Nf, nsamples).
        batch_seconds: wall-clock seconds of each batch (the first includes compilation).
    """

    draws: np.ndarray
    info: SolveInfo
    batch_seconds: list


def batch_key(key: jax.Array, b: int) -> jax.Array:
    """The key of batch ``b``: ``jax.random.fold_in(key, b)``."""
    return jax.random.fold_in(key, b)


def draw_batches(
    key: jax.Array,
    prepared: SamplerState,
    nsamples: int,
    batch: int,
    *,
    progress: Callable[[Iterable[int]], Iterable[int]] | None = None,
) -> BatchedDraws:
    """``nsamples`` exact draws from ``prepared`` in batches of ``batch`` (see the module doc).

    Args:
        key: the run's PRNG key (e.g. ``jax.random.PRNGKey(seed)``).
        prepared: a prepared path (:func:`gcrsky.prepare` / :func:`gcrsky.inference.prepare_system`).
        nsamples: total number of draws.
        batch: draws per batch (part of the draws' identity).
        progress: optional wrapper of the batch-index iterable, e.g.
            ``lambda it: tqdm(it, unit="batch")`` (the library itself prints nothing).

    Returns:
        :class:`BatchedDraws`.
    """
    if int(nsamples) != nsamples or nsamples < 1:
        raise ValueError(f"nsamples must be a positive integer, got {nsamples!r}")
    if int(batch) != batch or batch < 1:
        raise ValueError(f"batch must be a positive integer, got {batch!r}")
    nsamples, batch = int(nsamples), int(batch)
    nbatch = -(-nsamples // batch)
    batches: Iterable[int] = range(nbatch)
    if progress is not None:
        batches = progress(batches)
    chunks, infos, seconds = [], [], []
    for b in batches:
        t0 = time.perf_counter()
        d, info = draw_exactly(batch_key(key, b), prepared, batch)
        d = np.asarray(jax.block_until_ready(d))
        take = min(batch, nsamples - b * batch)
        chunks.append(d[:, :take])
        infos.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:, :take], info.draws))
        seconds.append(time.perf_counter() - t0)
    draws = np.concatenate(chunks, axis=1)
    info = jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *infos)
    return BatchedDraws(draws, info, seconds)
