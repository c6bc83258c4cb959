"""The band limit of a model: which degree a baseline needs, and what to do with those beyond ``lmax``.

**Reach of a baseline** (DESIGN section 11).  A zenith-pointed drift scan measures
``V(b) = int A_i A_j(s) T(s) exp(-2 pi i b.s / lambda) dOmega``: in the uv plane, the
sky's Fourier transform convolved with that of the power beam, whose support is the
aperture's autocorrelation, a disc of radius ``D / lambda`` wavelengths for a dish of
diameter ``D``.  So baseline ``b = (b_e, b_n)`` sees uv points with
``|u| <= |b_e| + D`` and ``|v| <= |b_n| + D`` (in wavelengths after dividing by
``lambda``).  A harmonic of degree ``l`` has angular wavenumber ``l`` (``l ~ 2 pi |u|``
for the flat-sky limit near zenith), so the baseline responds to degrees up to
driftscan's

    m_max = 2 pi (|b_e| + D) / lambda,
    l_max = 2 pi sqrt((|b_e| + D)^2 + (|b_n| + D)^2) / lambda

(:func:`baseline_reach` with ENU vectors; with lengths only, the isotropic rule
``2 pi (|b| + D) / lambda``).  For a beam without a dish (a UVBeam, a Gaussian), the
equivalent diameter is the Airy one of its measured FWHM, ``D = 1.029 lambda / FWHM``
(:func:`equivalent_dish_m`; pyuvdata's ``GaussianBeam(diameter=D)`` has FWHM
``~lambda / D``, so its equivalent is ``1.03 D``).  A Gaussian aperture has no hard
edge: the rule puts the reach at 2.7 sigma of its uv taper.

**Beyond lmax** (``mode``): a model truncated below a used baseline's reach absorbs
the baseline's unmodelled fringes into wrong low-l coefficients with small posterior
errors (``"truncate"``: today's behaviour, kept for controls).  Instead:

* ``"cut"`` (default): every (channel, row) whose reach exceeds ``lmax`` gets weight
  0, and rows cut at every channel are dropped (:func:`cut_rows`); what was cut is
  reported (count and lengths).
* ``"marginalise"``: the sky above ``lmax``, ``a_hi ~ N(0, S_hi)`` with the prior's
  C_l extended as a power law up to the reach (:func:`extend_cl`), is a Gaussian
  term ``X_hi S_hi X_hi^T`` in the data covariance.  The primal paths need a
  diagonal noise, so only its diagonal is added to the noise variance
  (:func:`marginalise_rows`).  For an isotropic ``S_hi`` that diagonal is the same at
  every time and in every frame (a rotation keeps ``sum_m |X_lm|^2`` per degree), so one
  response at the reach degree gives it: per component
  ``sigma_hi^2 = 1/2 sum_{l > lmax} var_k |X_k|^2``.  Approximated: the correlation of
  the high-l signal between times, rows and the real and imaginary parts, which the
  diagonal drops.  Measured against the exact answer (the dense posterior at the reach
  with the full prior, restricted to l <= lmax; ``tests/test_bandlimit.py``,
  ``benchmarks/band_limit.py``): 4 antennas of 6 m dishes at 40 and 45 MHz, 12 times,
  noise 0.02 K sr, lmax 12 with the sky drawn to l = 36, over 5 seeds: the Wiener filter
  differs from the exact one by 0.30-0.40 exact posterior standard deviations (rms over
  the modes), the posterior standard deviations are 0.70-1.79 x the exact ones (the
  dropped correlations make some directions over-, others under-confident), and the
  truth's whitened error z2 stays within its 99.9 % range (0.82-1.13 per channel;
  truncation: 3.8-22, cut: 0.80-1.18).  On matvis's visibilities of such a sky at real
  times (``tests/test_bandlimit.py``) z2 is 0.69 and 0.75: there the diagonal is
  conservative (a wider posterior than the exact one).  Cutting approximates nothing beyond the reach
  rule itself (a Gaussian beam's uv taper has no edge: what leaks past the rule stays
  unmodelled, within the noise in the test above).
"""

from __future__ import annotations

import dataclasses
import logging
import math

import jax.numpy as jnp
import numpy as np

