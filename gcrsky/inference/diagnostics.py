"""Has a Markov chain mixed?  The effective sample size of every sampled scalar, against a stated floor.

:func:`chain_diagnostics` takes the chain of a run (one chain; each entry a named scalar
``(ndraws,)`` or a named group of scalars ``(ndraws, k)``: the flux scale per channel, the
bandpass or gain modes) and returns a JSON-friendly block: per group the ESS of its
scalars (min, median, the worst few) and the split R-hat, and over all of them the
scalars whose ESS is below the floor.  :func:`diagnostics_warning` is its one WARNING
line (None when every scalar is above the floor).

**The floor**, :data:`ESS_FLOOR` = 100 effective draws per scalar, whatever the chain's
length.  The Monte-Carlo error of a posterior mean is ``sd / sqrt(ESS)``: 10 % of the
posterior sd at ESS 100.  A 95 % interval's end points come from the 2.5 % tails, ~2.5
effective draws each at ESS 100, so below it the intervals a summary reports are
themselves noise; Vehtari, Gelman, Simpson, Carpenter & Buerkner (2021, Bayesian
Analysis 16, 667; "Rank-normalization, folding, and localization") ask for an ESS of at
least 100 per chain for that reason.  A floor relative to the length (e.g. 10 % of the
draws) would pass a chain of 40 draws with ESS 4, whose interval is meaningless; an
absolute floor says that a short run cannot give intervals, which is true.  A chain
shorter than the floor is therefore always below it.

**The estimators.**  ESS: :func:`gcrsky.inference.effective_sample_size` (blackjax, Stan's
estimator: Geyer's initial monotone sequence).  Split R-hat: the chain cut into its two
halves, blackjax's ``potential_scale_reduction`` of them (near 1 for a stationary chain;
Vehtari et al. ask for < 1.01 with several chains; reported, not tested: one split chain
is a weak test).  A scalar that never moves (every draw equal: a Metropolis chain that
never accepted, a stuck Gibbs block) has no defined ESS: it is reported as ``null`` and
counted below the floor.  Fewer than :data:`MIN_DRAWS` draws: nothing is estimated (the
block says so and its ``ok`` is None).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["ESS_FLOOR", "MIN_DRAWS", "chain_diagnostics", "diagnostics_warning"]

#: Effective draws per sampled scalar below which a chain counts as not mixed (module docstring: why 100).
ESS_FLOOR = 100.0
#: Draws below which no ESS is estimated (the autocorrelation needs a few lags; split R-hat two halves of 2).
MIN_DRAWS = 4
#: Scalars listed by name, the worst first (the rest counted).
MAX_LISTED = 10
#: Groups up to this size list every scalar's ESS; larger ones their min, median and worst.
FULL_LIST = 16

DIAGNOSTICS_NOTE = (
    "effective sample size (ESS, blackjax / Stan's estimator) of every sampled scalar of one chain; floor: the ESS "
    "below which a scalar counts as not mixed (100: the Monte-Carlo error of a mean is 10 % of the posterior sd and a "
    "95 % interval's ends rest on ~2.5 effective draws each; Vehtari et al. 2021); below_floor: the worst scalars, "
    "'name[i]' the i-th of a group; ess null: the scalar never moved (counted below the floor); split_rhat: "
    "potential scale reduction of the chain's two halves (near 1 when stationary)"
)


def _ess_and_rhat(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ESS (k,) and split R-hat (k,) of one chain ``x`` (ndraws, k); NaN where a scalar never moves."""
    import jax.numpy as jnp

    from .collapsed import blackjax_module, effective_sample_size

    ess = np.asarray(effective_sample_size(jnp.asarray(x)[None]), np.float64)
    half = x.shape[0] // 2
    halves = jnp.asarray(np.stack([x[:half], x[half:2 * half]]))
    rhat = np.asarray(blackjax_module().diagnostics.potential_scale_reduction(halves, chain_axis=0, sample_axis=1),
                      np.float64)
    still = np.ptp(x, axis=0) == 0
    return np.where(still, np.nan, ess), np.where(still, np.nan, rhat)


