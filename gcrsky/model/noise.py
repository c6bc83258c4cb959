"""Noise model: radiometer noise from auto-visibilities, flags as weights.

Convention: complex noise ``n = n_re + i n_im`` with ``n_re, n_im ~ N(0, sigma^2)``
independent, so ``E|n|^2 = 2 sigma^2``.  Everywhere in gcrsky ``sigma`` means the
*per-component* standard deviation.  The radiometer equation gives
``E|n|^2 = V_ii V_jj / (dt dnu)``, hence ``sigma^2 = V_ii V_jj / (2 dt dnu)``.

Weights ``w`` (0 = flagged, 1 = kept, fractional allowed) multiply the inverse
noise variance: ``W = w / sigma^2`` per component (so a fractional weight means a
noise variance ``sigma^2 / w``).  Boolean flags (True = bad, the pyuvdata
convention) become weights with :func:`weights_from_flags`.  Flagged samples
contribute nothing: :func:`clean_data` sets their data to exactly 0 whatever they
held (NaN, +-Inf, 1e300, ...), so the posterior cannot depend on them, not even
through ``0 * inf = NaN``.  Non-finite data are allowed only where ``w == 0``;
anywhere else they are an error naming the sample.
"""

from __future__ import annotations

from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "radiometer_sigma",
    "radiometer_variance",
    "time_difference_variance",
    "adjacent_times",
    "inverse_variance",
    "draw_noise",
    "clean_data",
    "weights_from_flags",
]