from ..base.units import SPEED_OF_LIGHT
from ..sphere.modes import mode_table

__all__ = [
    "BAND_LIMIT_MODES",
    "apply_band_limit",
    "baseline_reach",
    "beam_dish_m",
    "check_quadrature",
    "choose_lmax",
    "cut_rows",
    "equivalent_dish_m",
    "extend_cl",
    "high_l_variance",
    "marginalise_rows",
    "memory_lmax",
    "observation_lmax",
    "observation_reach",
    "observation_rows",
    "problem_baselines",
    "required_lmax",
]

log = logging.getLogger(__name__)

#: What to do with rows whose reach exceeds lmax (module docstring).
BAND_LIMIT_MODES = ("cut", "marginalise", "truncate")

#: Airy FWHM factor: FWHM = AIRY * lambda / D for a uniformly illuminated circular aperture.
AIRY = 1.02899


def baseline_reach(baselines_m, freqs_hz, dish_diameter_m) -> np.ndarray:
    """The highest degree each baseline sees at each frequency (module docstring), (Nf, Nbl).

    Args:
        baselines_m: (Nbl, 2 or 3) ENU baseline vectors in metres (driftscan's form from
            the east and north components), or (Nbl,) lengths (``2 pi (|b| + D) / lambda``).
        freqs_hz: (Nf,) frequencies, Hz.
        dish_diameter_m: the dish (or equivalent) diameter, metres: a scalar or (Nf,).

    Returns:
        (Nf, Nbl) float reach ``l_max`` (not rounded).
    """
    b = np.asarray(baselines_m, np.float64)
    lam = SPEED_OF_LIGHT / np.atleast_1d(np.asarray(freqs_hz, np.float64))
    d = np.broadcast_to(np.asarray(dish_diameter_m, np.float64), lam.shape)
    if np.any(~(d > 0)):
        raise ValueError(f"dish_diameter_m must be positive, got {dish_diameter_m!r}")
    if b.ndim == 1:
        return 2 * np.pi * (np.abs(b)[None, :] + d[:, None]) / lam[:, None]
    if b.ndim != 2 or b.shape[1] not in (2, 3):
        raise ValueError(f"baselines_m must be (Nbl,) lengths or (Nbl, 2|3) ENU vectors, got shape {b.shape}")
    ue = np.abs(b[:, 0])[None, :] + d[:, None]
    vn = np.abs(b[:, 1])[None, :] + d[:, None]
    return 2 * np.pi * np.hypot(ue, vn) / lam[:, None]


def equivalent_dish_m(fwhm_rad, freq_hz) -> np.ndarray:
    """The Airy-equivalent dish diameter of a beam of FWHM ``fwhm_rad`` at ``freq_hz``: ``1.029 lambda / FWHM``, m."""
    return AIRY * SPEED_OF_LIGHT / np.asarray(freq_hz, np.float64) / np.asarray(fwhm_rad, np.float64)


def beam_dish_m(beams, freqs_hz, dish_diameter_m: float | None = None) -> np.ndarray:
    """(Nf,) the D of the reach: ``dish_diameter_m`` if given, else the largest Airy-equivalent
    diameter (:func:`equivalent_dish_m` of the measured FWHM) over the distinct beams; a beam
    whose FWHM cannot be measured (a dipole's wider than the sky, a pattern with negative
    power) counts as one wavelength across (FWHM ~ 59 deg: conservative, a larger reach, for
    anything wider)."""
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if dish_diameter_m is not None:
        return np.full(freqs.shape, float(dish_diameter_m))
    from ..instrument.beams import beam_fwhm_rad

    def dish(beam, f):
        try:
            return float(equivalent_dish_m(beam_fwhm_rad(beam, f), f))
        except ValueError as err:  # no half-power point, or a power pattern that cannot be measured
            log.info("band limit: the beam's FWHM at %.4g MHz cannot be measured (%s): D = one wavelength", f / 1e6,
                     err)
            return SPEED_OF_LIGHT / f

    distinct = {id(b): b for b in (beams if isinstance(beams, (list, tuple)) else [beams])}.values()
    out = np.zeros(freqs.shape)
    for b in distinct:
        out = np.maximum(out, [dish(b, f) for f in freqs])
    return out


