"""Exact compression of redundant baselines: data, systems and problems.

For a group ``g`` of baselines with a common response row (grouped and verified by
:mod:`gcrsky.instrument.redundancy`) the likelihood depends on their data only
through ``W_g = sum_b W_b`` and ``d_g = sum_b W_b d_b / W_g`` per (frequency, time),
with ``W_b`` the per-component inverse noise variance (0 = flagged).  So P, the
Wiener right-hand side and the posterior are unchanged (up to rounding, ~1e-16
relative) while every matrix-free product costs ``Ngroups / Nbl`` of the
uncompressed one.  See :mod:`gcrsky.instrument.redundancy` for the rules.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..instrument.antennas import AntennaArray
from ..instrument.redundancy import (
    DEFAULT_RTOL,
    DEFAULT_TOL_M,
    RedundantGroups,
    check_redundancy,
    groups_for_array,
    redundant_groups,
    validate_groups,
)
from .system import LinearSystem

#: Grouping tolerance of the automatic compression, metres: wide enough for the ~1e-9 m that positions
#: read through ECEF differ by (at the default 1e-9 m such jitter splits groups and a hexagon's grouping is
#: refused as ambiguous), far below any array's spacing; exactness is then the phase guard's or the
#: response check's (:data:`gcrsky.model.observed.COMPRESS_RTOL`), not this tolerance's.
COMPRESS_TOL_M = 1e-6

__all__ = ["compress_problem", "compress_rows", "compress_system", "compress_visibilities", "row_groups"]


@partial(jax.jit, static_argnames=("n_groups",))
def compress_visibilities(data, inv_noise, group_of, n_groups: int):
    """Inverse-variance-weighted group sums of data and noise (the jittable core).

    Args:
        data: (..., Nbl) complex visibilities; ignored (treated as 0) where
            ``inv_noise == 0``, so flagged NaN/Inf cannot leak in.
        inv_noise: (..., Nbl) per-component inverse noise variance, >= 0.
        group_of: (Nbl,) int group of each baseline, in [0, n_groups).
        n_groups: number of groups (static).

    Returns:
        ``(data_g, inv_noise_g)``, each (..., n_groups): ``inv_noise_g = sum_b inv_noise_b``,
        ``data_g = sum_b inv_noise_b d_b / inv_noise_g`` (0 where ``inv_noise_g == 0``).
    """
    shape = inv_noise.shape[:-1] + (n_groups,)
    wd = jnp.where(inv_noise > 0, inv_noise * data, 0.0)
    iv_g = jnp.zeros(shape, inv_noise.dtype).at[..., group_of].add(inv_noise)
    wd_g = jnp.zeros(shape, wd.dtype).at[..., group_of].add(wd)
    ok = iv_g > 0
    return jnp.where(ok, wd_g / jnp.where(ok, iv_g, 1.0), 0.0), iv_g


def compress_system(
    system: LinearSystem, groups: RedundantGroups, *, rtol: float = DEFAULT_RTOL, check: bool = True
) -> LinearSystem:
    """The equivalent :class:`~gcrsky.model.LinearSystem` with one baseline per group.

    Response ``R[:, representative]`` (Nf, Ngroups, n), data and inverse noise
    compressed per (frequency, time) by :func:`compress_visibilities`; angles,
    frame and prior are passed through unchanged (the same objects).  P, the Wiener
    right-hand side and the posterior equal the uncompressed ones up to rounding.
    Inputs are not modified.  Compress before :func:`gcrsky.parallel.shard_system`
    (its zero-weight padding baselines are not in ``groups``).

    Args:
        system: the uncompressed system (Nbl baselines, in ``groups.antpairs`` order).
        groups: from :func:`redundant_groups` / :func:`groups_for_array`.
        rtol: tolerance of the row check (:func:`check_redundancy`).
        check: verify the rows first (needs concrete arrays, i.e. outside jit);
            ``check=False`` skips it and is jittable -- only for systems whose rows
            were already checked.

    Raises:
        ValueError: non-identical rows in a group (naming the baselines), shape
            mismatch, or negative / non-finite inverse noise (checked with ``check``).
    """
    nf, nbl, _ = system.op.response.shape
    if system.data.shape != (nf, system.op.angles.shape[0], nbl) or system.inv_noise.shape != system.data.shape:
        raise ValueError(
            f"data {system.data.shape} and inv_noise {system.inv_noise.shape} must be (Nf, Nt, Nbl) = "
            f"{(nf, system.op.angles.shape[0], nbl)}"
        )
    if check:
        check_redundancy(system.op.response, groups, rtol=rtol)
        iv = np.asarray(system.inv_noise)
        if not np.all(np.isfinite(iv)) or np.any(iv < 0):
            raise ValueError("inv_noise must be finite and >= 0 (0 = flagged)")
    else:
        validate_groups(groups, nbl)
    rep = jnp.asarray(groups.representative)
    data_g, iv_g = compress_visibilities(system.data, system.inv_noise, jnp.asarray(groups.group_of), groups.n_groups)
    op = system.op._replace(response=jnp.take(system.op.response, rep, axis=1))
    return LinearSystem(op, data_g, iv_g, system.prior)


def _pairs_groups(problem, array, pairs, tol_m) -> RedundantGroups:
    if array is not None:
        return groups_for_array(array, pairs, tol_m=tol_m)
    if problem.antpos_enu_m is None or problem.beam_ids is None:
        raise ValueError(
            "this Problem does not record its antenna layout (antpos_enu_m, beam_ids): pass array= (the "
            "gcrsky.instrument.AntennaArray it was built from) or groups="
        )
    return redundant_groups(problem.antpos_enu_m, pairs, beam_ids=np.asarray(problem.beam_ids), tol_m=tol_m)


def _problem_groups(problem, array, tol_m) -> RedundantGroups:
    """Redundant groups of the problem's rows; rows of different feed products never share a group."""
    return row_groups(np.asarray(problem.antpairs), problem.pols,
                      lambda pairs: _pairs_groups(problem, array, pairs, tol_m))


