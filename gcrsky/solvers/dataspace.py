"""The data-space exact path: everything through the ``N_d x N_d`` matrix (DESIGN section 10).

With ``n = (lmax+1)^2`` parameters and ``N_d = 2 Nt Nbl`` real data values per channel
(the real and imaginary parts of every sample, after any redundant compression),
partial coverage at high lmax has ``N_d`` far below ``n`` (a 37-antenna hexagon
compressed to 63 baselines, 10 LSTs: ``N_d = 1260`` against ``n = 40401`` at lmax 200).
There the posterior is cheapest in data space.  With ``W`` the per-component inverse
noise (the system's ``inv_noise``; 0 where flagged), ``Y = W^1/2 X`` the whitened
realified operator and ``S`` the prior covariance (``1 / inv_var``):

* ``D = I + Y S Y^T`` (``N_d x N_d``, SPD, eigenvalues >= 1: well conditioned; a
  flagged sample's rows of Y are 0, so its two rows of D are identity rows, decoupled);
* ``P^-1 = S - S Y^T D^-1 Y S`` (Woodbury);
* Wiener filter ``a_wf = a0 + S Y^T D^-1 W^1/2 (d - X a0)``;
* exact draws in the Hoffman & Ribak (1991) form: ``a_u ~ N(a0, S)``, ``n_u ~ N(0, N)``
  (so ``z = W^1/2 n_u ~ N(0, I)`` on the unflagged rows) and
  ``a = a_u + S Y^T D^-1 (W^1/2 (d - X a_u) - z)``, i.e.
  ``a = a_wf + delta - S Y^T D^-1 (Y delta + z)`` with ``delta = a_u - a0``: the
  covariance is ``P^-1`` exactly;
* the log evidence ``-1/2 [r~^T D^-1 r~ + log det D - log det W + N_d log 2 pi]``
  with ``r~ = W^1/2 (d - X a0)`` over the unflagged samples
  (:func:`dataspace_evidence_parts`; ``log det D = log det(I + H)`` by Sylvester).

Row layout (``N_d = 2 Nt Nbl`` rows per channel, flagged ones included as identity
rows so that shapes stay static): row ``t * 2 Nbl + p * Nbl + b`` is the real
(``p = 0``) or imaginary (``p = 1``) part of sample ``(t, b)``.

How ``D`` is built.  X is never materialised for every time: :func:`dataspace_matrix`
loops (``lax.map``) over the ``Nt (Nt + 1) / 2`` pairs of times ``t <= t'`` and forms
the ``2 Nbl x 2 Nbl`` block ``Y_t S Y_t'^T`` from the two per-time responses
(:func:`gcrsky.model.operator.response_at`, ``O(Nf Nbl n)`` each, frame map included), so the
only large arrays are D and its factor, ``8 Nf N_d^2`` bytes each
(:func:`dataspace_memory_bytes`), against ``8 Nf N_d n`` for X itself.  Each step is
rematerialised under reverse-mode differentiation (``jax.checkpoint``), so a gradient
does not store the per-time responses either.  Cost: ``~Nf N_d^2 n`` flop for D
(symmetry halves the block products), ``Nf N_d^3 / 3`` for its Cholesky factor; the
Wiener filter and each draw cost one product with X and one with ``X^T``
(``~8 Nf N_d n`` flop, matrix-free) and two triangular solves (``2 Nf N_d^2``).

Stationary shortcut (:func:`lag_structure`).  Without a frame map, ``X_t = R Q(t)`` with
``Q(t)`` the rotation about the pole (:func:`gcrsky.sphere.rotate`), and when S commutes
with it (equal variances for the two real parts of every ``a_lm``, as any isotropic
prior has) every block depends only on the lag: ``Y_t S Y_t'^T = W_t^1/2 R_r S Q(t - t')
R_r^T W_t'^1/2`` with ``R_r = [Re R; Im R]``.  Then D needs one ``2 Nbl x 2 Nbl`` product
per distinct lag ``t - t'`` (``2 Nt - 1`` for equally spaced times, against
``Nt (Nt + 1) / 2`` blocks, each of per-time responses): measured ~30x faster at 60
times.  It is used when the angles and the prior are concrete (host-side), there is no
frame map and S commutes; lags closer than :data:`LAG_TOL` rad share one block (phase
error ``<= lmax LAG_TOL``).  Under a trace (e.g. ``jax.grad`` of the evidence in the
prior) the general construction runs: same D to rounding.

With a frame map (a file's ICRS coefficients) the shortcut does not apply; for an isotropic prior
:func:`prepare_dataspace` then factorises the *stationary proxy*'s ``D0`` (the frame map's rotations
without aberration) by the shortcut and solves every ``D^-1 b`` by CG with the true matrix-free D,
preconditioned by ``D0^-1`` (:mod:`gcrsky.solvers.dataspace_proxy`: rigorous stop ``||r||_2 <= tol``,
iterations reported; no ``log det D``, so no evidence from such a state).

Differentiation is implicit as on the primal Cholesky path: solves with D go through
:func:`gcrsky.solvers.dense.cholesky_solve` (``dx = D^-1 (db - dD x)``, the factor held
fixed) and ``log det D`` through :func:`gcrsky.solvers.dense.cholesky_logdet`
(``tr(D^-1 dD)``); D itself differentiates natively in the response, the angles, the
noise and the prior.

Draw ``i`` of a batch uses ``jax.random.split(key, ndraws)[i]``, split again into the
prior part (``delta``, (Nf, n)) and the noise part (``z``, (Nf, N_d)).  A flat prior
(``S^-1 = 0`` somewhere) has no S: refused with a ``ValueError`` on concrete arrays
(under a trace it gives non-finite results, an error with ``DataSpaceOptions(throw=True)``).
"""

from __future__ import annotations

import dataclasses
import logging
from functools import partial
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import check_float64
from ..base.memory import available_memory_bytes, check_memory, format_bytes
from ..model.operator import adjoint, apply, response_at
from ..model.system import LinearSystem, precision_apply, wiener_rhs
from ..sphere.rotation import wigner_nbytes
from .blocked import triangular_solves
from .dataspace_large import (
    HostFactor,
    dataspace_large_bytes,
    factor_in_place,
    host_logdet,
    lag_blocks_by_m,
    logdet_no_grad,
)
from .dataspace_proxy import PROXY_ITERATIONS, pcg_solve, proxy_applies, proxy_memory_bytes, stationary_proxy
from .dense import cholesky_logdet, cholesky_solve, solve_accuracy
from .info import DrawInfo, Result, SolveInfo, direct_info, exact_info
from .options import DataSpaceOptions
from .path import AUTO_MEMORY_FRACTION, EvidenceParts, SolverPath, is_traced

__all__ = [
    "DATASPACE_IN_PLACE_MAX_ND",
    "DATASPACE_MAX_ND",
    "DataSpacePath",
    "DataSpaceState",
    "CHUNK_BYTES",
    "GROUP_BYTES",
    "LAG_TOL",
    "MATERIALIZE_MEMORY_FRACTION",
    "MAX_TIME_CHUNK",
    "RESPONSE_TRANSIENT",
    "LagStructure",
    "ROWS_MAX_BYTES",
    "lag_structure",
    "materialize_rows",
    "check_proper_prior",
    "channel_group",
    "choose_time_chunk",
    "data_size",
    "dataspace_evidence_parts",
    "dataspace_matrix",
    "dataspace_memory_bytes",
    "draw_dataspace",
    "from_rows",
    "prepare_dataspace",
    "time_chunk",
    "to_rows",
]

log = logging.getLogger(__name__)