def required_lmax(reach) -> int:
    """The smallest lmax that reaches every (channel, baseline) of ``reach`` (:func:`baseline_reach`)."""
    return int(math.ceil(float(np.max(reach))))


def memory_lmax(n_freqs: int, n_rows: int, budget_bytes: float, *, frame_pad: int = 4,
                n_times: int | None = None, channels_at_once: int | None = None) -> int:
    """The largest lmax whose large arrays fit in ``budget_bytes``: the response (Nf, Nrow,
    (lmax + pad + 1)^2 complex128) plus, for ``channels_at_once`` channels (default all ``n_freqs``;
    :func:`choose_lmax` counts one, the set-up of a run that goes one channel at a time where all at
    once do not fit, :func:`gcrsky.run.memoryplan.fit_in_memory`), the cheapest exact path's: one dense (n, n)
    float64 precision, or (with ``n_times``) a data-space set-up (``N_d = 2 Nrow Nt`` real data
    values): the standard one's (N_d, N_d) matrix three times over and the explicit (N_d / 2, n_resp)
    complex128 operator twice, or the in-place one's
    (:func:`gcrsky.solvers.dataspace_large.dataspace_large_bytes`: D once, the lag blocks
    ``2 x 8 Nt (2 Nrow)^2`` and the response's four real copies ``4 x 8 (2 Nrow) n_resp``)."""
    lmax = 1
    while True:
        n, nr = (lmax + 2) ** 2, (lmax + 2 + frame_pad) ** 2
        per_channel = 8.0 * n * n
        if n_times is not None:
            nd = 2 * n_rows * n_times
            standard = 3 * 8.0 * nd * nd + 2 * 16.0 * (nd / 2) * nr
            in_place = 8.0 * nd * nd + 2 * 8.0 * n_times * (2 * n_rows) ** 2 + 4 * 8.0 * 2 * n_rows * nr
            per_channel = min(per_channel, standard, in_place)
        at_once = n_freqs if channels_at_once is None else min(n_freqs, channels_at_once)
        if 16.0 * n_freqs * n_rows * nr + at_once * per_channel > budget_bytes:
            return lmax
        lmax += 1


def choose_lmax(reach, lmax: int | None, *, n_rows: int, budget_bytes: float | None = None,
                frame_pad: int = 4, n_times: int | None = None) -> tuple[int, dict]:
    """The model's lmax: ``lmax`` if given, else the reach of every row (capped by memory).

    Returns:
        ``(lmax, note)`` with note ``{"lmax": ..., "reach": ..., "chosen": "given" |
        "reach" | "memory", "memory_lmax": ...}`` (JSON-friendly).
    """
    need = required_lmax(reach)
    if lmax is not None:
        if lmax < 1:
            raise ValueError(f"lmax must be at least 1, got {lmax}")
        return int(lmax), {"lmax": int(lmax), "reach": need, "chosen": "given"}
    if budget_bytes is None:
        from ..base.memory import available_memory_bytes

        budget_bytes = 0.5 * available_memory_bytes()
    cap = memory_lmax(np.shape(reach)[0], n_rows, budget_bytes, frame_pad=frame_pad, n_times=n_times,
                      channels_at_once=1)
    chosen = min(need, cap)
    if chosen < need:
        log.warning("band limit: the longest baselines reach l = %d, memory allows lmax %d: using %d and cutting "
                    "what it cannot represent", need, cap, chosen)
    else:
        log.info("band limit: lmax %d, the reach of every used baseline at the highest used frequency", chosen)
    return chosen, {"lmax": chosen, "reach": need, "chosen": "reach" if chosen == need else "memory",
                    "memory_lmax": cap}


def problem_baselines(problem) -> np.ndarray:
    """(Nrow, 3) ENU baseline vectors ``x_j - x_i`` of a problem's rows (needs ``antpos_enu_m``)."""
    if problem.antpos_enu_m is None:
        raise ValueError("the problem does not record its antenna positions (antpos_enu_m): give baselines_m")
    pos = np.asarray(problem.antpos_enu_m, np.float64)
    pairs = np.asarray(problem.antpairs)
    return pos[pairs[:, 1]] - pos[pairs[:, 0]]