def radiometer_variance(auto_i, auto_j, dt_s, dnu_hz, nsamples=1.0) -> np.ndarray:
    """The radiometer equation: per-component noise variance ``V_ii V_jj / (2 dt dnu N)``.

    The one implementation of the equation in gcrsky (simulated problems through
    :func:`radiometer_sigma`, real files through :func:`gcrsky.model.problem_from_observation`
    and :func:`gcrsky.ingest.inspect_uvdata`).  Elementwise and NaN-propagating, with no checks,
    so that a missing or flagged autocorrelation (NaN) or a zero ``nsamples`` (Inf) marks
    the samples whose noise is unknown.

    Args:
        auto_i, auto_j: real auto-visibilities ``V_ii``, ``V_jj`` (any broadcastable shapes,
            e.g. (Nf, Nt, Nbl); the file's units, or K sr).
        dt_s: integration time, seconds (broadcastable, e.g. (1, Nt, Nbl)).
        dnu_hz: channel width, Hz (broadcastable, e.g. (Nf, 1, 1)).
        nsamples: the samples' nsample ``N`` (broadcastable; default 1).

    Returns:
        the per-component variance ``sigma^2`` (each of Re, Im), in the autos' units squared.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return auto_i * auto_j / (2.0 * dt_s * dnu_hz * nsamples)


def radiometer_sigma(
    auto_i, auto_j, dt_s: float, dnu_hz: float, *, convention: Literal["per_component", "total"] = "per_component"
) -> np.ndarray:
    """Noise standard deviation from the radiometer equation (:func:`radiometer_variance`).

    Args:
        auto_i, auto_j: real auto-visibilities ``V_ii``, ``V_jj`` (any broadcastable shape).
        dt_s: integration time, seconds.  dnu_hz: channel width, Hz.
        convention: ``"per_component"`` (default) returns ``sigma`` with
            ``sigma^2 = V_ii V_jj / (2 dt dnu)`` (each of Re, Im);
            ``"total"`` returns ``sqrt(E|n|^2) = sqrt(V_ii V_jj / (dt dnu))``.
    """
    if not (dt_s > 0 and dnu_hz > 0):
        raise ValueError(f"dt_s and dnu_hz must be positive, got {dt_s}, {dnu_hz}")
    ai, aj = np.asarray(auto_i, np.float64), np.asarray(auto_j, np.float64)
    if np.any(ai <= 0) or np.any(aj <= 0):
        raise ValueError("auto-visibilities must be positive to define radiometer noise")
    if convention not in ("per_component", "total"):
        raise ValueError(f"convention must be 'per_component' or 'total', got {convention!r}")
    var = radiometer_variance(ai, aj, dt_s, dnu_hz)  # exact powers of two apart from V_ii V_jj / (dt dnu)
    return np.sqrt(var) if convention == "per_component" else np.sqrt(2.0 * var)


#: Integrations further apart than this many steps are not adjacent (a gap between files or nights): no
#: time difference spans them.  The step is the longer of the integration time and the median
#: separation (a sparse simulation's uniform steps stay adjacent).
ADJACENT_GAP = 1.5


def adjacent_times(times_jd, integration_time_s) -> np.ndarray:
    """(Nt-1,) bool: whether integrations ``t`` and ``t+1`` are adjacent (their separation at most
    :data:`ADJACENT_GAP` steps, a step the longer of the integration time and the median separation),
    so that a time difference between them sees only noise and the sky's drift over one step; files
    of a night abut, nights (and snapshots hours apart in a night of 10-second integrations) do not.

    Args:
        times_jd: (Nt,) increasing Julian dates.
        integration_time_s: (Nt, Nbl) or (Nt,) seconds (0 where absent); the longest per time is used, and
            a time without one takes the median step.
    """
    t = np.asarray(times_jd, np.float64)
    if t.size < 2:
        return np.zeros(0, bool)
    step = np.diff(t) * 86400.0
    it = np.asarray(integration_time_s, np.float64)
    it = it.max(axis=tuple(range(1, it.ndim))) if it.ndim > 1 else it
    med = float(np.median(step))
    it = np.maximum(np.where(it > 0, it, med), med)
    return step <= ADJACENT_GAP * np.maximum(it[1:], it[:-1])


def time_difference_variance(vis, usable, nsamples, adjacent=None) -> np.ndarray:
    """Per-component noise variance from time-adjacent differences, one level per channel and baseline.

    ``E|V_t+1 - V_t|^2 = 2 sigma_1^2 (1/N_t + 1/N_t+1)`` for white noise of variance
    ``sigma_1^2 / N`` per component: ``sigma_1^2`` is the mean of
    ``|V_t+1 - V_t|^2 / (2 (1/N_t + 1/N_t+1))`` over the usable adjacent pairs.  It includes
    any change of the sky between adjacent integrations (an overestimate for long
    integrations on long baselines).

    Args:
        vis: (Nf, Nt, Nbl) complex visibilities (time on axis 1).
        usable: (Nf, Nt, Nbl) bool, True where a sample is unflagged with a positive nsample.
        nsamples: (Nf, Nt, Nbl) nsample ``N`` of each sample.
        adjacent: (Nt-1,) bool, which consecutive integrations are adjacent (:func:`adjacent_times`);
            None: all.

    Returns:
        (Nf, Nt, Nbl) variance ``sigma_1^2 / N_t``; NaN for unusable samples and for a
        (channel, baseline) without a usable adjacent pair.
    """
    if vis.shape[1] < 2:
        raise ValueError("noise='diff' needs at least two integrations")
    ok = usable
    inv_n = np.where(ok, 1.0 / np.where(ok, nsamples, 1.0), 0.0)
    pair_ok = ok[:, 1:] & ok[:, :-1]
    if adjacent is not None:
        pair_ok = pair_ok & np.asarray(adjacent, bool)[None, :, None]
    d2 = np.abs(vis[:, 1:] - vis[:, :-1]) ** 2 / (2.0 * (inv_n[:, 1:] + inv_n[:, :-1]) + ~pair_ok)
    cnt = pair_ok.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        s1 = np.where(cnt > 0, np.sum(np.where(pair_ok, d2, 0.0), axis=1) / cnt, np.nan)  # (Nf, Nbl): sigma_1^2
    return s1[:, None, :] * np.where(ok, inv_n, np.nan)


def inverse_variance(sigma, weights=None) -> np.ndarray:
    """Per-component inverse variance ``w / sigma^2`` (flagged -> exactly 0).

    Args:
        sigma: per-component noise std, (Nf, Nt, Nbl), positive.
        weights: same shape, in [0, 1]; None means all ones.
    """
    sigma = np.asarray(sigma, np.float64)
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise ValueError("noise sigma must be finite and positive everywhere (flag with weights instead)")
    if weights is None:
        return 1.0 / sigma**2
    w = np.broadcast_to(np.asarray(weights, np.float64), sigma.shape)
    if not np.all(np.isfinite(w)) or np.any(w < 0) or np.any(w > 1):
        raise ValueError("weights must be finite and within [0, 1]")
    return w / sigma**2


def weights_from_flags(flags, weights=None, shape=None) -> np.ndarray:
    """Weights from boolean flags: 0 where flagged, ``weights`` (default 1) elsewhere.

    Args:
        flags: boolean array, True = flagged (bad), e.g. pyuvdata's ``flag_array``
            reshaped to (Nf, Nt, Nbl); any shape broadcastable to ``shape`` (e.g.
            (1, Nt, 1) to flag whole times at every frequency and baseline).
        weights: optional prior weights in [0, 1] (e.g. nsample fractions),
            broadcastable together with ``flags``.  Values under a flag are ignored
            (they may be NaN); unflagged ones must be finite and within [0, 1].
        shape: optional target shape, e.g. (Nf, Nt, Nbl); the result is broadcast
            to it and a mismatch is an error.  Default: the broadcast shape of
            ``flags`` and ``weights``.

    Returns:
        float64 weights of the broadcast shape, exactly 0.0 where flagged.

    Raises:
        TypeError: ``flags`` is not boolean (integers are refused rather than guessed:
            pass ``flags != 0`` or ``flags.astype(bool)`` explicitly).
        ValueError: shapes do not broadcast, or unflagged weights are outside [0, 1].
    """
    f = np.asarray(flags)
    if f.dtype != np.bool_:
        raise TypeError(
            f"flags must be a boolean array (True = flagged), got dtype {f.dtype}; "
            "convert explicitly, e.g. flags.astype(bool) or (flags != 0)"
        )
    w = np.ones((), np.float64) if weights is None else np.asarray(weights, np.float64)
    try:
        out_shape = np.broadcast_shapes(f.shape, w.shape) if shape is None else tuple(int(k) for k in shape)
        f = np.broadcast_to(f, out_shape)
        w = np.broadcast_to(w, out_shape)
    except ValueError:
        what = f"flags {f.shape}" + ("" if weights is None else f" and weights {w.shape}")
        target = "each other" if shape is None else f"the data shape {tuple(shape)} (Nf, Nt, Nbl)"
        raise ValueError(f"{what} do not broadcast to {target}") from None
    kept = w[~f]
    if not np.all(np.isfinite(kept)) or np.any(kept < 0) or np.any(kept > 1):
        raise ValueError("unflagged weights must be finite and within [0, 1]")
    return np.where(f, 0.0, w)


def _describe(value) -> str:
    """'NaN', '+Inf' or '-Inf' for a non-finite (real or complex) value."""
    parts = (value.real, value.imag) if np.iscomplexobj(value) else (value,)
    if any(np.isnan(p) for p in parts):
        return "NaN"
    return "+Inf" if any(p == np.inf for p in parts) else "-Inf"


def clean_data(data, inv_var, antpairs=None) -> np.ndarray:
    """Zero every flagged sample; error on any non-finite unflagged sample.

    Args:
        data: (Nf, Nt, Nbl) complex visibilities (any leading batch axes allowed).
        inv_var: per-component inverse variance ``w / sigma^2``, broadcastable to
            ``data``; 0 marks a flagged sample.
        antpairs: optional (Nbl, 2) antenna indices of the baselines, only used to
            name the antennas of a bad sample in the error message.

    Returns:
        a copy of ``data`` with flagged samples set to exactly 0 (whatever they held:
        NaN, +-Inf or finite garbage), so nothing downstream can depend on them.

    Raises:
        ValueError: some unflagged sample is NaN, +Inf or -Inf.  The message counts
            each kind and names the first few as (freq, time, baseline) indices, with
            the antenna pair when ``antpairs`` is given.
    """
    d = np.asarray(data)
    iv = np.asarray(inv_var)
    try:
        iv = np.broadcast_to(iv, d.shape)
    except ValueError:
        raise ValueError(f"inverse variance of shape {iv.shape} does not broadcast to the data's {d.shape}") from None
    flagged = ~(iv > 0)
    bad = ~np.isfinite(d) & ~flagged
    if np.any(bad):
        locs = np.argwhere(bad)
        kinds = [_describe(d[tuple(i)]) for i in locs]
        counts = ", ".join(f"{kinds.count(k)} {k}" for k in ("NaN", "+Inf", "-Inf") if k in kinds)
        shown = []
        for i, kind in zip(locs[:5], kinds[:5]):
            where = tuple(int(j) for j in i)
            v = d[tuple(i)]
            v = complex(v) if np.iscomplexobj(v) else float(v)
            text = f"{kind} (value {v}) at (freq, time, baseline) = {where[-3:] if len(where) >= 3 else where}"
            if len(where) > 3:
                text += f" of batch {where[:-3]}"
            if antpairs is not None and len(where) >= 1:
                ap = np.asarray(antpairs)[where[-1]]
                text += f" (antennas {int(ap[0])}-{int(ap[1])})"
            shown.append(text)
        more = f"; and {len(locs) - 5} more" if len(locs) > 5 else ""
        raise ValueError(
            f"data contain {len(locs)} non-finite unflagged samples ({counts}): "
            + "; ".join(shown)
            + more
            + ". Flag them (weight 0) or fix the data."
        )
    return np.where(flagged, np.zeros((), d.dtype), d)


def draw_noise(key: jax.Array, sigma) -> jax.Array:
    """Complex Gaussian noise, each component ``N(0, sigma^2)`` (sigma per component)."""
    sigma = jnp.asarray(sigma)
    kr, ki = jax.random.split(key)
    return sigma * jax.random.normal(kr, sigma.shape, sigma.dtype) + 1j * sigma * jax.random.normal(
        ki, sigma.shape, sigma.dtype
    )
