"""Goodness of fit: a posterior predictive check of the data against the model (DESIGN section 11).

**Exact, per channel.**  Under the model the data are marginally ``d ~ N(X a0, C)``,
``C = N + X S X^T``, so ``chi2 = (d - X a0)^T C^-1 (d - X a0)`` is exactly chi-square
with ``N_d`` degrees of freedom (real, unflagged values).  By Woodbury it is the minimum
of the Wiener objective, reached at the Wiener filter ``a_wf``:

    chi2 = (d - X a_wf)^T W (d - X a_wf) + (a_wf - a0)^T S^-1 (a_wf - a0)
         = r^T W r - b'^T (a_wf - a0),   r = d - X a0,  b' = X^T W r,

the second form being what :func:`gcrsky.inference.log_evidence` reports as
``EvidenceInfo.chi2`` (equal to it to 1e-8 in the tests).  The run's Wiener filter gives
it with no new solve; the first form is used: it has no cancellation (``r^T W r`` is
``SNR^2`` times larger than ``chi2`` on bright data) and its error is second order in the
solver's (``(a_wf - a*)^T P (a_wf - a*)``, never negative), where the second form's is
first order.  Prior directions that are flat (``inv_var = 0``) are fitted, not
predicted: each that the data constrain takes one degree of freedom (all of them, or the
eigen path's kept rank less the proper directions).  The p-value is the *upper* tail
``P(chi2_dof >= chi2)`` (a model that fits worse than its noise and prior say); the
lower tail ``p_value_low`` says the data vary far *less* than the model expects (noise or
prior too large: a flux scale far below the prior's, as redundantly calibrated data in
uncalibrated units give).  The fit is rejected when either tail of a channel is below
``alpha / (2 Nf)`` (two-sided, Bonferroni over channels, ``alpha = 1e-3``).

**Where, per sample.**  The Wiener residual ``d - X a_wf`` has covariance
``N - X P^-1 X^T <= N``: whitened by the noise alone, ``z = (d - X a_wf) / sigma`` per
real component has variance at most 1, so a group's ``sum z^2`` is stochastically below
chi-square with its count of values.  Groups (rows = baseline groups, times; channels and
components pooled) whose ``chi2/dof`` exceeds that chi-square's upper ``alpha / Ngroups``
quantile are outliers (a conservative test: a false alarm has probability at most
``alpha``); single values beyond ``|z| > z_max``, the normal's two-sided ``alpha /
Nvalues`` quantile, are counted.  On a right model the groups' ``chi2/dof`` sit
somewhat below 1 (by the fraction of each sample's variance the posterior explains).
"""

from __future__ import annotations

import logging

import jax.numpy as jnp
import numpy as np
from scipy import stats

__all__ = ["FIT_ALPHA", "FIT_NOTE", "fit_warning", "goodness_of_fit", "run_fit"]

log = logging.getLogger(__name__)

#: Family-wise false-alarm probability of the fit's rejection and of its outlier lists.
FIT_ALPHA = 1e-3
#: Groups listed per kind of outlier (the worst first).
MAX_LISTED = 10

FIT_NOTE = (
    "posterior predictive check: chi2 = (d - X a0)^T (N + X S X^T)^-1 (d - X a0) per channel, chi-square with dof "
    "= real unflagged data values (minus flat prior directions) under the model; p_value: upper tail, p_value_low: "
    "lower tail; rejected when either tail of a channel < alpha / (2 Nf) (two-sided, Bonferroni); rows / times: the Wiener residual whitened by the noise alone "
    "(variance <= 1 per value, so chi2/dof a little below 1 on a right model), outliers beyond the chi-square's "
    "upper alpha / Ngroups quantile (conservative); z_max: |z| threshold of single values (alpha / Nvalues two-sided)"
)


def _exact_chi2(system, a_wf, z2, rank=None) -> tuple[np.ndarray, np.ndarray]:
    """Per channel ``(chi2, dof)`` of the data's marginal distribution (module docstring's first form;
    ``z2`` (Nf, Nt, Nrow) the noise-whitened squared Wiener residual; ``rank`` (Nf,) the eigen path's
    kept rank, where flat directions the data do not constrain were dropped)."""
    iv = np.asarray(system.prior.inv_var)
    shift = np.asarray(a_wf) - np.asarray(system.prior.mean)
    chi2 = z2.sum(axis=(1, 2)) + np.sum(np.where(iv > 0, iv * shift**2, 0.0), axis=1)
    n_data = 2.0 * np.sum(np.asarray(system.inv_noise) > 0, axis=(1, 2))
    n_flat = np.sum(iv <= 0, axis=1)
    fitted = n_flat if rank is None else np.minimum(n_flat, np.asarray(rank) - (iv.shape[1] - n_flat))
    return chi2, n_data - fitted