def _take_rows(problem, rows: np.ndarray):
    """The problem restricted to rows ``rows`` (indices into its antpairs)."""
    idx = jnp.asarray(rows)
    return dataclasses.replace(
        problem, antpairs=np.asarray(problem.antpairs)[rows],
        pols=None if problem.pols is None else tuple(problem.pols[int(r)] for r in rows),
        response=jnp.take(problem.response, idx, axis=1), data=jnp.take(problem.data, idx, axis=2),
        sigma=jnp.take(problem.sigma, idx, axis=2), weights=jnp.take(problem.weights, idx, axis=2),
        sigma_sky=None if problem.sigma_sky is None else jnp.take(problem.sigma_sky, idx, axis=2))


def cut_rows(problem, lmax: int, dish_diameter_m, *, baselines_m=None):
    """Cut what ``lmax`` cannot represent: weight 0 where a row's reach exceeds ``lmax``.

    A (channel, row) whose reach (:func:`baseline_reach`) exceeds ``lmax`` gets weight 0;
    a row cut in every channel is dropped.

    Args:
        problem: a :class:`~gcrsky.model.Problem`.
        lmax: the model's degree.
        dish_diameter_m: D of the reach, scalar or (Nf,) (:func:`beam_dish_m`).
        baselines_m: (Nrow, 2|3) ENU vectors (default: from the problem's antenna positions).

    Returns:
        ``(problem, report)``; report: ``{"rows_cut": rows dropped, "samples_cut": (channel,
        row) pairs given weight 0 in rows kept, "cut_lengths_m": sorted distinct lengths of
        the rows cut anywhere, "max_kept_length_m": ...}``.
    """
    b = problem_baselines(problem) if baselines_m is None else np.asarray(baselines_m, np.float64)
    reach = baseline_reach(b, np.asarray(problem.freqs_hz), dish_diameter_m)
    over = reach > lmax + 1e-9
    lengths = np.linalg.norm(b[:, :2], axis=1)
    keep_rows = np.flatnonzero(~over.all(axis=0))
    report = {"rows_cut": int(over.all(axis=0).sum()), "samples_cut": int(over[:, keep_rows].sum()),
              "cut_lengths_m": sorted({round(float(x), 2) for x in lengths[over.any(axis=0)]}),
              "max_kept_length_m": round(float(lengths[keep_rows].max()), 2) if keep_rows.size else None}
    if keep_rows.size == 0:
        raise ValueError(f"lmax {lmax} reaches no baseline (the shortest needs {required_lmax(reach.min(axis=1))}); "
                         "raise lmax or use --band-limit marginalise")
    if over.any():
        w = jnp.where(jnp.asarray(over)[:, None, :], 0.0, problem.weights)
        problem = _take_rows(dataclasses.replace(problem, weights=w), keep_rows)
        log.info("band limit: cut %d rows and %d (channel, row) samples beyond lmax %d (lengths %s m)",
                 report["rows_cut"], report["samples_cut"], lmax, report["cut_lengths_m"])
    return problem, report