def row_groups(pairs, pols, group_pairs) -> RedundantGroups:
    """Redundant groups of rows ``pairs`` (Nrow, 2) with products ``pols`` (Nrow names, or None):
    ``group_pairs(pairs)`` groups the rows of one product (e.g. :func:`groups_for_array`); rows of
    different products never share a group; representatives in row order."""
    pairs = np.asarray(pairs)
    if pols is None or len(set(pols)) == 1:
        return group_pairs(pairs)
    pols = np.asarray(pols)
    group_of = np.empty(pairs.shape[0], np.int64)
    reps, vecs, offs = [], [], []
    for p in dict.fromkeys(pols.tolist()):  # in order of first appearance
        rows = np.flatnonzero(pols == p)
        g = group_pairs(pairs[rows])
        group_of[rows] = g.group_of + len(reps)
        reps.extend(rows[g.representative].tolist())
        vecs.append(g.vectors_m)
        offs.append(g.max_offset_m)
    order = np.argsort(np.asarray(reps), kind="stable")  # representatives in row order
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    rep = np.asarray(reps)[order]
    return RedundantGroups(rank[group_of], rep, np.bincount(rank[group_of], minlength=rep.size).astype(np.int64),
                           pairs.copy(), np.concatenate(vecs)[order], np.concatenate(offs)[order])