def _groups(z2: np.ndarray, count: np.ndarray, labels, alpha: float) -> dict:
    """chi2/dof per group, the threshold and the outliers (worst first) of one grouping."""
    ok = count > 0
    per = np.where(ok, z2 / np.where(ok, count, 1), np.nan)
    n_groups = max(int(ok.sum()), 1)
    limit = np.where(ok, stats.chi2.isf(alpha / n_groups, np.maximum(count, 1)) / np.maximum(count, 1), np.nan)
    bad = np.flatnonzero(ok & (per > limit))
    bad = bad[np.argsort(-per[bad])][:MAX_LISTED]
    return {"chi2_per_dof": [None if not np.isfinite(x) else float(x) for x in per],
            "n_outliers": int(np.sum(ok & (per > limit))),
            "outliers": [{"index": int(i), "label": labels[i], "chi2_per_dof": float(per[i]),
                          "threshold": float(limit[i])} for i in bad]}


def _whitened_residual(sys, prob, a_wf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(z2, count, zabs)`` (Nf, Nt, Nrow): the noise-whitened squared Wiener residual summed over the
    two real components, their count (0 or 2) and the larger |z| of the two."""
    w = np.asarray(sys.inv_noise)
    r = np.asarray(sys.data) - np.asarray(prob.visibilities(jnp.asarray(a_wf)))
    kept = w > 0
    z2 = np.where(kept, w * (r.real**2 + r.imag**2), 0.0)
    zabs = np.where(kept, np.sqrt(w) * np.maximum(np.abs(r.real), np.abs(r.imag)), 0.0)
    return z2, 2.0 * kept, zabs


def _residual_groups(prob, z2, count, zabs, alpha: float) -> dict:
    """The noise-whitened Wiener residual by row, by time and single values (module docstring)."""
    pairs = np.asarray(prob.antpairs)
    pols = prob.pols or ("",) * pairs.shape[0]
    conv = getattr(getattr(prob, "config", None), "conventions", None) or {}
    numbers = conv.get("antenna_numbers")  # a file's: rows labelled by its antenna numbers, not indices
    name = (lambda k: str(int(numbers[int(k)]))) if numbers is not None and len(numbers) > pairs.max(initial=0) \
        else (lambda k: str(int(k)))
    rows = [f"{name(i)}-{name(j)}{' ' + p if p else ''}" for (i, j), p in zip(pairs, pols)]
    times = [f"t{k}" for k in range(z2.shape[1])]
    n_values = max(int(count.sum()), 1)
    z_max = float(stats.norm.isf(alpha / (2 * n_values)))
    return {"rows": _groups(z2.sum(axis=(0, 1)), count.sum(axis=(0, 1)), rows, alpha),
            "times": _groups(z2.sum(axis=(0, 2)), count.sum(axis=(0, 2)), times, alpha),
            "residual_chi2_per_dof": [float(x) for x in z2.sum(axis=(1, 2)) / np.maximum(count.sum(axis=(1, 2)), 1)],
            "z_max": z_max, "n_values_beyond_z_max": int(np.sum(zabs > z_max))}


def goodness_of_fit(prob, wiener, *, alpha: float = FIT_ALPHA, rank=None) -> dict:
    """The posterior predictive check of a problem's data given its Wiener filter (module docstring).

    Args:
        prob: a :class:`~gcrsky.model.Problem`.
        wiener: (Nf, n) its posterior mean (the Wiener filter), K.
        alpha: family-wise false-alarm probability of the rejection and the outlier lists.
        rank: (Nf,) the eigen path's kept rank (flat prior directions the data do not
            constrain are dropped, and take no degree of freedom), or None.

    Returns:
        a JSON-friendly dict: ``chi2`` (Nf), ``dof`` (Nf), ``chi2_per_dof`` (Nf),
        ``p_value`` (Nf, upper tail), ``p_value_low`` (Nf) (None where no degree of freedom
        is left), ``alpha``, ``threshold_p``
        (``alpha / (2 Nf)``, each tail), ``rejected_channels``, ``rejected`` (bool), ``rows`` and
        ``times`` (chi2/dof of the noise-whitened Wiener residual per group, outliers),
        ``residual_chi2_per_dof`` (Nf), ``z_max``, ``n_values_beyond_z_max``, ``note``.
    """
    sys = prob.system()
    z2, count, zabs = _whitened_residual(sys, prob, wiener)
    chi2, dof = _exact_chi2(sys, wiener, z2, rank)
    ok = dof > 0  # no degree of freedom left (the data fitted exactly): nothing to test
    dof_safe = np.maximum(dof, 1)
    p_up = stats.chi2.sf(chi2, dof_safe)
    p_low = stats.chi2.cdf(chi2, dof_safe)
    threshold = alpha / (2 * chi2.size)
    rejected = np.flatnonzero((np.minimum(p_up, p_low) < threshold) & ok)

    def per_channel(x):
        return [float(v) if k else None for v, k in zip(x, ok)]

    out = {"chi2": chi2.tolist(), "dof": dof.tolist(), "chi2_per_dof": per_channel(chi2 / dof_safe),
           "p_value": per_channel(p_up), "p_value_low": per_channel(p_low), "alpha": alpha, "threshold_p": threshold,
           "rejected_channels": rejected.tolist(), "rejected": bool(rejected.size),
           **_residual_groups(prob, z2, count, zabs, alpha), "note": FIT_NOTE}
    return out


#: Rejected channels named in :func:`fit_warning`'s line (the worst first; the rest counted).
MAX_NAMED_CHANNELS = 6


def fit_warning(gof: dict, freqs_hz) -> str | None:
    """The one WARNING line of a rejected fit (None when it is not rejected): how many channels, then each
    rejected channel (the worst first, up to :data:`MAX_NAMED_CHANNELS`) with its frequency, chi2/dof and
    the tail that rejects it, and what each tail means."""
    if not gof.get("rejected"):
        return None
    chans = sorted(gof["rejected_channels"], key=lambda k: min(gof["p_value"][k], gof["p_value_low"][k]))
    low = {k: gof["p_value_low"][k] < gof["p_value"][k] for k in chans}
    named = ", ".join(
        f"{float(freqs_hz[k]) / 1e6:.3f} MHz chi2/dof {gof['chi2_per_dof'][k]:.3g} ({'lower' if low[k] else 'upper'} "
        f"p {gof['p_value_low' if low[k] else 'p_value'][k]:.2g})" for k in chans[:MAX_NAMED_CHANNELS])
    if len(chans) > MAX_NAMED_CHANNELS:
        named += f" and {len(chans) - MAX_NAMED_CHANNELS} more"
    why = []
    if not all(low.values()):
        why.append("upper: the data vary more than noise and prior allow")
    if any(low.values()):
        why.append("lower: the data vary far less than the model expects (noise or prior too large, e.g. a flux "
                   "scale far below the prior's)")
    return (f"WARNING: the model does not fit the data in {len(chans)} of {len(gof['chi2'])} channels (chi2/dof "
            f"rejected at p < {gof['threshold_p']:.2g} in either tail): {named}; {'; '.join(why)}; see summary.json "
            f"goodness_of_fit")


def run_fit(prob, wiener, warnings: list, rank=None) -> dict | None:
    """The run's :func:`goodness_of_fit` (``summary.json``'s ``goodness_of_fit``); a rejected fit adds
    :func:`fit_warning`'s line to ``warnings`` and the log.  Non-finite inputs give None (the run's
    other warnings say why)."""
    if not np.isfinite(np.asarray(wiener)).all():
        log.warning("goodness of fit skipped: the Wiener filter is not finite")
        return None
    gof = goodness_of_fit(prob, wiener, rank=rank)
    line = fit_warning(gof, np.asarray(prob.freqs_hz))
    if line is not None:
        log.warning(line.removeprefix("WARNING: "))
        warnings.append(line)
    else:
        log.info("goodness of fit: chi2/dof %s (not rejected)", gof["chi2_per_dof"])
    return gof