def extend_cl(cl, lmax_hi: int, *, fit_from: int | None = None) -> np.ndarray:
    """C_l (Nf, lmax+1) extended to ``lmax_hi`` by a power law in l fitted over its upper half, (Nf, lmax_hi+1).

    ``fit_from``: the first degree of the fit (default ``max(1, lmax // 2)``).
    """
    cl = np.atleast_2d(np.asarray(cl, np.float64))
    lmax = cl.shape[1] - 1
    if lmax_hi <= lmax:
        return cl[:, : lmax_hi + 1]
    lo = max(1, lmax // 2) if fit_from is None else fit_from
    ell = np.arange(lo, lmax + 1, dtype=np.float64)
    if ell.size < 2 or np.any(cl[:, lo:] <= 0):
        raise ValueError("extending C_l needs positive C_l at two or more degrees >= 1")
    slope, icpt = np.polyfit(np.log(ell), np.log(cl[:, lo:]).T, 1)
    ext = np.exp(icpt[:, None] + slope[:, None] * np.log(np.arange(lmax + 1, lmax_hi + 1))[None, :])
    return np.concatenate([cl, ext], axis=1)


def prior_cl(prior, lmax: int) -> np.ndarray:
    """(Nf, lmax+1) C_l of an isotropic prior (the variance of its m = 0 modes)."""
    iv = np.asarray(prior.inv_var, np.float64)
    tab = mode_table(lmax)
    m0 = np.flatnonzero(tab.m == 0)
    if np.any(iv[:, m0] <= 0):
        raise ValueError("marginalising the sky above lmax needs a proper isotropic prior (C_l > 0): not a flat one")
    return 1.0 / iv[:, m0][:, np.argsort(tab.ell[m0])]


def high_l_variance(response_hi, lmax: int, cl_hi) -> np.ndarray:
    """(Nf, Nrow) per-component variance of the sky with ``lmax < l <= lmax_hi`` through a response.

    Args:
        response_hi: (Nf, Nrow, (lmax_hi+1)^2) complex response at degree ``lmax_hi`` (any
            time, any frame: the value is rotation invariant for an isotropic sky).
        lmax: the model's degree (the variance counts l > lmax).
        cl_hi: (Nf, lmax_hi+1) C_l, K^2.

    Returns:
        ``1/2 sum_{l > lmax} var_k |X_k|^2`` with ``var_k`` the isotropic prior's variances
        (``C_l``, ``C_l / 2`` for the real and imaginary parts of m > 0).
    """
    from .prior import isotropic_prior

    x = np.asarray(response_hi)
    lmax_hi = int(round(math.sqrt(x.shape[-1]))) - 1
    cl_hi = np.atleast_2d(cl_hi)
    var = 1.0 / np.asarray(isotropic_prior(np.broadcast_to(cl_hi, (x.shape[0], lmax_hi + 1)), x.shape[-1]).inv_var)
    hi = mode_table(lmax_hi).ell > lmax
    return 0.5 * np.einsum("fbk,fk->fb", np.abs(x[:, :, hi]) ** 2, var[:, hi])


def marginalise_rows(problem, response_hi, cl_hi=None):
    """The problem with the sky above its lmax marginalised on the diagonal: ``sigma^2 += sigma_hi^2``.

    Args:
        problem: a :class:`~gcrsky.model.Problem` (isotropic proper prior, unless ``cl_hi``).
        response_hi: (Nf, Nrow, (lmax_hi+1)^2) the rows' response at the reach degree.
        cl_hi: (Nf, lmax_hi+1) C_l up to the reach; default: the prior's extended as a power
            law (:func:`extend_cl`).

    Returns:
        ``(problem, sigma_hi)`` with ``sigma_hi`` (Nf, Nrow) the added per-component std (K sr); the
        problem's ``sigma_sky`` records it (sky signal: it passes through the gains).
    """
    lmax_hi = int(round(math.sqrt(np.shape(response_hi)[-1]))) - 1
    if cl_hi is None:
        cl_hi = extend_cl(prior_cl(problem.prior, problem.lmax), lmax_hi)
    var = high_l_variance(response_hi, problem.lmax, cl_hi)
    sigma = jnp.sqrt(problem.sigma**2 + jnp.asarray(var)[:, None, :])
    sky2 = jnp.broadcast_to(jnp.asarray(var)[:, None, :], sigma.shape)
    if problem.sigma_sky is not None:
        sky2 = sky2 + problem.sigma_sky**2
    log.info("band limit: marginalised l = %d..%d on the noise diagonal (added std / noise std: median %.3g)",
             problem.lmax + 1, lmax_hi, float(np.median(np.sqrt(var)[:, None, :] / np.asarray(problem.sigma))))
    return dataclasses.replace(problem, sigma=sigma, sigma_sky=jnp.sqrt(sky2)), np.sqrt(var)


# ---------------------------------------------------------------- a file's problem


def observation_reach(obs, beams, dish_diameter_m: float | None = None, *, isotropic: bool = False
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``(reach (Nf, Nbl), dish_m (Nf,))`` of an Observation's baselines with its beams (:func:`beam_dish_m`);
    ``isotropic``: the rule of lengths, ``2 pi (|b| + D) / lambda`` (the band limit of a fringe times the
    beam, whose uv support is a disc), instead of driftscan's ENU rule (the degree a model needs)."""
    pos = np.asarray(obs.antpos_enu_m, np.float64)
    pairs = np.asarray(obs.antpairs)
    dish = beam_dish_m(beams, obs.freqs_hz, dish_diameter_m)
    b = pos[pairs[:, 1]] - pos[pairs[:, 0]]
    return baseline_reach(np.linalg.norm(b, axis=-1) if isotropic else b, obs.freqs_hz, dish), dish


def quadrature_degree(reach, lmax: int, mode: str, *, frame_pad: int = 0) -> int:
    """The highest degree the response's HEALPix quadrature must resolve: the response's own degree
    (``lmax + frame_pad``) and, unless rows beyond ``lmax`` are cut (``mode="cut"``), the reach of every
    row (its fringe times the beam: the isotropic rule of :func:`baseline_reach`, since the product's uv
    support is a disc of radius ``(|b| + D) / lambda``), which the quadrature integrates."""
    need = int(lmax) + int(frame_pad)
    if mode != "cut" and np.size(reach):
        need = max(need, int(np.ceil(np.max(reach))))
    return need


def check_quadrature(reach, lmax: int, nside: int, mode: str, *, frame_pad: int = 0) -> None:
    """Refuse an ``nside`` whose quadrature cannot resolve what the response integrates.

    A HEALPix grid of ``nside`` resolves degrees up to ``3 nside - 1``; the response of a row
    integrates its fringe times the beam (degrees up to its reach) against ``Y_lm`` up to the
    response's degree (:func:`quadrature_degree`).  Beyond that the fringes alias onto low
    degrees: at lmax 8, nside 16, a 7-dish 14.6 m hexagon at 101 MHz (reach ~91) with its rows kept,
    the Wiener filter was 182 % away from nside 128's, without a word (the longest rows' responses
    there are ~1000x too large: aliasing; at nside 32, 3 nside - 1 = 95 against a reach of 92, every row is
    within 6e-4 of the largest row's norm of nside 256's).  Simulated runs need only
    ``3 nside - 1 >= lmax`` (their data come from the same quadrature); a file's come from the sky.

    Raises:
        ValueError: naming the degree needed, the rows' reach and the smallest nside that resolves it.
    """
    need = quadrature_degree(reach, lmax, mode, frame_pad=frame_pad)
    if 3 * int(nside) - 1 >= need:
        return
    fit = 1 << max(0, math.ceil(math.log2((need + 1) / 3)))
    why = (f"the response's degree lmax + frame pad = {int(lmax) + int(frame_pad)}" if need == int(lmax) + int(frame_pad)
           else f"the kept baselines' fringes and beam reach l = {need} (--band-limit {mode})")
    raise ValueError(f"nside {nside} cannot resolve the response: {why}, and a HEALPix grid resolves l <= 3 nside - 1 "
                     f"= {3 * int(nside) - 1}; use --nside {fit} or more"
                     + ("" if mode == "cut" else ", or --band-limit cut (drops the rows beyond lmax)"))


def observation_rows(obs, compress: bool = False) -> int:
    """Rows per product a problem of ``obs`` has before its band limit: every baseline, or with
    ``compress`` one per redundant group (:func:`gcrsky.instrument.redundant_groups` within
    :data:`gcrsky.model.compress.COMPRESS_TOL_M`; every baseline where the grouping is refused)."""
    if not compress:
        return int(obs.n_baselines)
    from ..instrument.redundancy import redundant_groups
    from .compress import COMPRESS_TOL_M

    try:
        return redundant_groups(obs.antpos_enu_m, obs.antpairs, tol_m=COMPRESS_TOL_M).n_groups
    except ValueError:
        return int(obs.n_baselines)


def observation_lmax(obs, beams, lmax: int | None, *, n_products: int = 1, frame_pad: int = 4,
                     budget_bytes: float | None = None, dish_diameter_m: float | None = None,
                     compress: bool = False) -> tuple[int, dict]:
    """An Observation's lmax (:func:`choose_lmax`: ``lmax`` if given, else the reach of every used
    baseline at the highest used frequency, capped by memory) and its note (reach, D).  ``compress``:
    the memory cap counts one row per redundant group (:func:`observation_rows`), as the problem has."""
    reach, dish = observation_reach(obs, beams, dish_diameter_m)
    n_rows = observation_rows(obs, compress) * n_products
    chosen, note = choose_lmax(reach, lmax, n_rows=n_rows, budget_bytes=budget_bytes, n_times=obs.n_times,
                               frame_pad=frame_pad)
    note["dish_m"] = [round(float(dish.min()), 3), round(float(dish.max()), 3)]
    note["rows_for_memory"] = int(n_rows)
    return chosen, note


def _marginalise(prob, array, dish, nside: int, budget_bytes: float | None):
    """:func:`marginalise_rows` with the rows' response at their reach (of-date frame, ``lst_ref``)."""
    from ..base.memory import check_memory
    from ..instrument.response import response_matrix

    lmax_hi = required_lmax(baseline_reach(problem_baselines(prob), np.asarray(prob.freqs_hz), dish))
    if lmax_hi <= prob.lmax:
        return prob, {"lmax_hi": int(lmax_hi), "added_std_over_noise": {"median": 0.0, "max": 0.0}}
    nf, nrow = prob.response.shape[:2]
    check_memory(16.0 * nf * nrow * (lmax_hi + 1) ** 2, f"the response at the reach lmax {lmax_hi}",
                 "use --band-limit cut, or fewer channels or baselines", budget=budget_bytes)
    nside_hi = max(nside, 1 << max(0, math.ceil(math.log2(max(lmax_hi, 1) / 2))))
    resp = response_matrix(array, np.asarray(prob.antpairs), np.asarray(prob.freqs_hz), lmax_hi, nside_hi,
                           lst_ref_rad=prob.lst_ref_rad, pols=None if prob.pols is None else list(prob.pols))
    out, sig = marginalise_rows(prob, resp)
    ratio = sig[:, None, :] / np.asarray(prob.sigma)
    return out, {"lmax_hi": int(lmax_hi), "nside_hi": int(nside_hi), "cl_above_lmax": "the prior's, power law",
                 "added_std_over_noise": {"median": float(np.median(ratio)), "max": float(ratio.max())}}


def apply_band_limit(prob, array, mode: str, note: dict, *, nside: int, budget_bytes: float | None = None):
    """A file's Problem with its band limit applied (``mode``: :data:`BAND_LIMIT_MODES`), recorded in
    ``config.checks["band_limit"]`` (``note`` from :func:`observation_lmax` plus what was done).

    Args:
        prob: the :class:`~gcrsky.model.Problem` (``config`` a :class:`~gcrsky.model.DataConfig`).
        array: its :class:`~gcrsky.instrument.AntennaArray` (the beams, for the reach and the
            marginalised response).
        mode: ``"cut"``, ``"marginalise"`` or ``"truncate"``.
        note: the lmax choice (:func:`observation_lmax`).
        nside: the problem's quadrature nside (raised for the response at the reach).
        budget_bytes: memory the marginalised response may use (default: the free memory).
    """
    if mode not in BAND_LIMIT_MODES:
        raise ValueError(f"band_limit must be one of {BAND_LIMIT_MODES}, got {mode!r}")
    dish = beam_dish_m(list(array.beams), np.asarray(prob.freqs_hz))
    reach = baseline_reach(problem_baselines(prob), np.asarray(prob.freqs_hz), dish)
    beyond = int(np.sum((reach > prob.lmax + 1e-9).any(axis=0)))
    check = {"mode": mode, **note, "lmax": int(prob.lmax), "rows_beyond_lmax": beyond}
    if mode == "cut":
        prob, report = cut_rows(prob, prob.lmax, dish)
        check.update(report)
    elif mode == "marginalise":
        prob, report = _marginalise(prob, array, dish, nside, budget_bytes)
        check.update(report)
    elif beyond:
        log.warning("band limit: %d rows reach beyond lmax %d and are kept (--band-limit truncate): their fringes "
                    "are unmodelled and bias the low-l coefficients", beyond, prob.lmax)
    cfg = prob.config
    if cfg is not None and hasattr(cfg, "checks"):
        cfg = dataclasses.replace(cfg, checks={**cfg.checks, "band_limit": check})
        prob = dataclasses.replace(prob, config=cfg)
    return prob