class DataSpaceState(eqx.Module):
    """The data-space path set up for many draws (a PyTree; pass it through jit).

    Attributes:
        system: the linear system.
        a_wf: (Nf, n) Wiener filter.
        wiener: SolveInfo of the Wiener filter, (Nf,) fields: ``err_sigma`` from the
            true primal residual ``b - P a_wf`` (matrix-free P) in posterior-sigma units,
            ``sqrt(r^T P^-1 r)`` with ``P^-1`` applied in data space (rounding only).
        gram: ``D = I + W^1/2 X S X^T W^1/2``, (Nf, N_d, N_d); None after the in-place set-up
            (:mod:`gcrsky.solvers.dataspace_large`), whose solves differentiate against the
            matrix-free ``D v`` instead.
        chol: lower Cholesky factor of D, (Nf, N_d, N_d).
        rows: ``Y = W^1/2 X`` realified, (Nf, N_d, n), when materialised
            (:class:`~gcrsky.solvers.DataSpaceOptions` ``materialize``): then the draws'
            products with Y and ``Y^T`` are two matrix products over the batch instead of
            per-draw matrix-free products with their per-time rotations; else None.
    """

    system: LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    gram: jax.Array | None
    chol: jax.Array
    rows: jax.Array | None = None
    options: DataSpaceOptions = eqx.field(static=True, default=DataSpaceOptions())

    method: ClassVar[str] = "dataspace"


# ---------------------------------------------------------------- layout and sizes


def data_size(system: LinearSystem) -> int:
    """``N_d = 2 Nt Nbl``: the rows of D per channel (flagged samples included, as identity rows)."""
    _, nt, nbl = system.data.shape
    return 2 * int(nt) * int(nbl)


def to_rows(v: jax.Array) -> jax.Array:
    """Complex samples (..., Nt, Nbl) -> real rows (..., 2 Nt Nbl) in the layout of the module docstring."""
    return jnp.stack([v.real, v.imag], axis=-2).reshape(v.shape[:-2] + (-1,))


def from_rows(u: jax.Array, nt: int, nbl: int) -> jax.Array:
    """Real rows (..., 2 Nt Nbl) -> complex samples (..., Nt, Nbl); inverse of :func:`to_rows`."""
    u = u.reshape(u.shape[:-1] + (nt, 2, nbl))
    return u[..., 0, :] + 1j * u[..., 1, :]


#: Transient bytes of one time's rows while a chunk is formed, in units of ``8 Nf Nbl n_resp`` (one real
#: copy of the response): the rotation and the frame map's Wigner steps hold complex (l, m) grids of the
#: real and imaginary parts.  XLA's memory analysis says 17-18 with a frame map (lmax 30-185); the
#: process's peak on this CPU grows by 39 per time of a chunk (lmax 100, 171 baselines; the runtime's
#: matrix-product scratch is not in XLA's buffers): ``benchmarks/dataspace_memory.py``.
RESPONSE_TRANSIENT = 40.0
#: Copies of the frame map's Wigner blocks (:func:`gcrsky.sphere.wigner_nbytes`) a chunk's rows hold (measured
#: ~3.4 copies of the padded table before the blocks were stored by band; with the banded real products the
#: estimate still bounds the measured peaks, which fell: ``benchmarks/dataspace_memory.py``).
WIGNER_COPIES = 4.0


def _wigner_bytes(system: LinearSystem) -> float:
    blocks = getattr(system.op.frame, "blocks", None)
    return 0.0 if blocks is None else wigner_nbytes(blocks)


def dataspace_memory_bytes(system: LinearSystem, ndraws: int = 1, materialize: bool = False,
                           chunk: int = 1) -> float:
    """Estimated peak bytes of the data-space path (float64), beyond the system: a bound on the set-up's
    measured peak (XLA's memory analysis of the set-up and the process's peak, ``benchmarks/dataspace_memory.py``,
    ``tests/test_dataspace.py``) plus the draws'.

    * D, its factor and the transient copies of its assembly: ``4 x 8 Nf N_d^2``;
    * the rows of ``chunk`` times being formed: ``RESPONSE_TRANSIENT x 8 Nf Nbl n_resp`` each (twice: the
      block assembly forms two chunks at once; once where ``materialize`` builds ``Y`` chunk by chunk; for
      many channels (:func:`channel_group`) one group's rows and one time's transient instead),
      and the frame map's Wigner blocks (``WIGNER_COPIES`` copies);
    * with ``materialize``, ``Y`` itself (``8 Nf N_d n``) twice: the process holds a second copy's worth
      while D is formed from it, outside XLA's buffers (measured +0.5 Y at lmax 100, +1.2 Y at lmax 185);
    * per draw the operator's rotated copies (``2 x 8 Nf Nt n``, not with ``materialize``) and vectors
      (``~6 x 8 Nf (N_d + n)``).

    Not counted, as for every path: the process's fixed cost of running a compiled program (thread
    pools, code, allocator arenas; 0.1-0.2 GB measured), which the planner's memory fractions leave
    room for.
    """
    nf, nt, nbl = (int(x) for x in system.data.shape)
    n = int(system.prior.mean.shape[-1])
    n_resp = int(system.op.response.shape[-1])
    nd = 2 * nt * nbl
    chunk = max(1, min(nt, int(chunk)))
    per_time = RESPONSE_TRANSIENT * 8.0 * nf * nbl * n_resp
    build = 4.0 * 8 * nf * nd * nd + WIGNER_COPIES * _wigner_bytes(system)
    g = None if materialize else channel_group(system, chunk)
    if g is not None:  # D formed for one group of channels at a time from its materialised rows
        build += g * _group_channel_bytes(system)
    else:
        build += (2.0 * 8 * nf * nd * n + chunk * per_time) if materialize else 2.0 * chunk * per_time
    per_draw = 6.0 * 8 * nf * (nd + n) + (0.0 if materialize else 2.0 * 8 * nf * nt * n)
    return build + max(1, ndraws) * per_draw


def choose_time_chunk(system: LinearSystem, options: DataSpaceOptions, budget: float, ndraws: int = 1) -> int:
    """Times per chunk for the set-up on concrete arrays: ``options.time_chunk`` if given; 1 where ``Y`` is
    materialised (its rows are formed once whatever the chunk, and larger chunks only cost memory:
    measured no faster); else the largest (at most :data:`MAX_TIME_CHUNK`) whose estimated peak
    (:func:`dataspace_memory_bytes`) fits in ``AUTO_MEMORY_FRACTION x budget`` (fewer chunk pairs, each
    forming its rows again: measured ~4x faster at 8 times than at 1), or 1 where none does (the memory
    check then refuses)."""
    nt = int(system.data.shape[1])
    if options.time_chunk is not None:
        return max(1, min(nt, int(options.time_chunk)))
    if materialize_rows(system, options):
        return 1
    fits = [c for c in range(1, min(nt, MAX_TIME_CHUNK) + 1)
            if dataspace_memory_bytes(system, ndraws, False, c) <= AUTO_MEMORY_FRACTION * budget]
    return fits[-1] if fits else 1


def _improper_prior(system: LinearSystem) -> str:
    """``""`` if every prior direction is proper (concrete arrays), else what is flat."""
    iv = np.asarray(system.prior.inv_var)
    bad = ~(iv > 0)
    if not bad.any():
        return ""
    f, k = np.argwhere(bad)[0]
    return (f"the data-space path needs a proper prior (S = 1 / inv_var), but the prior is flat or non-positive in "
            f"{int(bad.sum())} directions (first: frequency {f}, parameter {k}, inv_var = {float(iv[f, k])!r}); "
            "use method='eigh' (dense) or method='cg' (m-block preconditioner) for a flat prior")


