"""Pre-fit data checks on an :class:`~gcrsky.io.Observation`: noise excess, outlier flags, empty data.

Nothing here builds a response or fits a sky: these are checks of the file against the
radiometer equation (:mod:`gcrsky.model.noise`) that can run before anything costly.

* **Noise excess** (:func:`noise_excess`).  For three adjacent integrations ``t-1, t, t+1`` of one
  (product, channel, baseline), ``z = |V_t+1 - 2 V_t + V_t-1|^2 / (2 (s_t-1 + 4 s_t + s_t+1))`` with
  ``s`` the per-component radiometer variance of the autos (:func:`gcrsky.model.radiometer_variance`,
  nsample included) is exponentially distributed with mean 1 for white radiometer noise.  The
  second difference cancels whatever changes linearly over two integrations: the sky's drift
  through the fringes and a slow gain drift, which a first difference ``V_t+1 - V_t`` took for
  noise (on a clean twin of H1C at its signal to noise: excess 1.7-2.2 in every channel, 18-65 on
  the shortest east-west baselines whenever the gains drifted; issue 39).  What is left of the
  drift is second order in the fringe's turn per step.  With only two integrations the first
  difference is used.  The excess is the mean of ``z`` over the usable terms: the
  difference variance over the radiometer variance (DESIGN section 11; RFI channels stand out
  by orders of magnitude).  Adjacent terms share samples: their mean scatters like
  :data:`SECOND_DIFF_EFFICIENCY` times as many independent terms.  Times are judged on first
  differences of adjacent pairs (a burst at ``t`` spoils both of its pairs; the drift is common to
  every time and does not single one out).
* **Outliers** (:func:`outlier_rule`, :func:`find_outliers`, :func:`flag_outliers`).  On the
  logarithm of a statistic per channel (median over products and baselines), per baseline
  (median over products and channels) and per adjacent pair of times (median of ``z``), an
  item is an outlier when ``log s > median + max(k * scale, log(min_factor))`` with
  ``scale = max(1.4826 MAD, the estimator's own scatter)``.  ``k = 5``: a Gaussian-tailed
  statistic exceeds it with probability 3e-7, so a clean file of a few hundred channels has
  no false alarm; the MAD makes the rule robust to the outliers themselves (up to half of
  the items); the estimator's scatter keeps a very clean file (MAD ~ 0) from flagging its
  fluctuations; ``min_factor = 2`` (a noise variance twice the median) keeps the sky's drift
  over one integration and the autos' own scatter (10-60 % on H1C) from flagging channels
  and long baselines.  Channels are judged first; baselines and times on what remains; then
  single (channel, baseline) cells (median over products) among the kept channels and
  baselines (H1C: 198.4 MHz on baseline 1-13, excess 103).  A baseline's excess also holds
  the sky's drift between integrations, ~ (fringe rotation per step)^2 x |V|^2 / noise: it
  grows with the baseline, the step and the sky's brightness, so a baseline whose fringe turns
  more than :data:`MAX_DRIFT_RAD` = 0.2 rad per step (H1C: at most 0.13 rad, 40 m at 198 MHz
  over 10.7 s; a simulation with 30-minute steps: radians) is not judged on its own: with long
  steps the short, bright baselines would stand out as "outliers" of pure sky.  Channels and
  times are judged on every baseline (the drift changes smoothly across them).  The rule is
  relative to the selection: it needs most items clean (and at least three); one or two
  channels cannot reveal an RFI channel.
* **Nothing to constrain** (:func:`refuse_empty`): every cross-correlation flagged, or a zero
  nsample everywhere, is refused with the reason before anything is built.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from scipy.special import polygamma

from ..io.visdata import Observation
from .noise import adjacent_times, radiometer_variance

__all__ = [
    "DEFAULT_K",
    "DEFAULT_MIN_FACTOR",
    "MAX_DRIFT_RAD",
    "NoiseExcess",
    "SECOND_DIFF_EFFICIENCY",
    "Outliers",
    "dead_channels",
    "drift_phase_rad",
    "find_outliers",
    "flag_outliers",
    "flagged_antennas",
    "noise_excess",
    "outlier_rule",
    "refuse_empty",
    "refuse_nonfinite",
]

log = logging.getLogger(__name__)

#: Robust threshold in units of the statistic's scatter (module docstring).
DEFAULT_K = 5.0
#: Smallest excess over the median that is flagged (module docstring).
DEFAULT_MIN_FACTOR = 2.0
#: Largest fringe rotation between adjacent integrations (radians) of a baseline judged on its own
#: (module docstring).
MAX_DRIFT_RAD = 0.2
#: Earth's rotation rate (sidereal), rad/s.
OMEGA_EARTH = 7.2921150e-5


@dataclasses.dataclass(frozen=True)
class NoiseExcess:
    """Time-difference scatter over radiometer noise (:func:`noise_excess`).

    Attributes:
        pol_names: (Npols,) the feed products judged (those with autocorrelations).
        excess: (Npols, Nf, Nbl) mean over the usable terms of ``z`` from second differences of three
            adjacent integrations (first differences where the file has only two), NaN without one.
        z: (Npols, Nf, Nt-1, Nbl) ``z`` of each adjacent pair (first differences: the times' test, where
            the drift is common to every time), NaN where unusable.
        n_pairs: (Npols, Nf, Nbl) usable terms of the excess per (product, channel, baseline).
        order: 2 (the excess from second differences) or 1 (first differences: two integrations).
        per_file: with several files (``Observation.files``), each file's median excess over products,
            channels and baselines from the terms centred on its integrations (None without one).
    """

    pol_names: tuple
    excess: np.ndarray
    z: np.ndarray
    n_pairs: np.ndarray
    order: int = 1
    per_file: tuple = ()

    @property
    def efficiency(self) -> float:
        """Effective independent terms per term (1 for first differences, :data:`SECOND_DIFF_EFFICIENCY`)."""
        return SECOND_DIFF_EFFICIENCY if self.order == 2 else 1.0

    def per_channel(self) -> np.ndarray:
        """(Nf,) median excess over products and baselines (NaN where nothing is usable)."""
        return _nanmedian(np.moveaxis(self.excess, 1, 0).reshape(self.excess.shape[1], -1))

    def per_baseline(self, channels=None) -> np.ndarray:
        """(Nbl,) median excess over products and the given channels (default all)."""
        ex = self.excess if channels is None else self.excess[:, channels]
        return _nanmedian(np.moveaxis(ex, 2, 0).reshape(ex.shape[2], -1))


@dataclasses.dataclass(frozen=True)
class Outliers:
    """What :func:`find_outliers` found (indices into the Observation's axes; :meth:`to_dict` names them).

    Attributes:
        channels, baselines, times: outlying channels, baselines (pair indices) and times.
        channel_excess, baseline_excess: their statistics (median excess).
        thresholds: the thresholds on each statistic, ``k`` and ``min_factor``.
        dead_channels: channels whose data are all exactly 0 or whose autos are all <= 0.
        cells: outlying (channel, baseline) cells among the kept ones; cell_excess their excess.
        not_judged_baselines: baselines not judged one by one (the sky drifts too far per step).
    """

    channels: tuple
    baselines: tuple
    times: tuple
    channel_excess: tuple
    baseline_excess: tuple
    thresholds: dict
    dead_channels: tuple = ()
    cells: tuple = ()
    cell_excess: tuple = ()
    not_judged_baselines: tuple = ()

    @property
    def any(self) -> bool:
        return bool(self.channels or self.baselines or self.times or self.dead_channels or self.cells)

    def to_dict(self, obs: Observation) -> dict:
        """JSON-friendly: channels by index and MHz, baselines by antenna numbers, times by index."""
        return {"channels": list(self.channels), "channels_mhz": [float(obs.freqs_hz[c] / 1e6) for c in self.channels],
                "channel_excess": list(self.channel_excess), "dead_channels": list(self.dead_channels),
                "baselines": [[int(a) for a in obs.baseline_antnums[b]] for b in self.baselines],
                "baseline_excess": list(self.baseline_excess), "times": list(self.times),
                "cells": [[int(c), [int(a) for a in obs.baseline_antnums[b]]] for c, b in self.cells],
                "cell_excess": list(self.cell_excess),
                "not_judged_baselines": len(self.not_judged_baselines),
                "thresholds": dict(self.thresholds)}


def _nanmedian(a: np.ndarray) -> np.ndarray:
    """Median over the last axis ignoring NaN; NaN (no warning) where a row is all NaN."""
    ok = np.isfinite(a)
    out = np.full(a.shape[0], np.nan)
    for i in np.flatnonzero(ok.any(axis=1)):
        out[i] = np.median(a[i][ok[i]])
    return out


def _auto_var(obs: Observation, name: str) -> np.ndarray | None:
    """(Nf, Nt, Nant) ``|Re V_ii|`` of the product ``name`` (NaN where flagged), None if not read."""
    if name not in obs.pol_names:
        return None
    k = obs.pol_index(name)
    return np.where(~obs.auto_flags[k], np.abs(obs.autos[k].real), np.nan)


#: Effective number of independent terms per second-difference term: adjacent second differences share
#: samples (their correlation is -2/3 at lag 1, 1/6 at lag 2; their squares' 4/9 and 1/36), so the mean of
#: ``n`` of them scatters like ``n / (1 + 2 (4/9 + 1/36))`` independent ones.
SECOND_DIFF_EFFICIENCY = 1.0 / (1.0 + 2.0 * (4.0 / 9.0 + 1.0 / 36.0))


def _pair_z(obs: Observation, k: int, au_p: np.ndarray, au_q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``z`` of product ``k`` (module docstring) from first differences (Nf, Nt-1, Nbl) and from second
    differences (Nf, Nt-2, Nbl; the first differences' again with two integrations), NaN where a sample is
    unusable."""
    ai, aj = au_p[:, :, obs.antpairs[:, 0]], au_q[:, :, obs.antpairs[:, 1]]
    ok = obs.usable[k]
    ns = np.where(ok, obs.nsamples[k], 1.0)
    var = radiometer_variance(ai, aj, obs.integration_time_s[None], obs.channel_width_hz[:, None, None], ns)
    var = np.where(ok & np.isfinite(var) & (var > 0), var, np.nan)
    v = np.where(ok, obs.vis[k], 0.0)
    adj = adjacent_times(obs.times_jd, obs.integration_time_s)  # no difference spans a gap between files / nights
    with np.errstate(invalid="ignore"):
        z1 = np.where(adj[None, :, None], np.abs(v[:, 1:] - v[:, :-1]) ** 2 / (2.0 * (var[:, 1:] + var[:, :-1])),
                      np.nan)
        if v.shape[1] < 3:
            return z1, z1
        d2 = v[:, 2:] - 2.0 * v[:, 1:-1] + v[:, :-2]
        z2 = np.abs(d2) ** 2 / (2.0 * (var[:, 2:] + 4.0 * var[:, 1:-1] + var[:, :-2]))
        return z1, np.where((adj[1:] & adj[:-1])[None, :, None], z2, np.nan)


def noise_excess(obs: Observation) -> NoiseExcess:
    """Time-difference scatter over the autos' radiometer noise per (product, channel, baseline).

    Args:
        obs: an Observation with autocorrelations and at least two integrations.

    Returns:
        :class:`NoiseExcess` for every feed product ``pq`` whose autos ``pp`` and ``qq``
        were read (dimensionless; ~1 for clean data, >> 1 under RFI).

    Raises:
        ValueError: fewer than two integrations, or no autocorrelations of the products.
    """
    if obs.n_times < 2:
        raise ValueError("the noise excess needs at least two integrations (time-adjacent differences)")
    names, zs, z2s = [], [], []
    for k, name in enumerate(obs.pol_names):
        au_p, au_q = _auto_var(obs, name[0] * 2), _auto_var(obs, name[1] * 2)
        if au_p is None or au_q is None or not obs.has_autos:
            continue
        names.append(name)
        z1, z2 = _pair_z(obs, k, au_p, au_q)
        zs.append(z1)
        z2s.append(z2)
    if not zs:
        raise ValueError("the noise excess needs the autocorrelations of the feed products (none were read)")
    z, z2 = np.stack(zs), np.stack(z2s)
    n = np.sum(np.isfinite(z2), axis=2)
    with np.errstate(invalid="ignore"):
        excess = np.where(n > 0, np.nansum(z2, axis=2) / np.maximum(n, 1), np.nan)
    return NoiseExcess(pol_names=tuple(names), excess=excess, z=z, n_pairs=n, order=2 if obs.n_times >= 3 else 1,
                       per_file=_per_file_excess(obs, z2))


def _per_file_excess(obs: Observation, z2: np.ndarray) -> tuple:
    """Each file's median excess (:attr:`NoiseExcess.per_file`) from the terms ``z2`` (Npols, Nf, Nterms, Nbl)
    centred on its integrations; ``()`` for one file."""
    if not obs.files:
        return ()
    tf = np.asarray(obs.time_file)
    centre = tf[1:-1] if z2.shape[2] == obs.n_times - 2 else tf[:-1]  # second differences, or first
    out = []
    for k in range(len(obs.files)):
        sel = z2[:, :, centre == k]
        cnt = np.sum(np.isfinite(sel), axis=2)
        with np.errstate(invalid="ignore"):
            ex = np.where(cnt > 0, np.nansum(sel, axis=2) / np.maximum(cnt, 1), np.nan)
        out.append(float(np.nanmedian(ex)) if np.any(np.isfinite(ex)) else None)
    return tuple(out)


def outlier_rule(stat: np.ndarray, n_terms: np.ndarray, *, k: float = DEFAULT_K,
                 min_factor: float = DEFAULT_MIN_FACTOR) -> tuple[np.ndarray, float]:
    """Which items of a positive statistic are high outliers (module docstring), and the threshold.

    Args:
        stat: (M,) a statistic whose clean value is ~1 (NaN: not judged).
        n_terms: (M,) how many unit-mean exponential terms each item summarises (its own
            scatter in log is about ``sqrt(trigamma(n))``; a median of ``m`` such items
            shrinks it by ``sqrt(pi / (2 m))``: pass the effective number).
        k: threshold in units of the scale.  min_factor: smallest flagged ratio to the median.

    Returns:
        ((M,) bool outliers, the threshold on ``stat`` itself).
    """
    s = np.asarray(stat, np.float64)
    ok = np.isfinite(s) & (s > 0)
    if not np.any(ok):
        return np.zeros(s.shape, bool), float("nan")
    ls = np.log(s[ok])
    med = float(np.median(ls))
    mad = 1.4826 * float(np.median(np.abs(ls - med)))
    own = float(np.median(np.sqrt(polygamma(1, np.maximum(np.asarray(n_terms, np.float64)[ok], 1.0)))))
    cut = med + max(k * max(mad, own), float(np.log(min_factor)))
    out = np.zeros(s.shape, bool)
    out[ok] = ls > cut
    return out, float(np.exp(cut))


def _effective_terms(n_pairs: np.ndarray, axes) -> np.ndarray:
    """Effective number of exponential terms behind a median over ``axes`` of pair means."""
    m = np.sum(n_pairs > 0, axis=axes)
    per = np.sum(n_pairs, axis=axes) / np.maximum(m, 1)
    return per * np.maximum(m, 1) * 2.0 / np.pi


def drift_phase_rad(obs: Observation) -> np.ndarray:
    """(Nbl,) how far a baseline's fringe turns between adjacent integrations, radians (upper bound).

    ``2 pi omega_E dt |b_horizontal| nu_max / c`` with ``dt`` the median step between the
    integrations: the sky's own change over one step is ~ this phase times the visibility, and
    it enters the time differences beside the noise.
    """
    from ..base.units import SPEED_OF_LIGHT

    if obs.n_times < 2:
        return np.zeros(obs.n_baselines)
    dt = float(np.median(np.diff(obs.times_jd))) * 86400.0
    b = np.linalg.norm(obs.baselines_enu_m[:, :2], axis=1)
    return 2 * np.pi * OMEGA_EARTH * dt * b * float(obs.freqs_hz.max()) / SPEED_OF_LIGHT


def find_outliers(obs: Observation, ex: NoiseExcess | None = None, *, k: float = DEFAULT_K,
                  min_factor: float = DEFAULT_MIN_FACTOR, max_drift_rad: float = MAX_DRIFT_RAD) -> Outliers:
    """Channels, then baselines, then times, then cells whose noise excess is a robust outlier (module docstring).

    Baselines (and their cells) whose fringe turns more than ``max_drift_rad`` between
    adjacent integrations (:func:`drift_phase_rad`) are not judged one by one: their excess
    holds the sky's drift, which grows with the baseline and the sky's brightness.
    """
    ex = noise_excess(obs) if ex is None else ex
    ch_stat = ex.per_channel()
    eff = ex.efficiency
    ch_bad, ch_cut = outlier_rule(ch_stat, eff * _effective_terms(ex.n_pairs, (0, 2)), k=k, min_factor=min_factor)
    dead = dead_channels(obs)
    keep = np.flatnonzero(~ch_bad & ~np.isin(np.arange(obs.n_freqs), dead))
    judged = drift_phase_rad(obs) <= max_drift_rad
    bl_stat = np.where(judged, ex.per_baseline(keep), np.nan)
    bl_bad, bl_cut = outlier_rule(bl_stat, eff * _effective_terms(ex.n_pairs[:, keep], (0, 1)), k=k,
                                  min_factor=min_factor)
    z = ex.z[:, keep][..., ~bl_bad]
    t_stat = _nanmedian(np.moveaxis(z, 2, 0).reshape(z.shape[2], -1))
    t_terms = np.sum(np.isfinite(np.moveaxis(z, 2, 0).reshape(z.shape[2], -1)), axis=1) * 2.0 / np.pi
    pair_bad, t_cut = outlier_rule(t_stat, t_terms, k=k, min_factor=min_factor)
    times = _times_of_pairs(pair_bad, obs.n_times)
    cells, cell_stat, c_cut = _cell_outliers(ex, keep, np.flatnonzero(~bl_bad & judged), k=k, min_factor=min_factor)
    return Outliers(
        channels=tuple(int(i) for i in np.flatnonzero(ch_bad)),
        baselines=tuple(int(i) for i in np.flatnonzero(bl_bad)),
        times=tuple(int(i) for i in times),
        channel_excess=tuple(float(x) for x in ch_stat[ch_bad]),
        baseline_excess=tuple(float(x) for x in bl_stat[bl_bad]),
        thresholds={"channel": ch_cut, "baseline": bl_cut, "time_pair": t_cut, "cell": c_cut, "k": float(k),
                    "min_factor": float(min_factor), "max_drift_rad": float(max_drift_rad)},
        dead_channels=tuple(dead),
        cells=tuple(cells),
        cell_excess=tuple(cell_stat),
        not_judged_baselines=tuple(int(i) for i in np.flatnonzero(~judged)),
    )


def _cell_outliers(ex: NoiseExcess, chans, bls, *, k, min_factor):
    """Single (channel, baseline) cells among the kept channels and baselines (median over products)."""
    if len(chans) == 0 or len(bls) == 0:
        return [], [], float("nan")
    sub = ex.excess[:, chans][:, :, bls]
    cell = _nanmedian(np.moveaxis(sub, 0, -1).reshape(-1, sub.shape[0]))
    terms = ex.efficiency * np.sum(ex.n_pairs[:, chans][:, :, bls], axis=0).reshape(-1) / sub.shape[0]
    bad, cut = outlier_rule(cell, terms, k=k, min_factor=min_factor)
    idx = np.flatnonzero(bad)
    return ([(int(chans[i // len(bls)]), int(bls[i % len(bls)])) for i in idx], [float(cell[i]) for i in idx], cut)


def dead_channels(obs: Observation) -> list[int]:
    """Channels with usable cross-correlations that are all exactly 0, or whose autos are all <= 0.

    (A correlator's zeroed band edges: the H1C file's first three channels hold exact zeros,
    unflagged.)  Such data carry no measurement: they are flagged with the outliers.
    """
    out = []
    for f in range(obs.n_freqs):
        ok = obs.usable[:, f]
        if not np.any(ok):
            continue
        autos = np.abs(obs.autos[:, f].real)[~obs.auto_flags[:, f]]
        if np.all(obs.vis[:, f][ok] == 0) or (autos.size and np.all(autos <= 0)):
            out.append(f)
    return out


def _times_of_pairs(pair_bad: np.ndarray, nt: int, span: int = 2) -> np.ndarray:
    """Times all of whose terms are outliers (term ``p`` spans times ``p .. p + span - 1``: a burst at ``t``
    spoils every term that holds it)."""
    bad = np.zeros(nt, bool)
    nterms = nt - span + 1
    for t in range(nt):
        adj = [p for p in range(t - span + 1, t + 1) if 0 <= p < nterms]
        bad[t] = bool(adj) and all(pair_bad[p] for p in adj)
    return np.flatnonzero(bad)


def flag_outliers(obs: Observation, *, k: float = DEFAULT_K,
                  min_factor: float = DEFAULT_MIN_FACTOR) -> tuple[Observation, Outliers]:
    """A new Observation with the outliers of :func:`find_outliers` flagged (``obs`` is not changed).

    Flagged channels and times are flagged for every product, baseline and autocorrelation;
    flagged baselines for every product, channel and time.

    Returns:
        (the flagged Observation, the :class:`Outliers` found).
    """
    out = find_outliers(obs, k=k, min_factor=min_factor)
    if not out.any:
        return obs, out
    extra = np.zeros(obs.flags.shape[1:], bool)  # (Nf, Nt, Nbl)
    aux = np.zeros(obs.auto_flags.shape[1:], bool)  # (Nf, Nt, Nant)
    for idx, axis in ((out.channels + out.dead_channels, 0), (out.times, 1)):
        sl = [slice(None)] * 3
        sl[axis] = list(idx)
        extra[tuple(sl)] = True
        aux[tuple(sl)] = True
    extra[:, :, list(out.baselines)] = True
    for c, b in out.cells:
        extra[c, :, b] = True
    log.warning("flagged as noise-excess outliers: channels %s (dead: %s), (channel, baseline) cells %s, "
                "baselines %s, times %s", list(out.channels), list(out.dead_channels),
                [(c, tuple(int(a) for a in obs.baseline_antnums[b])) for c, b in out.cells],
                [tuple(int(a) for a in obs.baseline_antnums[b]) for b in out.baselines], list(out.times))
    new = dataclasses.replace(obs, flags=obs.flags | extra[None], auto_flags=obs.auto_flags | aux[None])
    return new, out


def flagged_antennas(obs: Observation) -> list[int]:
    """Antenna numbers whose every cross-correlation sample (all products) is unusable."""
    usable = np.any(obs.usable, axis=(0, 1, 2))  # (Nbl,)
    seen = np.zeros(obs.n_antennas, bool)
    seen[obs.antpairs[usable].reshape(-1)] = True
    return [int(a) for a in obs.antenna_numbers[~seen]]


def refuse_nonfinite(obs: Observation) -> None:
    """Refuse unflagged visibilities that are NaN or Inf, cross- or autocorrelations, counted and located as the
    file holds them (before any combination of feed products, which turns an Inf into a NaN).

    ``run`` refuses them before anything is built (:func:`gcrsky.model.observed.check_observation`) and
    ``inspect`` reports them as a PROBLEM: one check.  An unflagged Inf autocorrelation would make that
    antenna's radiometer noise infinite, i.e. silently drop its baselines.

    Raises:
        ValueError: naming the count (NaN and Inf), the first sample's product, channel, time and baseline
            (or antenna), and the remedy (flag them in the file).
    """
    for what, vals, used, pair in (("visibilities", obs.vis, obs.usable, lambda i: obs.baseline_antnums[i]),
                                   ("autocorrelations", obs.autos, ~obs.auto_flags & (obs.auto_nsamples > 0),
                                    lambda i: (obs.antenna_numbers[i],) * 2)):
        bad = used & ~np.isfinite(vals)
        if not np.any(bad):
            continue
        k, f, t, b = (int(x[0]) for x in np.nonzero(bad))
        nan = int(np.sum(bad & np.isnan(vals)))
        a1, a2 = (int(a) for a in pair(b))
        raise ValueError(f"{int(bad.sum())} unflagged {what} are not finite ({nan} NaN, {int(bad.sum()) - nan} "
                         f"Inf), first {obs.pol_names[k]} at channel {f} ({obs.freqs_hz[f] / 1e6:.4f} MHz), time {t}, "
                         f"baseline {a1}-{a2} (value {complex(vals[k, f, t, b])!r}): a run refuses them; flag them in "
                         "the file (or select other channels, times or antennas)")


def refuse_empty(obs: Observation) -> None:
    """Refuse, with the reason, an Observation without a single usable cross-correlation sample.

    Raises:
        ValueError: every sample flagged; every unflagged sample with a zero (or negative)
            nsample; or nothing usable for some other mix of the two.
    """
    if np.any(obs.usable):
        return
    n = obs.flags.size
    unflagged = ~obs.flags
    if not np.any(unflagged):
        raise ValueError(f"every cross-correlation sample of the selection is flagged ({n} samples): nothing "
                         "constrains the sky; select other channels, times or antennas, or unflag the data")
    if np.all(obs.nsamples[unflagged] <= 0):
        raise ValueError(f"the nsample of every unflagged sample is zero ({int(unflagged.sum())} of {n} samples): "
                         "the file says no data were integrated, so nothing constrains the sky (fix the file's "
                         "nsample_array if the data are real)")
    raise ValueError("no cross-correlation sample is both unflagged and with a positive nsample")