def _number(v) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def chain_diagnostics(chains: dict, *, floor: float = ESS_FLOOR) -> dict:
    """The ESS of every sampled scalar of one Markov chain, against ``floor`` (module docstring).

    Args:
        chains: ``{name: draws}``, each ``draws`` a real array ``(ndraws,)`` (one scalar) or
            ``(ndraws, k)`` (``k`` scalars, ``name[i]`` the i-th), the same ``ndraws`` for all, in
            the chain's order (consecutive draws consecutive states).  E.g. ``{"flux_scale": q
            (ndraws, Nf), "gain_theta": theta (ndraws, P)}``.
        floor: the ESS below which a scalar counts as not mixed (default :data:`ESS_FLOOR`).

    Returns:
        a JSON-friendly dict: ``ndraws``, ``floor``, ``groups`` (per name: ``size``, ``ess_min``,
        ``ess_median``, ``split_rhat_max``, ``worst`` (up to 3 ``{"index", "ess"}``) and, for at most
        :data:`FULL_LIST` scalars, ``ess`` (every one's)), ``ess_min`` and ``worst`` (the least mixed
        scalar's ESS and name), ``n_scalars``, ``n_below_floor``, ``below_floor`` (up to
        :data:`MAX_LISTED` names, the worst first), ``ok`` (no scalar below the floor; None when
        there are fewer than :data:`MIN_DRAWS` draws and nothing was estimated), ``note``.
        ESS values are in draws; ``null`` where a scalar never moved.

    Raises:
        ValueError: no chains, a chain that is not 1-D or 2-D, or chains of different lengths.
    """
    if not chains:
        raise ValueError("chain_diagnostics needs at least one named chain")
    arrays, scalar = {}, {}
    for name, x in chains.items():
        x = np.asarray(x, np.float64)
        if x.ndim not in (1, 2):
            raise ValueError(f"chain {name!r} must be (ndraws,) or (ndraws, k), got shape {x.shape}")
        arrays[name], scalar[name] = x.reshape(x.shape[0], -1), x.ndim == 1
    lengths = {x.shape[0] for x in arrays.values()}
    if len(lengths) != 1:
        raise ValueError(f"the chains have different numbers of draws: {sorted(lengths)}")
    nd = lengths.pop()
    out = {"ndraws": nd, "floor": float(floor), "groups": {}, "ess_min": None, "worst": None,
           "n_scalars": int(sum(x.shape[1] for x in arrays.values())), "n_below_floor": None, "below_floor": [],
           "ok": None, "note": DIAGNOSTICS_NOTE}
    if nd < MIN_DRAWS:
        out["note"] = f"fewer than {MIN_DRAWS} draws: nothing estimated. " + DIAGNOSTICS_NOTE
        return out
    names, values = [], []
    for name, x in arrays.items():
        ess, rhat = _ess_and_rhat(x)
        k = x.shape[1]
        label = [name] if scalar[name] else [f"{name}[{i}]" for i in range(k)]
        key = np.where(np.isnan(ess), -1.0, ess)  # a scalar that never moved is the worst
        order = np.argsort(key, kind="stable")
        finite = ess[np.isfinite(ess)]
        block = {"size": k, "ess_min": None if np.isnan(ess).any() else _number(ess.min()),
                 "ess_median": _number(np.median(finite)) if finite.size else None,
                 "split_rhat_max": _number(np.nanmax(rhat)) if np.isfinite(rhat).any() else None,
                 "worst": [{"index": int(i), "ess": _number(ess[i])} for i in order[:3]]}
        if k <= FULL_LIST:
            block["ess"] = [_number(v) for v in ess]
        out["groups"][name] = block
        names += label
        values.append(key)
    key = np.concatenate(values)
    order = np.argsort(key, kind="stable")
    below = order[key[order] < floor]
    out.update(ess_min=_number(key[order[0]]) if key[order[0]] >= 0 else None, worst=names[order[0]],
               n_below_floor=int(below.size), below_floor=[names[i] for i in below[:MAX_LISTED]],
               ok=bool(below.size == 0))
    return out


def diagnostics_warning(block: dict, what: str = "the chain") -> str | None:
    """The WARNING line of a :func:`chain_diagnostics` block below its floor (None when it is not, or when
    nothing was estimated); ``what`` names the chain in the line (e.g. ``"the gain chain"``)."""
    if not block.get("n_below_floor"):
        return None
    ess = "never moved" if block["ess_min"] is None else f"ESS {block['ess_min']:.3g}"
    names = ", ".join(block["below_floor"][:5]) + (
        f" and {block['n_below_floor'] - 5} more" if block["n_below_floor"] > 5 else "")
    return (f"WARNING: {what} has not mixed: {block['n_below_floor']} of {block['n_scalars']} sampled scalars have an "
            f"effective sample size below {block['floor']:.0f} of {block['ndraws']} draws (worst {block['worst']}: "
            f"{ess}; {names}): its intervals are Monte-Carlo noise; run longer (more draws, "
            f"thinned) or burn in longer")
