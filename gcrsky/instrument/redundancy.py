"""Redundant baselines: grouping, verification and unique-row responses.

Two baselines are *redundant* when their responses are identical: the response of
baseline ``(i, j)`` (:func:`gcrsky.instrument.response_matrix`) depends on the antennas
only through the separation ``b_ij = x_j - x_i`` (gcrsky's and pyuvdata's sign,
:mod:`gcrsky.instrument.antennas`) and the beam pair ``(A_i, A_j)``.  A regular array (the
HERA hexagon) has many baselines sharing both.  For a group ``g`` of baselines with
the common response row ``X_g`` the likelihood depends on their data only through

    ``W_g = sum_b W_b``  and  ``d_g = sum_b W_b d_b / W_g``  (``d_g = 0`` where ``W_g = 0``)

per (frequency, time), with ``W_b = w_b / sigma_b^2`` the per-component inverse
noise variance (0 = flagged).  Indeed ``sum_b X_b^H W_b X_b = X_g^H W_g X_g`` and
``sum_b X_b^H W_b d_b = X_g^H W_g d_g``, so the precision ``P = X^T W X + S^-1``, the
Wiener right-hand side, the Wiener filter and the posterior are unchanged (up to
floating-point rounding of the sums, ~1e-16 relative), and the GCR fluctuation term
``X^T W^1/2 w`` keeps its distribution ``N(0, X^T W X)`` (it is a different draw
for a fixed key, since there are fewer noise variates).  The baseline contraction of
every matrix-free product then costs ``Ngroups / Nbl`` of the uncompressed one.

Rules this module keeps:

* A baseline and its reverse are *not* merged: ``b_ji = -b_ij`` gives the complex
  conjugate response row (for real beam amplitudes), which is a different row; merging
  would need the data conjugated too.  They form separate groups (still exact, only
  less compression).  ``gcrsky.instrument.antpairs`` (``i < j``) on
  ``hex_array`` never produces a reversed pair: within a row ``j`` is east of ``i``,
  across rows ``j`` is south of ``i``.
* The beam pair is compared as the *ordered* pair of per-antenna beam labels
  ``(beam_i, beam_j)`` (beams are distinct objects, compared by identity as in
  :func:`gcrsky.instrument.unique_beams`).  For today's unpolarised real amplitudes
  ``A_i A_j`` is symmetric, so ``(a, b)`` and ``(b, a)`` would in fact give the same
  row; they are kept apart to stay valid for polarised / complex beams.
* Grouping is geometric (:func:`redundant_groups`); :func:`~gcrsky.model.compress_system` and
  :func:`~gcrsky.model.compress_problem` then *verify* that the response rows of every group agree
  to ``rtol`` and raise a ``ValueError`` naming the antenna pairs otherwise.  Nothing
  is merged on geometry alone, except in :func:`unique_response`, which never computes
  the other rows: there the guard is the phase bound
  ``2 pi max|b - b_rep| nu_max / c <= rtol``.

Typical use:

    groups = groups_for_array(array)                        # pairs = antpairs(Nant)
    cross, auto = redundant_responses(array, groups, freqs, lmax, nside)  # unique rows only
    prob = build_problem(array, freqs, lsts, lmax, nside, ..., responses=(cross, auto))
    small = compress_problem(prob, groups=groups)           # a Problem with Ngroups baselines
    draws, info = gcrsky.sample(key, small, 100)             # same posterior

or, on any :class:`~gcrsky.model.LinearSystem`, ``compress_system(system, groups)``
and the ``*_system`` functions of :mod:`gcrsky.inference`.  The compression of data
and systems lives in :mod:`gcrsky.model.compress`.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..base.units import SPEED_OF_LIGHT
from .antennas import AntennaArray
from .antennas import antpairs as all_antpairs
from .beams import unique_beams
from .response import response_matrix

__all__ = [
    "DEFAULT_RTOL",
    "DEFAULT_TOL_M",
    "RedundantGroups",
    "check_redundancy",
    "groups_for_array",
    "redundant_groups",
    "redundant_responses",
    "unique_response",
    "validate_groups",
]

#: Default grouping tolerance on separation vectors, metres.  Far above the rounding of
#: computed layouts (~1e-13 m for km-scale coordinates), far below any physical offset.
DEFAULT_TOL_M = 1e-9
#: Default tolerance on response rows within a group, relative to the frequency's max |R|.
DEFAULT_RTOL = 1e-10


class RedundantGroups(NamedTuple):
    """Baselines grouped by (separation vector, ordered beam pair).

    Groups are numbered in order of first occurrence in ``antpairs``; the
    representative of a group is its first baseline, so ``representative`` is
    strictly increasing and ``group_of[representative] == arange(Ngroups)``.

    Attributes:
        group_of: (Nbl,) int64, the group of each baseline.
        representative: (Ngroups,) int64 index (into the baselines) of each group's
            first baseline.
        counts: (Ngroups,) int64 number of baselines per group.
        antpairs: (Nbl, 2) int64 the antenna pairs that were grouped (a copy).
        vectors_m: (Ngroups, 3) float64 separation ``x_j - x_i`` of each
            representative, ENU metres.
        max_offset_m: (Ngroups,) float64 largest ``|b - b_rep|`` (metres) within
            each group (0 for exactly redundant layouts up to rounding).
    """

    group_of: np.ndarray
    representative: np.ndarray
    counts: np.ndarray
    antpairs: np.ndarray
    vectors_m: np.ndarray
    max_offset_m: np.ndarray

    @property
    def n_groups(self) -> int:
        return int(self.representative.shape[0])

    @property
    def n_baselines(self) -> int:
        return int(self.group_of.shape[0])

    @property
    def representative_antpairs(self) -> np.ndarray:
        """(Ngroups, 2) antenna pairs of the representatives."""
        return self.antpairs[self.representative]

    def members(self, g: int) -> np.ndarray:
        """Baseline indices of group ``g`` (increasing)."""
        return np.flatnonzero(self.group_of == g)


def _positions(positions_enu_m) -> np.ndarray:
    pos = np.asarray(positions_enu_m, np.float64)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3):
        raise ValueError(f"positions_enu_m must be (Nants, 2 or 3) ENU metres, got shape {pos.shape}")
    if pos.shape[1] == 2:
        pos = np.concatenate([pos, np.zeros((pos.shape[0], 1))], axis=1)
    if not np.all(np.isfinite(pos)):
        raise ValueError("antenna positions contain non-finite values")
    return pos


def redundant_groups(positions_enu_m, antpairs, beam_ids=None, *, tol_m: float = DEFAULT_TOL_M) -> RedundantGroups:
    """Group baselines with the same separation vector and the same ordered beam pair.

    Greedy in baseline order: each baseline joins the group whose representative
    (first member) has the same ``(beam_i, beam_j)`` and a separation within
    ``tol_m`` (Euclidean, metres), else starts a new group.  A baseline within
    ``tol_m`` of two representatives is an error (``tol_m`` comparable to the
    spacing between distinct baselines).  A baseline and its reverse are different
    groups (see the module docstring).

    Args:
        positions_enu_m: (Nants, 3) or (Nants, 2) ENU antenna positions, metres.
        antpairs: (Nbl, 2) antenna index pairs ``(i, j)``, baseline ``x_j - x_i``;
            autos ``(i, i)`` allowed (separation 0).
        beam_ids: (Nants,) labels of each antenna's beam (ints, strings: anything
            ``numpy.unique`` sorts); None means one beam for all.  For an
            :class:`~gcrsky.instrument.AntennaArray` use :func:`groups_for_array`.
        tol_m: grouping tolerance, metres (>= 0).  The default absorbs only the
            rounding of computed positions: exactness needs identical responses, and
            an offset ``delta`` changes the fringe phase by ``2 pi delta nu / c``
            (2e-9 rad for 1 nm at 100 MHz).  ``tol_m=0`` demands bit-identical
            vectors, which computed layouts miss by rounding (~1e-14 m): the
            10-antenna ``hex_array`` then gives 17 groups instead of 14.

    Returns:
        :class:`RedundantGroups` (numpy arrays; deterministic for given inputs).
    """
    pos = _positions(positions_enu_m)
    nant = pos.shape[0]
    pairs = np.array(antpairs, dtype=np.int64, copy=True)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.shape[0] < 1:
        raise ValueError(f"antpairs must be (Nbl>=1, 2) antenna indices, got shape {pairs.shape}")
    if pairs.min() < 0 or pairs.max() >= nant:
        raise ValueError(f"antpairs hold antenna indices outside [0, {nant})")
    if not (np.isfinite(tol_m) and tol_m >= 0):
        raise ValueError(f"tol_m must be a finite non-negative length in metres, got {tol_m}")
    if beam_ids is None:
        bid = np.zeros(nant, np.int64)
    else:
        labels = np.asarray(beam_ids)
        if labels.shape != (nant,):
            raise ValueError(f"beam_ids must have one label per antenna, shape ({nant},), got {labels.shape}")
        bid = np.unique(labels, return_inverse=True)[1].reshape(nant).astype(np.int64)

    vec = pos[pairs[:, 1]] - pos[pairs[:, 0]]  # (Nbl, 3)
    beam_pair = bid[pairs[:, 0]] * (bid.max() + 1) + bid[pairs[:, 1]]  # ordered-pair code
    # hash representatives by (beam pair, cell of side >= tol_m): any representative within
    # tol_m of a vector lies in one of the 27 cells around it.  O(Nbl) lookups in all.
    cell_m = max(float(tol_m), 1e-12 * max(1.0, float(np.max(np.abs(vec)))))  # no int64 overflow
    cells = np.floor(vec / cell_m).astype(np.int64)
    near = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)], np.int64)
    nbl = pairs.shape[0]
    group_of = np.empty(nbl, np.int64)
    reps: list[int] = []
    table: dict[tuple, list[int]] = {}
    for b in range(nbl):
        bp = int(beam_pair[b])
        cand = [g for c in cells[b] + near for g in table.get((bp, *c.tolist()), ())]
        hit = sorted({g for g in cand if np.linalg.norm(vec[reps[g]] - vec[b]) <= tol_m})
        if len(hit) > 1:
            names = ", ".join(f"{tuple(int(x) for x in pairs[reps[g]])}" for g in hit)
            raise ValueError(
                f"baseline {b} {tuple(int(x) for x in pairs[b])} is within tol_m={tol_m} m of several "
                f"distinct baselines ({names}): tol_m is too large for this layout"
            )
        if hit:
            group_of[b] = hit[0]
        else:
            group_of[b] = len(reps)
            table.setdefault((bp, *cells[b].tolist()), []).append(len(reps))
            reps.append(b)
    representative = np.asarray(reps, np.int64)
    counts = np.bincount(group_of, minlength=representative.size).astype(np.int64)
    offset = np.linalg.norm(vec - vec[representative[group_of]], axis=1)
    max_offset = np.zeros(representative.size)
    np.maximum.at(max_offset, group_of, offset)
    return RedundantGroups(group_of, representative, counts, pairs, vec[representative].copy(), max_offset)


def groups_for_array(array: AntennaArray, antpairs=None, *, tol_m: float = DEFAULT_TOL_M) -> RedundantGroups:
    """:func:`redundant_groups` for an :class:`~gcrsky.instrument.AntennaArray`.

    Beams are told apart by object identity (:func:`gcrsky.instrument.unique_beams`,
    as the response builders do).  ``antpairs`` defaults to
    ``gcrsky.instrument.antpairs(Nants)`` (all cross-correlations, ``i < j``, the
    order :func:`gcrsky.model.build_problem` uses).
    """
    nant = array.positions_enu_m.shape[0]
    pairs = all_antpairs(nant) if antpairs is None else antpairs
    return redundant_groups(array.positions_enu_m, pairs, unique_beams(array.beams)[1], tol_m=tol_m)


def validate_groups(groups: RedundantGroups, nbl: int) -> None:
    g, rep = np.asarray(groups.group_of), np.asarray(groups.representative)
    if g.shape != (nbl,):
        raise ValueError(f"groups cover {g.shape[0]} baselines but the system has {nbl}")
    if rep.ndim != 1 or rep.size < 1 or rep.min() < 0 or rep.max() >= nbl:
        raise ValueError("groups.representative must be (Ngroups,) baseline indices")
    if g.min() < 0 or g.max() >= rep.size or not np.array_equal(g[rep], np.arange(rep.size)):
        raise ValueError("inconsistent groups: group_of[representative] must be arange(Ngroups)")


def check_redundancy(response, groups: RedundantGroups, *, rtol: float = DEFAULT_RTOL, freqs_hz=None) -> float:
    """Verify that every group's response rows agree; return the worst relative difference.

    For each frequency ``f`` and baseline ``b`` in group ``g`` with representative
    ``r``: ``max_k |R[f,b,k] - R[f,r,k]| <= rtol * max_{b',k} |R[f,b',k]|``, i.e.
    relative to the largest response at that frequency (over all baselines).  Not
    relative to the row's own max: a long baseline's low-l row can be 1e-5 of the
    largest (its fringe nearly cancels over the beam), while rounding in the
    quadrature scales with the beam, not with the row, so identical rows of the
    10-antenna hexagon (lmax 6, nside 32) differ by 3.6e-11 of their own max but
    1.4e-15 of the frequency's max.  The scale used is also the one that matters:
    a row difference ``dR`` changes ``X^T W X`` by ~``|dR| / max|R|`` relative.
    Non-identical rows differ far more: a 1 mm offset or a different dish diameter
    gives >~1e-5 of the max.  Runs in numpy (outside jit).

    Args:
        response: (Nf, Nbl, n) complex response (a concrete array, not a tracer).
        groups: the grouping of the Nbl baselines.
        rtol: tolerance relative to the frequency's max |R|.
        freqs_hz: optional (Nf,) frequencies, only to name them in the error.

    Returns:
        The largest relative row difference found (0.0 without multi-baseline groups).

    Raises:
        ValueError: naming up to 5 offending baselines (index, antenna pair,
            representative, frequency, relative difference).
    """
    if isinstance(response, jax.core.Tracer):
        raise TypeError(
            "check_redundancy needs concrete arrays: call it (or compress_system with check=True) "
            "outside jax.jit, or pass check=False inside jit after checking once outside"
        )
    R = np.asarray(response)
    if R.ndim != 3:
        raise ValueError(f"response must be (Nf, Nbl, n), got shape {R.shape}")
    validate_groups(groups, R.shape[1])
    if not (rtol >= 0):
        raise ValueError(f"rtol must be >= 0, got {rtol}")
    rep_of = np.asarray(groups.representative)[np.asarray(groups.group_of)]  # (Nbl,)
    members = np.flatnonzero(rep_of != np.arange(R.shape[1]))
    if members.size == 0:
        return 0.0
    worst = np.zeros((R.shape[0], members.size))
    for f in range(R.shape[0]):  # one frequency at a time: memory O(Nbl n)
        diff = np.max(np.abs(R[f, members] - R[f, rep_of[members]]), axis=1)
        scale = np.max(np.abs(R[f]))
        with np.errstate(divide="ignore", invalid="ignore"):
            worst[f] = diff / scale if scale > 0 else np.where(diff > 0, np.inf, 0.0)
    bad_f, bad_m = np.nonzero(~(worst <= rtol))  # NaN counts as bad
    if bad_f.size:
        order = np.argsort(-np.nan_to_num(worst[bad_f, bad_m], nan=np.inf), kind="stable")
        seen, lines = set(), []
        for k in order:
            b = int(members[bad_m[k]])
            if b in seen:
                continue
            seen.add(b)
            r, f = int(rep_of[b]), int(bad_f[k])
            fname = f"{float(np.asarray(freqs_hz)[f]) / 1e6:g} MHz" if freqs_hz is not None else f"frequency index {f}"
            lines.append(
                f"baseline {b} {tuple(int(x) for x in groups.antpairs[b])} vs its group's representative "
                f"{r} {tuple(int(x) for x in groups.antpairs[r])}: max|dR|/max|R| = {worst[f, bad_m[k]]:.3g} at {fname}"
            )
            if len(lines) == 5:
                break
        nbad = np.unique(members[bad_m]).size
        raise ValueError(
            f"{nbad} baseline(s) grouped as redundant have response rows differing by more than rtol={rtol:g} "
            "of the largest response; refusing to merge non-identical responses (the compression would not "
            "be exact). Offenders: " + "; ".join(lines) + ". Regroup with a smaller tol_m or fix the layout / beams."
        )
    return float(np.max(worst))


def unique_response(
    array: AntennaArray,
    groups: RedundantGroups,
    freqs_hz,
    lmax: int,
    nside: int,
    *,
    lst_ref_rad: float = 0.0,
    method: Literal["auto", "quadrature", "sht"] = "auto",
    rtol: float = DEFAULT_RTOL,
    pols=None,
) -> jax.Array:
    """Response rows of the group representatives only: (Nf, Ngroups, (lmax+1)**2) complex.

    Costs ``Ngroups / Nbl`` of building every row.  The other rows are never
    computed, so the guard is geometric: every member's separation is within
    ``max_offset_m`` of its representative's, which moves the fringe phase by at
    most ``2 pi max_offset_m nu_max / c``; that must be ``<= rtol`` (it is ~1e-13
    for computed hexagons).  Beams were matched by :func:`groups_for_array`.

    Args:
        array: the :class:`~gcrsky.instrument.AntennaArray` the groups were made for.
        groups: from :func:`groups_for_array` (the same array; beams by identity).
        freqs_hz, lmax, nside, lst_ref_rad: as for :func:`gcrsky.instrument.response_matrix`.
        method: ``"auto"`` (``response_matrix``'s choice by lmax), ``"quadrature"``
            (:func:`gcrsky.instrument.response_matrix` by rings) or ``"sht"``
            (:func:`gcrsky.instrument.response_sht.response_matrix_sht`).
        rtol: bound on the phase offset above.
        pols: None (the unpolarised kernel) or the product of each group, (Ngroups,) names
            (:func:`gcrsky.instrument.response_matrix`'s ``pols``; groups never mix products).

    Returns:
        ``R_u`` with ``R_u[:, g]`` the row of group ``g``; the full response is
        ``R_u[:, groups.group_of]``.
    """
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    nant = array.positions_enu_m.shape[0]
    if groups.antpairs.size and groups.antpairs.max() >= nant:
        raise ValueError(f"groups refer to antennas beyond this array's {nant}")
    vec = array.positions_enu_m[groups.antpairs[:, 1]] - array.positions_enu_m[groups.antpairs[:, 0]]
    if not np.allclose(vec[groups.representative], groups.vectors_m, rtol=0.0, atol=1e-12 + float(np.max(groups.max_offset_m))):
        raise ValueError("groups were made for a different layout than this array's")
    # beams: members must share the representative's ordered beam pair (by identity)
    bidx = unique_beams(array.beams)[1]
    bp = np.stack([bidx[groups.antpairs[:, 0]], bidx[groups.antpairs[:, 1]]], axis=1)
    if not np.array_equal(bp, bp[groups.representative[groups.group_of]]):
        raise ValueError("groups merge baselines with different beam pairs for this array; use groups_for_array(array)")
    phase = 2 * np.pi * float(np.max(groups.max_offset_m)) * float(np.max(freqs)) / SPEED_OF_LIGHT
    if phase > rtol:
        raise ValueError(
            f"group members are up to {float(np.max(groups.max_offset_m)):.3g} m from their representative: "
            f"a fringe phase offset of {phase:.3g} rad > rtol={rtol:g}; the unique rows would not be exact "
            "(regroup with a smaller tol_m)"
        )
    reps = groups.representative_antpairs
    how = {"auto": "auto", "quadrature": "rings", "sht": "sht"}.get(method)
    if how is None:
        raise ValueError(f"method must be 'auto', 'quadrature' or 'sht', got {method!r}")
    return response_matrix(array, reps, freqs, lmax, nside, lst_ref_rad=lst_ref_rad, method=how,
                           pols=None if pols is None else list(pols))


def redundant_responses(
    array: AntennaArray,
    groups: RedundantGroups,
    freqs_hz,
    lmax: int,
    nside: int,
    *,
    lst_ref_rad: float = 0.0,
    method: Literal["auto", "quadrature", "sht"] = "auto",
    rtol: float = DEFAULT_RTOL,
) -> tuple[jax.Array, jax.Array]:
    """``(cross, auto)`` responses for ``build_problem(..., responses=...)``, unique rows only.

    ``cross`` (Nf, Nbl, n) is :func:`unique_response` expanded by ``group_of`` (a
    gather: every member gets its representative's row exactly); ``auto``
    (Nf, Nants, n) is computed once per distinct beam (all autos have separation 0)
    and expanded likewise.  ``groups`` must cover ``antpairs(Nants)`` in that order
    (what :func:`groups_for_array` gives by default), as ``build_problem`` does.
    ``lmax`` is the response's degree (``lmax + frame_pad`` for real observing times).
    """
    nant = array.positions_enu_m.shape[0]
    if not np.array_equal(groups.antpairs, all_antpairs(nant)):
        raise ValueError("redundant_responses needs groups of antpairs(Nants) in that order (groups_for_array(array))")
    R_u = unique_response(array, groups, freqs_hz, lmax, nside, lst_ref_rad=lst_ref_rad, method=method, rtol=rtol)
    auto_groups = groups_for_array(array, np.stack([np.arange(nant)] * 2, axis=1))
    A_u = unique_response(array, auto_groups, freqs_hz, lmax, nside, lst_ref_rad=lst_ref_rad, method=method, rtol=rtol)
    return (
        jnp.take(R_u, jnp.asarray(groups.group_of), axis=1),
        jnp.take(A_u, jnp.asarray(auto_groups.group_of), axis=1),
    )