def compress_rows(data, sigma, weights, groups: RedundantGroups):
    """``(data_g, sigma_g, weights_g)`` (Nf, Nt, Ngroups) of rows (Nf, Nt, Nrow) merged by ``groups``.

    ``data_g`` the inverse-variance-weighted group average (0 where the whole group is flagged),
    ``sigma_g = 1/sqrt(sum_b w_b / sigma_b^2)`` (the unflagged group noise
    ``1/sqrt(sum_b 1/sigma_b^2)`` where the whole group is flagged) and ``weights_g`` 1 (0 there):
    :func:`compress_problem`'s numbers, without a response.
    """
    sigma = np.asarray(sigma, np.float64)
    iv = np.asarray(weights, np.float64) / sigma**2
    gof = jnp.asarray(groups.group_of)
    data_g, iv_g = compress_visibilities(jnp.asarray(data), jnp.asarray(iv), gof, groups.n_groups)
    _, iv_full = compress_visibilities(jnp.asarray(data), jnp.asarray(1.0 / sigma**2), gof, groups.n_groups)
    iv_g, iv_full = np.asarray(iv_g), np.asarray(iv_full)
    kept = iv_g > 0
    sigma_g = np.where(kept, 1.0 / np.sqrt(np.where(kept, iv_g, 1.0)), 1.0 / np.sqrt(iv_full))
    return data_g, sigma_g, kept.astype(np.float64)


def compress_problem(
    problem,
    array: AntennaArray | None = None,
    *,
    groups: RedundantGroups | None = None,
    tol_m: float = DEFAULT_TOL_M,
    rtol: float = DEFAULT_RTOL,
):
    """A :class:`~gcrsky.model.Problem` with one baseline per redundant group.

    The result is an ordinary Problem (``gcrsky.sample``, ``gcrsky.prepare``,
    ``gcrsky.wiener_filter`` and ``problem.system()`` accept it) with the same
    posterior: ``antpairs`` are the representatives' pairs, ``response`` their rows,
    ``data`` the inverse-variance-weighted group averages, ``sigma`` the group's
    per-component noise std ``1/sqrt(sum_b w_b/sigma_b^2)`` and ``weights`` 1 (0
    where the whole group is flagged; ``sigma`` is then the unflagged group noise
    ``1/sqrt(sum_b 1/sigma_b^2)`` and ``data`` 0).  So
    ``weights/sigma^2`` reproduces the compressed inverse noise to ~2 ulp.  Autos,
    LSTs, prior, frame, truth and static metadata are kept.  For the exact system
    without the sigma round trip use ``compress_system(problem.system(), groups)``.

    Args:
        problem: the uncompressed Problem.
        array: the :class:`~gcrsky.instrument.AntennaArray` it was built from.  If
            omitted, the positions and beam labels the Problem records
            (``antpos_enu_m``, ``beam_ids``, set by :func:`gcrsky.build_problem`)
            are used.
        groups: a precomputed grouping of ``problem.antpairs`` (then ``array`` and
            ``tol_m`` are not used).
        tol_m: grouping tolerance (:func:`redundant_groups`), metres.
        rtol: response-row check tolerance (:func:`check_redundancy`).

    Raises:
        ValueError: the grouping does not match the problem's baselines, or a group's
            responses differ (naming the antenna pairs).
    """
    if groups is None:
        groups = _problem_groups(problem, array, tol_m)
    pairs = np.asarray(problem.antpairs)
    if groups.antpairs.shape != pairs.shape or not np.array_equal(groups.antpairs, pairs):
        raise ValueError("groups were built for different antenna pairs than the problem's (order matters)")
    check_redundancy(problem.response, groups, rtol=rtol, freqs_hz=problem.freqs_hz)
    rep = jnp.asarray(groups.representative)
    data_g, sigma_g, kept = compress_rows(problem.data, problem.sigma, problem.weights, groups)
    pols = None if problem.pols is None else tuple(problem.pols[int(r)] for r in groups.representative)
    if pols is not None and any(problem.pols[b] != pols[g] for b, g in enumerate(np.asarray(groups.group_of))):
        raise ValueError("a redundant group mixes feed products (problem.pols): group each product apart")
    return dataclasses.replace(
        problem,
        pols=pols,
        antpairs=groups.representative_antpairs.copy(),
        response=jnp.take(problem.response, rep, axis=1),
        data=data_g,
        sigma=jnp.asarray(sigma_g),
        weights=jnp.asarray(kept),
        sigma_sky=None,  # not tracked through the merge (only a gain run uses it, and it keeps every baseline)
    )