def check_proper_prior(system: LinearSystem) -> None:
    """Refuse a flat (or non-positive) prior direction on concrete arrays: the data-space path needs S."""
    if not isinstance(system.prior.inv_var, jax.core.Tracer):
        why = _improper_prior(system)
        if why:
            raise ValueError(why)


# ---------------------------------------------------------------- D = I + Y S Y^T

#: Lags ``t - t'`` (radians) closer than this share one block of D on the stationary shortcut.
LAG_TOL = 1e-13


class LagStructure(NamedTuple):
    """The distinct lags of a stationary system (:func:`lag_structure`).

    Attributes:
        lags: (k,) distinct values of ``angle_t - angle_t'``, radians.
        index: (Nt, Nt) int, the lag of each pair of times (an index into ``lags``).
    """

    lags: jax.Array
    index: jax.Array


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def lag_structure(system: LinearSystem, tol: float = LAG_TOL) -> LagStructure | None:
    """The stationary shortcut's lags (module docstring), or None where it does not apply.

    None when there is a frame map, when the angles or the prior's inverse variances are
    traced (they decide whether the shortcut is exact), or when S does not commute with
    rotations about the pole (the two real parts of some ``a_lm``, ``m > 0``, have
    different prior variances).  Host-side.
    """
    op = system.op
    if op.frame is not None or not (_concrete(op.angles) and _concrete(system.prior.inv_var)):
        return None
    iv = np.asarray(system.prior.inv_var)
    n = iv.shape[-1]
    lmax = int(round(np.sqrt(n))) - 1
    nalm = (lmax + 1) * (lmax + 2) // 2
    if (lmax + 1) ** 2 != n or not np.array_equal(iv[..., lmax + 1 : nalm], iv[..., nalm:]):
        return None
    ang = np.asarray(op.angles, np.float64)
    diff = (ang[:, None] - ang[None, :]).ravel()
    order = np.argsort(diff, kind="stable")
    new = np.concatenate([[True], np.diff(diff[order]) > tol])  # start of each group of equal lags
    group = np.cumsum(new) - 1
    index = np.empty(diff.size, np.int64)
    index[order] = group
    lags = diff[order][new]  # each group's smallest member: an exact difference of two angles
    return LagStructure(jnp.asarray(lags), jnp.asarray(index.reshape(ang.size, ang.size), jnp.int32))


def _lag_matrix(system: LinearSystem, lagst: LagStructure) -> jax.Array:
    """``D`` by the stationary shortcut: one ``2 Nbl x 2 Nbl`` block per distinct lag, from per-order Grams
    (:func:`gcrsky.solvers.dataspace_large.lag_blocks_by_m`; measured equal to the lag-by-lag products
    ``R_r S Q(lag) R_r^T`` to 1e-15)."""
    nf, nt, nbl = system.data.shape
    G = lag_blocks_by_m(system, lagst.lags)  # (k, Nf, 2 Nbl, 2 Nbl), rows p * Nbl + b
    B = 2 * nbl
    core = jnp.moveaxis(G[lagst.index], 2, 0)  # (Nf, Nt, Nt, B, B)
    core = jnp.swapaxes(core, 2, 3).reshape(nf, nt * B, nt * B)
    sw = sqrt_weights(system)
    rows = jnp.concatenate([sw, sw], axis=-1).reshape(nf, nt * B)  # (Nf, N_d) in the row layout
    D = rows[:, :, None] * core * rows[:, None, :]
    D = 0.5 * (D + jnp.swapaxes(D, -1, -2))
    return D + jnp.eye(nt * B, dtype=D.dtype)


#: Largest size of one chunk of whitened rows ``Y_c`` (all channels) formed at a time when D is built
#: under a trace (on concrete arrays the chunk follows the free memory, :func:`choose_time_chunk`).
CHUNK_BYTES = 512 * 2**20
#: Most times per chunk :func:`choose_time_chunk` picks (beyond it the set-up is no faster, measured in
#: ``benchmarks/dataspace_memory.py``).
MAX_TIME_CHUNK = 8


def time_chunk(system: LinearSystem, chunk: int | None = None) -> int:
    """Times per chunk when D is built: ``chunk`` (clipped to Nt), or by default as many as keep one
    chunk's rows under :data:`CHUNK_BYTES`."""
    nf, nt, nbl = (int(x) for x in system.data.shape)
    n = int(system.prior.mean.shape[-1])
    if chunk is None:
        chunk = CHUNK_BYTES // (8 * nf * 2 * nbl * n)
    return max(1, min(nt, int(chunk)))


def _chunk_rows(op, sqrt_w: jax.Array, times: jax.Array) -> jax.Array:
    """``Y_c = W_c^1/2 X_c`` realified for the times ``times`` (c,): (Nf, c 2 Nbl, n), rows in D's layout.

    Indices ``>= Nt`` (padding of the last chunk) give zero rows.
    """
    nt = sqrt_w.shape[1]
    tt = jnp.minimum(times, nt - 1)
    X = jax.vmap(lambda t: response_at(op, op.angles[t]))(tt)  # (c, Nf, Nbl, n) complex
    sw = jnp.where((times < nt)[:, None, None], jnp.moveaxis(sqrt_w[:, tt, :], 1, 0), 0.0)[..., None]
    Y = jnp.stack([sw * X.real, sw * X.imag], axis=2)  # (c, Nf, 2, Nbl, n)
    c, nf, _, nbl, n = Y.shape
    return jnp.moveaxis(Y, 0, 1).reshape(nf, c * 2 * nbl, n)


#: Largest transient of the set-up before :func:`dataspace_matrix` forms D for groups of channels: where
#: forming a chunk of times' rows for every channel at once would hold more (``2 x RESPONSE_TRANSIENT x 8 Nf
#: Nbl n_resp`` per time), the rows ``Y`` of :func:`channel_group` channels are materialised at a time (each
#: time rotated once) and D formed from them.  64 H1C channels at lmax 195 formed at once held 33.8 GB of
#: temporaries (XLA's memory analysis) and took ~95 s per channel (the rows of every pair of chunks formed
#: again); in groups, about 2 GB.
GROUP_BYTES = 2 * 2**30


def _group_channel_bytes(system: LinearSystem) -> float:
    """Bytes one channel of a group holds while D is formed: its rows ``Y`` (twice: D is formed from them)
    and one time's transient."""
    _, nt, nbl = (int(x) for x in system.data.shape)
    n, n_resp = int(system.prior.mean.shape[-1]), int(system.op.response.shape[-1])
    return 2.0 * 8 * 2 * nt * nbl * n + RESPONSE_TRANSIENT * 8.0 * nbl * n_resp


def channel_group(system: LinearSystem, chunk: int | None = None) -> int | None:
    """None where :func:`dataspace_matrix` forms every channel's D at once (pairs of time chunks: their
    transient ``2 x RESPONSE_TRANSIENT x 8 Nf Nbl n_resp`` per time fits in :data:`GROUP_BYTES`); else the
    channels per group whose rows are materialised at a time (at least one; :func:`_group_channel_bytes`)."""
    nf, _, nbl = (int(x) for x in system.data.shape)
    c = time_chunk(system, chunk)
    if 2.0 * c * RESPONSE_TRANSIENT * 8 * nf * nbl * int(system.op.response.shape[-1]) <= GROUP_BYTES:
        return None
    return max(1, min(nf, int(GROUP_BYTES // _group_channel_bytes(system))))


@partial(jax.jit, static_argnames=("chunk",))
def dataspace_matrix(system: LinearSystem, chunk: int | None = None, lags: LagStructure | None = None) -> jax.Array:
    """``D = I + W^1/2 X S X^T W^1/2``, (Nf, N_d, N_d), from blocks of times (module docstring).

    With ``lags`` (:func:`lag_structure` of this system) by the stationary shortcut,
    one block per distinct lag; else as follows.

    Never materialises X for every time and channel (unless it is small): the times are cut into
    chunks of ``chunk`` times (default :func:`time_chunk`: rows of at most
    :data:`CHUNK_BYTES`), and a
    ``lax.map`` over the pairs of chunks ``c <= c'`` forms ``Y_c S Y_c'^T`` from the
    per-time responses (:func:`gcrsky.model.operator.response_at`), rematerialised under
    reverse-mode differentiation; memory ``O(Nf N_d^2 + CHUNK_BYTES)``.  Where that transient would
    exceed :data:`GROUP_BYTES` (many channels), a ``lax.map`` over groups of :func:`channel_group`
    channels materialises each group's rows (one rotation per time) and forms its D from them.
    """
    if lags is not None:
        return _lag_matrix(system, lags)
    nf = system.data.shape[0]
    c = time_chunk(system, chunk)
    g = channel_group(system, chunk)
    s = 1.0 / system.prior.inv_var  # (Nf, n)
    if g is None:
        return _matrix_of(system.op, sqrt_weights(system), s, c)
    k = -(-nf // g)
    pad = k * g - nf  # padding channels: zero weights, unit S (their D is I; dropped)

    def grouped(a, fill):
        a = jnp.concatenate([a, jnp.full((pad,) + a.shape[1:], fill, a.dtype)]) if pad else a
        return a.reshape((k, g) + a.shape[1:])

    def one(xs):
        resp, data, w, iv = xs
        sys_g = LinearSystem(system.op._replace(response=resp), data, w, system.prior._replace(mean=iv, inv_var=iv))
        D = _gram_from_rows(sys_g, _rows_by_chunks(sys_g, 1))
        return 0.5 * (D + jnp.swapaxes(D, -1, -2))  # exactly symmetric, as the pairs' assembly

    xs = (grouped(system.op.response, 0), grouped(system.data, 0), grouped(system.inv_noise, 0),
          grouped(system.prior.inv_var, 1))
    D = jax.lax.map(one, xs)
    return D.reshape((k * g,) + D.shape[2:])[:nf]


def _matrix_of(op, sqrt_w, s, c: int) -> jax.Array:
    """D (Nf, N_d, N_d) of the channels of ``op`` (response (Nf, Nbl, n_resp)), ``sqrt_w`` (Nf, Nt, Nbl) and
    ``S`` (Nf, n), the times in chunks of ``c`` (:func:`dataspace_matrix`)."""
    nf, nt, nbl = sqrt_w.shape
    k = -(-nt // c)  # chunks; the last one padded with zero rows
    B = c * 2 * nbl
    times = jnp.arange(k * c).reshape(k, c)
    I, J = np.triu_indices(k)

    @jax.checkpoint
    def block(ij):
        Yi = _chunk_rows(op, sqrt_w, times[ij[0]])
        Yj = Yi if k == 1 else _chunk_rows(op, sqrt_w, times[ij[1]])
        return jnp.einsum("fak,fbk->fab", Yi * s[:, None, :], Yj)

    blocks = jax.lax.map(block, jnp.asarray(np.stack([I, J], axis=1)))  # (npairs, Nf, B, B)
    D = jnp.zeros((nf, k, B, k, B), blocks.dtype)
    D = D.at[:, J, :, I, :].set(jnp.swapaxes(blocks, -1, -2))  # advanced indices first: (npairs, Nf, B, B)
    D = D.at[:, I, :, J, :].set(blocks)
    nd = 2 * nt * nbl
    D = D.reshape(nf, k * B, k * B)[:, :nd, :nd]  # drop the padding rows
    D = 0.5 * (D + jnp.swapaxes(D, -1, -2))  # exactly symmetric (the diagonal blocks up to rounding)
    return D + jnp.eye(nd, dtype=D.dtype)


# ---------------------------------------------------------------- products with Y, Y^T


def sqrt_weights(system: LinearSystem) -> jax.Array:
    """``W^1/2`` (Nf, Nt, Nbl), 0 on flagged samples with a zero (not NaN) derivative there."""
    w = system.inv_noise
    pos = w > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, w, 1.0)), 0.0)


def whitened_apply(system: LinearSystem, sqrt_w, a):
    """``Y a = W^1/2 X a`` as rows (Nf, N_d), matrix-free."""
    return to_rows(sqrt_w * apply(system.op, a))


def whitened_adjoint(system: LinearSystem, sqrt_w, u):
    """``Y^T u = X^T W^1/2 u`` for rows u (Nf, N_d) -> (Nf, n), matrix-free."""
    _, nt, nbl = system.data.shape
    return adjoint(system.op, sqrt_w * from_rows(u, nt, nbl))


def _whitened_residual(system: LinearSystem, sqrt_w):
    """``r~ = W^1/2 (d - X a0)`` as rows (Nf, N_d); 0 on flagged samples (whatever they hold)."""
    r = system.data - apply(system.op, system.prior.mean)
    return to_rows(jnp.where(system.inv_noise > 0, sqrt_w * r, 0.0))


def _factor(system: LinearSystem, chunk: int | None = None, lags: LagStructure | None = None):
    D = dataspace_matrix(system, chunk, lags)
    return D, jnp.linalg.cholesky(D)


def _d_matvec(system: LinearSystem, sqrt_w, u):
    """Matrix-free ``D u = u + Y S Y^T u`` for rows u (Nf, N_d)."""
    return u + whitened_apply(system, sqrt_w, whitened_adjoint(system, sqrt_w, u) / system.prior.inv_var)


def _d_solve(system: LinearSystem, sqrt_w, D, L, b):
    """``D^-1 b`` for rows b (Nf, N_d) by the factor L: differentiated implicitly against D where it is
    kept, else against the matrix-free :func:`_d_matvec` (the in-place set-up)."""
    if D is not None:
        return cholesky_solve(D, L, b)
    if isinstance(L, HostFactor):
        solve = lambda _, r: L.solve(r)  # noqa: E731
    else:
        Lc = jax.lax.stop_gradient(L)
        solve = lambda _, r: jax.vmap(triangular_solves)(Lc, r)  # noqa: E731
    return jax.lax.custom_linear_solve(lambda u: _d_matvec(system, sqrt_w, u), b, solve, symmetric=True)


def _factor_finite(L) -> jax.Array:
    """(Nf,) every entry of the channel's factor finite."""
    if isinstance(L, HostFactor):
        return jnp.asarray(L.finite)
    return jnp.all(jnp.isfinite(jax.lax.stop_gradient(L)), axis=(1, 2))


def _posterior_cov_apply(system: LinearSystem, sqrt_w, D, L, v):
    """``P^-1 v = S v - S Y^T D^-1 Y S v`` for v (Nf, n)."""
    s = 1.0 / system.prior.inv_var
    sv = s * v
    x = _d_solve(system, sqrt_w, D, L, whitened_apply(system, sqrt_w, sv))
    return sv - s * whitened_adjoint(system, sqrt_w, x)


#: Largest ``Y = W^1/2 X`` (bytes, all channels) that ``materialize=None`` keeps for the draws.
ROWS_MAX_BYTES = 4 * 2**30
#: Fraction of the free memory the set-up with a materialised Y may take (its estimate bounds the measured
#: peak; the alternative, forming the rows again per pair of chunks, is many times slower).
MATERIALIZE_MEMORY_FRACTION = 0.9


def materialize_rows(system: LinearSystem, options: DataSpaceOptions, budget: float | None = None) -> bool:
    """Whether the draws use a materialised ``Y`` (``options.materialize``; None: when ``8 Nf N_d n <=
    ROWS_MAX_BYTES`` and, given a ``budget``, the set-up with it fits in ``AUTO_MEMORY_FRACTION x budget``)."""
    if options.materialize is not None:
        return bool(options.materialize)
    nf = int(system.data.shape[0])
    if 8.0 * nf * data_size(system) * int(system.prior.mean.shape[-1]) > ROWS_MAX_BYTES:
        return False
    return budget is None or dataspace_memory_bytes(system, 1, True, 1) <= MATERIALIZE_MEMORY_FRACTION * budget


def _dataspace_wiener(system: LinearSystem, D, L, options: DataSpaceOptions):
    """``a_wf = a0 + S Y^T D^-1 r~`` and its info from the true (matrix-free) primal residual (on a proxy
    state: :func:`_proxy_wiener`)."""
    if options.proxy:
        return _proxy_wiener(system, L, options)
    sqrt_w = sqrt_weights(system)
    s = 1.0 / system.prior.inv_var
    x = _d_solve(system, sqrt_w, D, L, _whitened_residual(system, sqrt_w))
    a_wf = system.prior.mean + s * whitened_adjoint(system, sqrt_w, x)
    # how good is it: the true (matrix-free) residual of P a = b, in posterior-sigma units
    sg = jax.lax.stop_gradient
    ssys, Dc, Lc, a = sg(system), sg(D), sg(L), sg(a_wf)
    b = wiener_rhs(ssys)
    r = b - precision_apply(ssys, a)
    err = jnp.sqrt(jnp.abs(jnp.sum(r * _posterior_cov_apply(ssys, sg(sqrt_w), Dc, Lc, r), axis=-1)))
    finite = _factor_finite(L) & jnp.all(jnp.isfinite(a), axis=-1)
    info = direct_info(err, jnp.linalg.norm(r, axis=-1) / jnp.linalg.norm(b, axis=-1), finite, options.tol)
    if options.throw:
        a_wf = eqx.error_if(a_wf, ~info.converged, "gcrsky data space: D is not positive definite or the Wiener "
                                                    "filter is not finite (a flat prior direction?) or missed "
                                                    "DataSpaceOptions.tol")
    return a_wf, info


@partial(jax.jit, static_argnames=("options", "materialize"))
def _prepare_dataspace(system: LinearSystem, options: DataSpaceOptions = DataSpaceOptions(),
                       lags: LagStructure | None = None, materialize: bool = False) -> DataSpaceState:
    check_float64(system.op.response, system.inv_noise)
    rows = None
    if materialize:  # Y chunk by chunk (a chunk's transient, not all times' at once), then D from it
        rows = _rows_by_chunks(system, time_chunk(system, options.time_chunk))  # (Nf, N_d, n)
        D = _lag_matrix(system, lags) if lags is not None else _gram_from_rows(system, rows)
        L = jnp.linalg.cholesky(D)
    else:
        D, L = _factor(system, options.time_chunk, lags)
    a_wf, info = _dataspace_wiener(system, D, L, options)
    return DataSpaceState(system, a_wf, info, D, L, rows, options)


def _rows_by_chunks(system: LinearSystem, chunk: int) -> jax.Array:
    """``Y = W^1/2 X`` realified (Nf, N_d, n), formed ``chunk`` times at a time into one buffer (a
    ``fori_loop`` of in-place updates: the rows once, plus one chunk's transient)."""
    nf, nt, nbl = system.data.shape
    k = -(-nt // chunk)
    B = 2 * nbl * chunk
    n = system.prior.mean.shape[-1]
    sqrt_w = sqrt_weights(system)
    dtype = system.op.response.real.dtype

    def fill(i, Y):
        rows = _chunk_rows(system.op, sqrt_w, i * chunk + jnp.arange(chunk))  # (Nf, B, n); padding rows 0
        return jax.lax.dynamic_update_slice_in_dim(Y, rows, i * B, axis=1)

    Y = jax.lax.fori_loop(0, k, fill, jnp.zeros((nf, k * B, n), dtype))
    return Y[:, : 2 * nt * nbl]


def _gram_from_rows(system: LinearSystem, rows: jax.Array) -> jax.Array:
    """``D = I + Y S Y^T`` from materialised rows, ``2 Nbl`` rows at a time into one buffer (no full-size
    temporary of Y or D)."""
    nf, nd, n = rows.shape
    B = 2 * system.data.shape[2]
    s = 1.0 / system.prior.inv_var

    def fill(i, D):
        blk = jnp.einsum("fak,fbk->fab", jax.lax.dynamic_slice_in_dim(rows, i * B, B, axis=1) * s[:, None, :], rows)
        return jax.lax.dynamic_update_slice_in_dim(D, blk, i * B, axis=1)

    D = jax.lax.fori_loop(0, nd // B, fill, jnp.zeros((nf, nd, nd), rows.dtype))
    return D + jnp.eye(nd, dtype=D.dtype)


@jax.jit
def _condition_dataspace(state: DataSpaceState, data: jax.Array) -> DataSpaceState:
    system = state.system._replace(data=jnp.asarray(data, state.system.data.dtype))
    a_wf, info = _dataspace_wiener(system, state.gram, state.chol, state.options)
    return DataSpaceState(system, a_wf, info, state.gram, state.chol, state.rows, state.options)


def prepare_dataspace(system: LinearSystem, options: DataSpaceOptions | None = None, *,
                      memory_budget: float | None = None) -> DataSpaceState:
    """Build and factorise ``D = I + W^1/2 X S X^T W^1/2`` and solve for the Wiener filter, once.

    On concrete arrays, first refuses a flat prior (``ValueError``) and checks that D
    and its factor fit (:func:`gcrsky.base.check_memory`, naming the alternative paths).
    Where D and its factor do not fit together but D alone does (``options.in_place``
    None), the in-place set-up of :mod:`gcrsky.solvers.dataspace_large` runs instead.
    With a frame map and an isotropic prior (``options.proxy`` not False), the stationary
    proxy's ``D0`` is factorised instead and every solve with D is CG preconditioned by it
    (:mod:`gcrsky.solvers.dataspace_proxy`; the state's ``options.proxy`` is then True).

    Args:
        system: the linear system (every prior direction proper).
        options: :class:`DataSpaceOptions`.
        memory_budget: bytes the path may use (default: what is free on the device).
    """
    options = DataSpaceOptions() if options is None else options
    if not isinstance(options, DataSpaceOptions):
        raise TypeError(f"the data-space path takes DataSpaceOptions, got {type(options).__name__}")
    lags = lag_structure(system) if options.stationary else None
    if is_traced(system):
        if options.in_place or options.proxy:
            raise ValueError("DataSpaceOptions(in_place=True) and (proxy=True) need concrete arrays (their set-up "
                             "runs on the host)")
        return _prepare_dataspace(system, options, lags, bool(options.materialize))
    check_proper_prior(system)
    nd, nf = data_size(system), int(system.data.shape[0])
    budget = available_memory_bytes() if memory_budget is None else float(memory_budget)
    proxy = _proxy_of(system, options) if lags is None else None
    if proxy is not None:
        return _prepare_proxy(system, proxy, options, budget)
    if use_in_place(system, options, lags, budget):
        check_memory(dataspace_large_bytes(system, int(lags.lags.shape[0])),
                     f"the in-place data-space set-up (D: {nf} x {nd} x {nd}, kept once)",
                     "use method='cg' with CGOptions(dense=False) (matrix-free), fewer times or baselines, or a "
                     "lower lmax", budget=budget)
        return _prepare_in_place(system, dataclasses.replace(options, in_place=True, materialize=False), lags)
    options = dataclasses.replace(options, in_place=False, materialize=materialize_rows(system, options, budget))
    options = dataclasses.replace(options, time_chunk=choose_time_chunk(system, options, budget))
    check_memory(dataspace_memory_bytes(system, 1, materialize_rows(system, options), options.time_chunk),
                 f"the data-space path (D: {nf} x {nd} x {nd}; rows formed {options.time_chunk} time(s) at once)",
                 "use method='cg' with CGOptions(dense=False) (matrix-free), fewer times or baselines, or a "
                 "lower lmax", budget=budget)
    return _prepare_dataspace(system, options, lags, materialize_rows(system, options))


def use_in_place(system: LinearSystem, options: DataSpaceOptions, lags: LagStructure | None, budget: float) -> bool:
    """Whether :func:`prepare_dataspace` takes the in-place set-up: ``options.in_place`` if given (True
    needs the stationary shortcut, else ``ValueError`` naming why), else where the shortcut applies and
    the standard set-up at its smallest does not fit ``AUTO_MEMORY_FRACTION x budget``."""
    if options.in_place is False:
        return False
    if lags is None:
        if options.in_place:
            raise ValueError("DataSpaceOptions(in_place=True) needs the stationary shortcut (no frame map, a prior "
                             "with equal variances for the Re and Im parts of every a_lm, stationary=True)")
        return False
    if options.in_place:
        return True
    return dataspace_memory_bytes(system, 1, False, 1) > AUTO_MEMORY_FRACTION * budget


@partial(jax.jit, static_argnames=("options",))
def _in_place_wiener(system: LinearSystem, L: jax.Array, options: DataSpaceOptions):
    return _dataspace_wiener(system, None, L, options)


def _prepare_in_place(system: LinearSystem, options: DataSpaceOptions, lags: LagStructure) -> DataSpaceState:
    """The in-place set-up (:mod:`gcrsky.solvers.dataspace_large`): lag blocks by m, D filled and factorised in
    one host buffer, the Wiener filter through the factor."""
    check_float64(system.op.response, system.inv_noise)
    nf, nt, nbl = system.data.shape
    sw = sqrt_weights(system)
    rows = np.asarray(jnp.concatenate([sw, sw], axis=-1).reshape(nf, nt * 2 * nbl))
    L = factor_in_place(system, lag_blocks_by_m(system, lags.lags), np.asarray(lags.index), rows)
    a_wf, info = _in_place_wiener(system, L, options)
    return DataSpaceState(system, a_wf, info, None, L, None, options)


# ---------------------------------------------------------------- the stationary proxy (a frame map)


def _proxy_of(system: LinearSystem, options: DataSpaceOptions) -> LinearSystem | None:
    """The stationary proxy (:func:`gcrsky.solvers.dataspace_proxy.stationary_proxy`) where ``options`` allow
    it and it applies; ``ValueError`` naming why where ``options.proxy`` is True and it does not."""
    if options.proxy is False or system.op.frame is None:
        return None
    why = "stationary=False forbids it" if not options.stationary else proxy_applies(system)
    if why:
        if options.proxy:
            raise ValueError(f"DataSpaceOptions(proxy=True) does not apply: {why}")
        log.debug("data space: no stationary proxy (%s): the general construction", why)
        return None
    return stationary_proxy(system)


def _proxy_precond(L):
    """``r (..., Nf, N_d) -> D0^-1 r`` through the proxy's factor (host or jnp), held fixed."""
    if isinstance(L, HostFactor):
        return L.solve
    Lc = jax.lax.stop_gradient(L)

    def solve(r):
        return jnp.moveaxis(jax.vmap(triangular_solves)(Lc, jnp.moveaxis(r, -2, 0)), 0, -2)

    return solve


def _proxy_solve(system: LinearSystem, sqrt_w, L, b, options: DataSpaceOptions):
    """``D^-1 b`` for rows b (..., Nf, N_d) by CG with the true matrix-free D, preconditioned by the proxy's
    ``D0^-1``; stops per (draw, channel) on ``||b - D x||_2 <= options.tol`` (posterior sigma, a bound:
    :mod:`gcrsky.solvers.dataspace_proxy`).  Returns ``(x, SolveInfo)`` with (...,  Nf) fields."""
    def matvec(u):
        flat = u.reshape((-1,) + u.shape[-2:])
        return jax.vmap(lambda v: _d_matvec(system, sqrt_w, v))(flat).reshape(u.shape)

    return pcg_solve(matvec, _proxy_precond(L), b, tol=options.tol, maxiter=options.maxiter)


def _proxy_wiener(system: LinearSystem, L, options: DataSpaceOptions):
    """The Wiener filter ``a0 + S Y^T D^-1 r~`` by the proxy's CG; its info: CG's iterations and the rigorous
    bound ``||r||_2`` (posterior sigma) of the true data-space residual."""
    sqrt_w = sqrt_weights(system)
    x, info = _proxy_solve(system, sqrt_w, L, _whitened_residual(system, sqrt_w), options)
    a_wf = system.prior.mean + whitened_adjoint(system, sqrt_w, x) / system.prior.inv_var
    finite = jnp.all(jnp.isfinite(jax.lax.stop_gradient(a_wf)), axis=-1)
    code = jnp.where(finite, info.result, Result.NONFINITE)
    info = info._replace(result=code, converged=code == Result.SUCCESS)
    if options.throw:
        a_wf = eqx.error_if(a_wf, ~info.converged, "gcrsky data space (stationary proxy): CG did not reach "
                                                    "DataSpaceOptions.tol within maxiter, or a non-finite answer")
    return a_wf, info


@jax.jit
def _proxy_jnp_factor(proxy: LinearSystem, lags: LagStructure) -> jax.Array:
    """The lower Cholesky factor of the proxy's ``D0`` (Nf, N_d, N_d), by the stationary shortcut."""
    return jnp.linalg.cholesky(_lag_matrix(proxy, lags))


def _prepare_proxy(system: LinearSystem, proxy: LinearSystem, options: DataSpaceOptions,
                   budget: float) -> DataSpaceState:
    """The proxy set-up: ``D0`` of the stationary proxy factorised (in place on the host where the jnp factor
    does not fit, or as ``options.in_place`` says), the Wiener filter by CG with the true D."""
    check_float64(system.op.response, system.inv_noise)
    lags = lag_structure(proxy)
    if lags is None:  # the proxy is stationary by construction (isotropic prior, no frame map)
        raise RuntimeError("the stationary proxy has no lag structure")
    nlags, nf, nd = int(lags.lags.shape[0]), int(system.data.shape[0]), data_size(system)
    in_place = options.in_place
    if in_place is None:
        in_place = proxy_memory_bytes(system, nlags, 1, False) > AUTO_MEMORY_FRACTION * budget
    check_memory(proxy_memory_bytes(system, nlags, 1, in_place),
                 f"the data-space path's stationary proxy (D0: {nf} x {nd} x {nd}, factor {'in place' if in_place else 'jnp'})",
                 "use method='cg' with CGOptions(dense=False) (matrix-free), fewer times or baselines, or a "
                 "lower lmax", budget=budget)
    log.info("data space: stationary proxy of the frame map (%d lags, factor %s), CG with the true D to "
             "||r|| <= %.1e", nlags, "in place" if in_place else "jnp", options.tol)
    if in_place:
        nt, nbl = system.data.shape[1:]
        sw = sqrt_weights(proxy)
        rows = np.asarray(jnp.concatenate([sw, sw], axis=-1).reshape(nf, nt * 2 * nbl))
        L = factor_in_place(proxy, lag_blocks_by_m(proxy, lags.lags), np.asarray(lags.index), rows)
    else:
        L = _proxy_jnp_factor(proxy, lags)
    options = dataclasses.replace(options, proxy=True, in_place=bool(in_place), materialize=False)
    a_wf, info = _in_place_wiener(system, L, options)
    return DataSpaceState(system, a_wf, info, None, L, None, options)


@partial(jax.jit, static_argnames=("ndraws",))
def draw_dataspace(key: jax.Array, state: DataSpaceState, ndraws: int):
    """``ndraws`` exact draws ``a_wf + delta - S Y^T D^-1 (Y delta + z)`` (Hoffman & Ribak).

    Draw ``i`` uses ``k = jax.random.split(key, ndraws)[i]``; ``k_a, k_n = split(k)``
    give ``delta = S^1/2 N(0, I)`` (Nf, n) and ``z ~ N(0, I)`` (Nf, N_d) (masked to the
    unflagged rows, though flagged rows drop out of the product anyway).

    On a stationary-proxy state (``state.options.proxy``) ``D^-1`` is CG preconditioned by the proxy's
    factor, one solve per draw for the whole draw ``a0 + delta + S Y^T D^-1 (r~ - Y delta - z)`` (the same
    draw, algebraically), so that ``draws`` reports each draw's iterations and its own rigorous bound
    ``||r||_2`` on the draw's error (posterior sigma; not the Wiener solve's plus the fluctuation's).

    Returns:
        draws (Nf, ndraws, n); a :class:`~gcrsky.solvers.DrawInfo` (``wiener``, ``draws`` a SolveInfo over
        (Nf, ndraws), ``a_wf``).
    """
    system, a_wf, D, L = state.system, state.a_wf, state.gram, state.chol
    nf, n = a_wf.shape
    nd = L.shape[-1]
    sqrt_w = sqrt_weights(system)
    s = 1.0 / system.prior.inv_var
    keep = to_rows(jnp.where(system.inv_noise > 0, 1.0 + 1.0j, 0.0)).astype(a_wf.dtype)  # 1 on unflagged rows

    def normals(k):
        ka, kn = jax.random.split(k)
        delta = jnp.sqrt(s) * jax.random.normal(ka, (nf, n), a_wf.dtype)
        z = keep * jax.random.normal(kn, (nf, nd), a_wf.dtype)
        return delta, z

    delta, z = jax.vmap(normals)(jax.random.split(key, ndraws))  # (ndraws, Nf, n), (ndraws, Nf, N_d)
    Y = state.rows
    if Y is None:  # matrix-free products, draw by draw
        u = jax.vmap(lambda dd: whitened_apply(system, sqrt_w, dd))(delta) + z
    else:
        u = jnp.einsum("fak,dfk->dfa", Y, delta) + z
    base = a_wf
    if state.options.proxy:  # one CG solve per draw, a = a0 + delta - S Y^T D^-1 (Y delta + z - r~): its own bound
        base = system.prior.mean
        x, dinfo = _proxy_solve(system, sqrt_w, L, u - _whitened_residual(system, sqrt_w), state.options)
        dinfo = jax.tree_util.tree_map(lambda v: jnp.swapaxes(v, 0, 1), dinfo)  # (Nf, ndraws)
    else:
        x = jax.vmap(lambda uu: _d_solve(system, sqrt_w, D, L, uu))(u)
    if Y is None:
        corr = jax.vmap(lambda xx: s * whitened_adjoint(system, sqrt_w, xx))(x)
    else:
        corr = s * jnp.einsum("fak,dfa->dfk", Y, x)
    out = base[:, None, :] + jnp.moveaxis(delta - corr, 0, 1)
    finite = jnp.all(jnp.isfinite(out), axis=-1)
    if state.options.proxy:
        code = jnp.where(finite, dinfo.result, Result.NONFINITE)
        return out, DrawInfo(state.wiener, dinfo._replace(result=code, converged=code == Result.SUCCESS), a_wf)
    return out, DrawInfo(state.wiener, exact_info(state.wiener, finite, (nf, ndraws)), a_wf)


# ---------------------------------------------------------------- evidence


@partial(jax.jit, static_argnames=("chunk",))
def dataspace_evidence_parts(system: LinearSystem, chunk: int | None = None, lags: LagStructure | None = None):
    """The data-space terms of the log evidence, per channel (Nf,) each.

    Returns:
        ``(q, logdet, finite, (D, L, r~, D^-1 r~))``: ``q = r~^T D^-1 r~`` with ``r~ = W^1/2 (d - X a0)``
        (equal to ``r^T W r - b'^T P^-1 b'`` by Woodbury), ``logdet = log det D``
        (``= log det(I + H)``, the prior-whitened precision's, by Sylvester) and whether
        the factor is finite (``chunk``, ``lags``: as :func:`dataspace_matrix`).  ``log p(d) = -1/2 [q + logdet - log det W + N_d log 2 pi]``
        over the unflagged samples.  Differentiates implicitly (the solve) and by
        ``tr(D^-1 dD)`` (the log determinant), to second order.
    """
    sqrt_w = sqrt_weights(system)
    D, L = _factor(system, chunk, lags)
    rt = _whitened_residual(system, sqrt_w)
    y = cholesky_solve(D, L, rt)
    q = jnp.sum(rt * y, axis=-1)
    finite = jnp.all(jnp.isfinite(jax.lax.stop_gradient(L)), axis=(1, 2))
    return q, cholesky_logdet(D, L), finite, (D, L, rt, y)


# ---------------------------------------------------------------- the path

#: Largest number of real data values per channel for which ``method="auto"`` forms and
#: factorises the data-space matrix D (the same ~1 min factorisation bound as ``DENSE_MAX_N``).
DATASPACE_MAX_ND = 12000
#: The same bound for the in-place set-up (:mod:`gcrsky.solvers.dataspace_large`), where no other exact path
#: fits (partial coverage of the HERA core at lmax 300: N_d = 37800, a factor of ~2e13 flop, minutes).
DATASPACE_IN_PLACE_MAX_ND = 50000


def _parts(system: LinearSystem, options: DataSpaceOptions, terms, q, logdet, finite, solved=None) -> EvidenceParts:
    """The evidence's parts; ``solved = (D, L, r~, D^-1 r~)`` gives the solve's accuracy from its true residual
    (:func:`gcrsky.solvers.dense.solve_accuracy`, in D's norm: ``q`` is within ``sqrt(q) err_sigma``), else
    (a prepared state's) the factor's finiteness alone."""
    zeros = jnp.zeros(q.shape)
    if solved is None:
        info = direct_info(zeros, zeros, finite, options.tol)
    else:
        D, L, rt, y = solved
        Lc = jax.lax.stop_gradient(L)
        info = solve_accuracy(D, lambda r: jax.vmap(lambda l, v: jax.scipy.linalg.cho_solve((l, True), v))(Lc, r),
                              rt, y, finite, options.tol)
    if options.throw:
        q = eqx.error_if(q, ~finite, "gcrsky data space: D is not positive definite (a flat prior direction?)")
    return EvidenceParts(q, logdet, zeros, info)


def _proxy_lags(system: LinearSystem, options: DataSpaceOptions) -> int | None:
    """Distinct lags of the stationary proxy where :func:`prepare_dataspace` would take it (else None),
    without forming the proxy (its lags depend only on the angles)."""
    if options.proxy is False or not options.stationary or system.op.frame is None or proxy_applies(system):
        return None
    lags = lag_structure(system._replace(op=system.op._replace(frame=None)))
    return None if lags is None else int(lags.lags.shape[0])


def _proxy_memory(system: LinearSystem, options: DataSpaceOptions, nlags: int, ndraws: int) -> float:
    """The proxy's estimate: in place, jnp factor, or the smaller (``options.in_place`` None)."""
    if options.in_place is not None:
        return proxy_memory_bytes(system, nlags, ndraws, options.in_place)
    return min(proxy_memory_bytes(system, nlags, ndraws, b) for b in (False, True))


class DataSpacePath(SolverPath):
    """Everything through ``D = I + W^1/2 X S X^T W^1/2`` (:func:`prepare_dataspace`): fewer data than
    parameters, a proper prior."""

    name = "dataspace"
    options_type = DataSpaceOptions
    state_type = DataSpaceState

    def check(self, system, options):
        return _improper_prior(system)

    def memory_bytes(self, system, options, ndraws=1):
        """The set-up's estimated peak at its smallest chunk (1 time, or ``options.time_chunk``); without
        ``options.materialize`` the smaller of with and without ``Y`` (:func:`prepare_dataspace` falls back);
        with the in-place set-up where it applies (``options.in_place`` not False), the smaller of that too;
        with the stationary proxy where it applies (a frame map), its estimate
        (:func:`gcrsky.solvers.dataspace_proxy.proxy_memory_bytes`: D0's factor and the CG vectors)."""
        nlags = _proxy_lags(system, options)
        if nlags is not None:
            return _proxy_memory(system, options, nlags, ndraws)
        chunk = options.time_chunk or 1
        if options.materialize is not None:
            std = dataspace_memory_bytes(system, ndraws, options.materialize, chunk)
        else:
            std = min(dataspace_memory_bytes(system, ndraws, m, chunk) for m in (False, materialize_rows(system, options)))
        lags = lag_structure(system) if options.stationary and options.in_place is not False else None
        if lags is None:
            return std
        big = dataspace_large_bytes(system, int(lags.lags.shape[0]), ndraws)
        return big if options.in_place else min(std, big)

    def cost_flop(self, system, options, ndraws):
        """D (``4 Nf N_d^2 n``; on the stationary shortcut ``16 Nf (2 Nbl)^2 n`` for the per-order Grams plus
        ``4 Nf k (2 Nbl)^2 (lmax + 1)`` for ``k`` distinct lags) and its factor (``Nf N_d^3 / 3``), then per
        draw the products with X and ``X^T`` (``16 Nf Nt Nbl n`` plus ``~8 Nf Nt (lmax+1)^3`` for the
        rotations; ``4 Nf N_d n`` with Y materialised) and two triangular solves (``2 Nf N_d^2``).  With the
        stationary proxy: its D0 by the shortcut and its factor, then per solve (the Wiener filter and each
        draw) ``PROXY_ITERATIONS + 1`` products with the true D, m-factorised (``16 Nf Nbl n_resp`` for the
        response, ``32 Nf Nt Nbl lmax_out`` for the phases, ``~16 Nf lmax_out^3`` for the frame map's
        rotations and aberration) and preconditioner solves (``2 Nf N_d^2``)."""
        nf, nt, nbl = (int(x) for x in system.data.shape)
        n = int(system.prior.mean.shape[-1])
        nd = 2.0 * nt * nbl
        nlags = _proxy_lags(system, options)
        if nlags is not None:
            n_resp = int(system.op.response.shape[-1])
            build = 16.0 * nf * (2.0 * nbl) ** 2 * n + 4.0 * nf * nlags * (2.0 * nbl) ** 2 * np.sqrt(n)
            lout = np.sqrt(n_resp)
            prod = 16.0 * nf * nbl * n_resp + 32.0 * nf * nt * nbl * lout + 16.0 * nf * lout**3
            per_solve = (PROXY_ITERATIONS + 1) * (prod + 2.0 * nf * nd * nd)
            return build + nf * nd**3 / 3.0 + (ndraws + 1) * per_solve
        lags = lag_structure(system) if options.stationary else None
        if lags is None:
            build = 4.0 * nf * nd * nd * n
        else:
            build = 16.0 * nf * (2.0 * nbl) ** 2 * n + 4.0 * nf * lags.lags.shape[0] * (2.0 * nbl) ** 2 * np.sqrt(n)
        rot = 8.0 * nf * nt * np.sqrt(n) ** 3
        per_draw = 4.0 * nf * nd * n if materialize_rows(system, options) else 16.0 * nf * nt * nbl * n + rot
        return build + nf * nd**3 / 3.0 + ndraws * (per_draw + 2.0 * nf * nd * nd)

    def auto_limits(self, system, options, budget, ndraws):
        nd, n = data_size(system), int(system.prior.mean.shape[-1])
        if nd >= n:
            return f"N_d = {nd} real data values per channel >= n = {n}"
        in_place = options.stationary and options.in_place is not False and lag_structure(system) is not None
        in_place = in_place or _proxy_lags(system, options) is not None  # the proxy's factor: in place if need be
        cap = DATASPACE_IN_PLACE_MAX_ND if in_place else DATASPACE_MAX_ND
        if nd > cap:
            return f"N_d = {nd} > {cap} (DATASPACE_{'IN_PLACE_' if in_place else ''}MAX_ND)"
        mem = self.memory_bytes(system, options, ndraws)
        if mem > AUTO_MEMORY_FRACTION * budget:
            what = "D + factor" if _proxy_lags(system, options) is None else "the stationary proxy (D0's factor, CG)"
            return f"{what} would need {format_bytes(mem)}, more than {AUTO_MEMORY_FRACTION:.0%} of " \
                   f"{format_bytes(budget)}"
        return ""

    def describe(self, system, options, memory):
        if _proxy_lags(system, options) is not None:
            return (f"N_d = {data_size(system)} real data values per channel < n = {int(system.prior.mean.shape[-1])}: "
                    f"data space with a frame map: the stationary proxy's D0 factorised, CG with the true D "
                    f"({format_bytes(memory)})")
        return (f"N_d = {data_size(system)} real data values per channel < n = {int(system.prior.mean.shape[-1])}: "
                f"data space (D + factor {format_bytes(memory)})")

    def prepare(self, system, options):
        return prepare_dataspace(system, options)

    def draw(self, key, state, ndraws):
        return draw_dataspace(key, state, ndraws)

    def condition(self, state, data):
        return _condition_dataspace(state, data)

    def evidence_parts(self, system, options, terms, *, slq=None, key=None):
        lags = lag_structure(system) if options.stationary else None  # None under a trace
        q, logdet, finite, solved = dataspace_evidence_parts(system, options.time_chunk, lags)
        return _parts(system, options, terms, q, logdet, finite, solved)

    def state_evidence_parts(self, state, terms, *, slq=None, key=None):
        if state.options.proxy:
            raise ValueError("the evidence needs log det D, and a data-space state set up by the stationary proxy "
                             "(a frame map: DataSpaceOptions(proxy) None or True) has only the proxy's D0, which "
                             "differs from D by aberration; use gcrsky.inference.log_evidence_system (builds the "
                             "exact D) or prepare with DataSpaceOptions(proxy=False)")
        sqrt_w = sqrt_weights(state.system)
        rt = _whitened_residual(state.system, sqrt_w)
        q = jnp.sum(rt * _d_solve(state.system, sqrt_w, state.gram, state.chol, rt), axis=-1)
        finite = _factor_finite(state.chol)
        if isinstance(state.chol, HostFactor):
            s = state.system
            logdet = host_logdet(jnp.asarray(state.chol.logdet), s.inv_noise, s.prior.inv_var, s.op.response)
        elif state.gram is None:
            logdet = logdet_no_grad(state.chol)
        else:
            logdet = cholesky_logdet(state.gram, state.chol)
        return _parts(state.system, state.options, terms, q, logdet, finite)
