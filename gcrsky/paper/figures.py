"""Figures in the style of Glasscock et al. (2024): Figs. 3, 4, 5, 6/8 and 7.

Each function takes plain arrays and an output path, writes a PNG and returns the
path.  matplotlib is imported lazily; if pyplot is not imported yet, the
non-interactive Agg backend is selected (a caller's existing pyplot setup is left
alone).  Nothing is shown on screen; figures are closed after saving.  Angles are in degrees; maps are HEALPix RING, equatorial
(see :mod:`gcrsky.paper.metrics`).
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

__all__ = [
    "plot_alm_residuals",
    "plot_sky_maps",
    "plot_posterior_maps",
    "plot_beam_region",
    "plot_frac_slices",
    "plot_correlation_matrix",
    "plot_corner",
]


def _plt():
    """pyplot, selecting the Agg backend unless the caller already set pyplot up."""
    import sys

    from ..base.extras import require

    matplotlib = require("matplotlib", "plots", "the paper's figures")
    if "matplotlib.pyplot" not in sys.modules:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finish(fig, path) -> str:
    path = os.fspath(path)
    d = os.path.dirname(path)
    if d:
        os.makedirs(d, exist_ok=True)
    fig.savefig(path, dpi=130, bbox_inches="tight")
    _plt().close(fig)
    return path


# ---------------------------------------------------------------- Fig. 3


def plot_alm_residuals(z, ell, m, is_imag, path, *, clip: float = 15.0, title: str | None = None) -> str:
    """Per-mode ``(mean - truth) / std`` of the draws, real and imaginary parts (paper Fig. 3).

    Modes are ordered by ``(l, m)``; the x axis is labelled by ``l`` (ticks at the
    first mode of each degree).  Values beyond ``+-clip`` sigma are drawn at the
    clip level as red triangles pointing outwards.  Grey bands mark +-1 and +-3 sigma.

    Args:
        z: ``(n,)`` z-scores of the realified modes (:func:`gcrsky.paper.metrics.mode_z_scores`).
        ell, m, is_imag: ``(n,)`` mode table (:func:`gcrsky.sphere.mode_table`).
        path: output PNG path.
        clip: clip level in sigma.
        title: optional figure title.
    """
    plt = _plt()
    z = np.asarray(z, np.float64)
    ell, m, is_imag = (np.asarray(a) for a in (ell, m, is_imag))
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.2), sharex=True, constrained_layout=True)
    lmax = int(ell.max())
    # common x coordinate: position of (l, m) in the (l, m)-sorted list of m >= 0 modes
    order_l = np.concatenate([[l] * (l + 1) for l in range(lmax + 1)])
    order_m = np.concatenate([np.arange(l + 1) for l in range(lmax + 1)])
    xpos = {(int(a), int(b)): i for i, (a, b) in enumerate(zip(order_l, order_m))}
    x = np.array([xpos[(int(a), int(b))] for a, b in zip(ell, m)])
    starts = [xpos[(l, 0)] for l in range(lmax + 1)]
    fin_all = np.isfinite(z)
    zmax = float(np.max(np.abs(z[fin_all]))) if fin_all.any() else clip
    ylim = 1.12 * max(4.0, min(clip, 1.1 * zmax))  # zoom in when nothing is clipped
    for ax, imag, label in ((axes[0], False, r"Re $a_{\ell m}$"), (axes[1], True, r"Im $a_{\ell m}$ ($m \geq 1$)")):
        sel = is_imag == imag
        xs, zs = x[sel], z[sel]
        ax.axhspan(-3, 3, color="0.92", zorder=0)
        ax.axhspan(-1, 1, color="0.82", zorder=0)
        ax.axhline(0, color="0.4", lw=0.8, zorder=1)
        for s in starts:
            ax.axvline(s - 0.5, color="0.85", lw=0.5, zorder=0)
        inside = np.isfinite(zs) & (np.abs(zs) <= clip)
        ax.plot(xs[inside], zs[inside], "o", ms=3.2, color="C0", zorder=3)
        hi = np.isfinite(zs) & (zs > clip)
        lo = np.isfinite(zs) & (zs < -clip)
        ax.plot(xs[hi], np.full(hi.sum(), clip), "^", ms=6, color="C3", zorder=4)
        ax.plot(xs[lo], np.full(lo.sum(), -clip), "v", ms=6, color="C3", zorder=4)
        n_out = int(hi.sum() + lo.sum())
        ax.set_ylim(-ylim, ylim)
        ax.set_ylabel(r"(mean $-$ truth) / std")
        fin = np.isfinite(zs)
        rms = float(np.sqrt(np.mean(zs[fin] ** 2))) if fin.any() else float("nan")
        ax.set_title(
            f"{label}:  rms {rms:.2f},  |z|>3: {int((np.abs(zs[fin]) > 3).sum())}/{int(fin.sum())}"
            + (f",  beyond $\\pm${clip:g}$\\sigma$ (red triangles): {n_out}" if n_out else ""),
            loc="left", fontsize=9,
        )
    ticks, last = [], -np.inf
    for l in range(lmax + 1):  # label an l only where it is not crowded (low l have few modes)
        if xpos[(l, 0)] - last >= len(order_l) / 45.0 or l == lmax:
            if l == lmax and ticks and xpos[(l, 0)] - last < len(order_l) / 45.0:
                ticks.pop()
            ticks.append(l)
            last = xpos[(l, 0)]
    axes[1].set_xticks([xpos[(l, 0)] for l in ticks])
    axes[1].set_xticklabels([str(l) for l in ticks])
    axes[1].set_xlabel(r"mode, ordered by ($\ell$, $m$); ticks at $m = 0$ of each $\ell$")
    axes[1].set_xlim(-1, len(order_l))
    if title:
        fig.suptitle(title)
    return _finish(fig, path)


# ---------------------------------------------------------------- Fig. 4


def _band_outline(centre_dec_deg, fwhm_deg, ra_range_deg, npts=100):
    """The four sides of the +-FWHM band over the RA range: list of (theta, phi) radian arrays."""
    start, stop = float(ra_range_deg[0]), float(ra_range_deg[1])
    if stop < start:
        stop += 360.0
    ra = np.linspace(start, min(stop, start + 360.0), npts)
    d_hi = min(centre_dec_deg + fwhm_deg, 90.0)
    d_lo = max(centre_dec_deg - fwhm_deg, -90.0)
    dec = np.linspace(d_lo, d_hi, max(npts // 4, 2))
    sides = [(ra, np.full(npts, d_hi)), (ra, np.full(npts, d_lo))]
    if stop - start < 360.0:
        sides += [(np.full(dec.size, ra[0]), dec), (np.full(dec.size, ra[-1]), dec)]
    return [(np.deg2rad(90.0 - d), np.deg2rad(r % 360.0)) for r, d in sides]


def plot_sky_maps(
    truth_map,
    mean_map,
    std_map,
    path,
    *,
    frac_clip: float = 0.10,
    region: tuple | None = None,
    title: str | None = None,
    unit: str = "K",
) -> str:
    """2x2 Mollview panels: truth, posterior mean, fractional difference, posterior std (paper Fig. 4).

    Truth and mean share a logarithmic colour scale; the fractional difference
    ``(mean - truth)/truth`` is clipped to ``+-frac_clip``.  Equatorial coordinates
    (RA increasing to the left, healpy's astro convention) with a 30 deg graticule.

    Args:
        truth_map, mean_map, std_map: RING maps ``(12 nside^2,)`` in ``unit``.
        path: output PNG path.
        frac_clip: colour limit of the fractional-difference panel.
        region: optional ``(centre_dec_deg, fwhm_deg, ra_range_deg)``; its +-FWHM band
            is outlined on every panel.
        title: optional figure title.
    """
    import warnings

    import healpy as hp

    from .metrics import frac_diff_map

    plt = _plt()
    truth_map, mean_map, std_map = (np.asarray(a, np.float64) for a in (truth_map, mean_map, std_map))
    frac = frac_diff_map(mean_map, truth_map)
    pos = np.concatenate([truth_map[truth_map > 0], mean_map[mean_map > 0]])
    log_ok = pos.size > 0 and (truth_map > 0).all()
    vmin, vmax = (np.percentile(pos, 0.5), np.percentile(pos, 99.5)) if pos.size else (None, None)
    fig = plt.figure(figsize=(13, 8.6))
    with warnings.catch_warnings():  # healpy calls matplotlib APIs that warn of their deprecation
        warnings.filterwarnings("ignore", message=r"The set_(over|under|bad) function will be deprecated")
        common = dict(fig=fig.number, cbar=True, hold=False, notext=False)
        sky_kw = dict(norm="log" if log_ok else None, min=vmin, max=vmax, unit=unit, cmap="inferno", format="%.4g")
        hp.mollview(truth_map, sub=(2, 2, 1), title="truth", **sky_kw, **common)
        hp.mollview(mean_map, sub=(2, 2, 2), title="posterior mean", **sky_kw, **common)
        hp.mollview(
            np.clip(frac, -frac_clip, frac_clip), sub=(2, 2, 3), min=-frac_clip, max=frac_clip, cmap="RdBu_r",
            title=f"(mean $-$ truth) / truth, clipped to $\\pm${frac_clip:.0%}", unit="fraction", format="%.2f", **common,
        )
        smax = np.percentile(std_map, 99.5) if std_map.size else None
        hp.mollview(std_map, sub=(2, 2, 4), title="posterior std", unit=unit, cmap="viridis", min=0.0, max=smax,
                    format="%.4g", **common)
    for ax in fig.axes:
        if isinstance(ax, hp.projaxes.SphericalProjAxes):
            ax.graticule(dpar=30, dmer=30, color="0.6", alpha=0.6)
            if region is not None:
                for th, ph in _band_outline(*region):
                    ax.projplot(th, ph, "-", color="lime", lw=1.0)
    if title:
        fig.suptitle(title, y=1.0)
    return _finish(fig, path)


def plot_posterior_maps(mean_map, std_map, path, *, region: tuple | None = None, title: str | None = None,
                        unit: str = "K") -> str:
    """Two Mollview panels, posterior mean and posterior std, for a run without a truth (real data).

    Args:
        mean_map, std_map: RING maps ``(12 nside^2,)`` in ``unit``.
        path: output PNG path.
        region: optional ``(centre_dec_deg, fwhm_deg, ra_range_deg)``, outlined on both panels.
        title: optional figure title.
    """
    import warnings

    import healpy as hp

    plt = _plt()
    mean_map, std_map = (np.asarray(a, np.float64) for a in (mean_map, std_map))
    fig = plt.figure(figsize=(13, 4.6))
    pos = mean_map[mean_map > 0]
    log_ok = pos.size == mean_map.size
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"The set_(over|under|bad) function will be deprecated")
        common = dict(fig=fig.number, cbar=True, hold=False, notext=False)
        lo, hi = np.percentile(mean_map, [0.5, 99.5])
        hp.mollview(mean_map, sub=(1, 2, 1), title="posterior mean", unit=unit, cmap="inferno", format="%.4g",
                    norm="log" if log_ok else None, min=lo, max=hi, **common)
        hp.mollview(std_map, sub=(1, 2, 2), title="posterior std", unit=unit, cmap="viridis", min=0.0,
                    max=np.percentile(std_map, 99.5), format="%.4g", **common)
    for ax in fig.axes:
        if isinstance(ax, hp.projaxes.SphericalProjAxes):
            ax.graticule(dpar=30, dmer=30, color="0.6", alpha=0.6)
            if region is not None:
                for th, ph in _band_outline(*region):
                    ax.projplot(th, ph, "-", color="lime", lw=1.0)
    if title:
        fig.suptitle(title, y=1.02)
    return _finish(fig, path)


# ---------------------------------------------------------------- Fig. 5


def plot_beam_region(
    frac_map,
    path,
    *,
    centre_dec_deg: float,
    fwhm_deg: float,
    ra_range_deg: Sequence[float],
    margin_deg: float = 20.0,
    frac_clip: float = 0.10,
    title: str | None = None,
    resolution_deg: float | None = None,
) -> str:
    """Cartesian RA/Dec close-up of the fractional difference around the beam region (paper Fig. 5).

    The map is interpolated (``healpy.get_interp_val``) onto a regular grid covering
    the observed RA range +- ``margin_deg`` and ``centre_dec +- (FWHM + margin_deg)``,
    clipped to ``+-frac_clip``.  Solid line: the beam-centre declination; dashed: +-1
    FWHM; dotted verticals: the observed RA range; black contours at |frac| = 5% and
    10%.  RA increases to the left (as on the sky and in the Mollweide panels).

    Args:
        frac_map: RING map ``(12 nside^2,)`` of ``(mean - truth)/truth``.
        path: output PNG path.
        centre_dec_deg, fwhm_deg, ra_range_deg: beam-region geometry (degrees).
        margin_deg: extra sky shown around the region.
        frac_clip: colour limit.
        title: optional title.
        resolution_deg: grid step (default: a quarter of the HEALPix pixel size, at
            least 0.1 deg).
    """
    import healpy as hp

    plt = _plt()
    frac_map = np.asarray(frac_map, np.float64)
    nside = hp.npix2nside(frac_map.size)
    if resolution_deg is None:
        resolution_deg = max(0.1, hp.nside2resol(nside, arcmin=True) / 60.0 / 4.0)
    start, stop = float(ra_range_deg[0]), float(ra_range_deg[1])
    if stop < start:
        stop += 360.0
    width = min(stop - start, 360.0)
    ra_lo, ra_hi = start - margin_deg, start + width + margin_deg
    if ra_hi - ra_lo > 360.0:
        ra_lo, ra_hi = start + width / 2 - 180.0, start + width / 2 + 180.0
    dec_lo = max(centre_dec_deg - fwhm_deg - margin_deg, -90.0)
    dec_hi = min(centre_dec_deg + fwhm_deg + margin_deg, 90.0)
    ra = np.arange(ra_lo, ra_hi + 1e-9, resolution_deg)
    dec = np.arange(dec_lo, dec_hi + 1e-9, resolution_deg)
    RA, DEC = np.meshgrid(ra, dec)
    vals = hp.get_interp_val(frac_map, np.deg2rad(90.0 - DEC), np.deg2rad(RA % 360.0))
    fig, ax = plt.subplots(figsize=(10, 5.0), constrained_layout=True)
    im = ax.pcolormesh(ra, dec, np.clip(vals, -frac_clip, frac_clip), cmap="RdBu_r", vmin=-frac_clip,
                       vmax=frac_clip, shading="nearest", rasterized=True)
    cs = ax.contour(ra, dec, np.abs(vals), levels=[0.05, 0.10], colors="k", linewidths=[0.6, 1.0])
    ax.clabel(cs, fmt={0.05: "5%", 0.10: "10%"}, fontsize=7)
    ax.axhline(centre_dec_deg, color="k", lw=1.4, label=f"beam centre, dec {centre_dec_deg:.2f}$^\\circ$")
    for s in (-1, 1):
        ax.axhline(centre_dec_deg + s * fwhm_deg, color="k", ls="--", lw=1.1,
                   label=f"$\\pm$1 FWHM ({fwhm_deg:.1f}$^\\circ$)" if s > 0 else None)
    if width < 360.0:
        for r in (start, start + width):
            ax.axvline(r, color="0.25", ls=":", lw=1.1)
    ax.set_xlim(ra_hi, ra_lo)  # RA increasing to the left
    ax.set_ylim(dec_lo, dec_hi)
    ticks = ax.get_xticks()
    ax.set_xticks(ticks)
    ax.set_xticklabels([f"{t % 360:g}" for t in ticks])
    ax.set_xlim(ra_hi, ra_lo)
    ax.set_xlabel("RA [deg]  (dotted: observed LST range)")
    ax.set_ylabel("Dec [deg]")
    ax.set_aspect("equal")
    cb = fig.colorbar(im, ax=ax, shrink=0.8, extend="both", pad=0.02)
    cb.set_label(f"(mean $-$ truth) / truth, clipped $\\pm${frac_clip:.0%}")
    ax.legend(loc="lower left", fontsize=8, framealpha=0.85)
    if title:
        ax.set_title(title, fontsize=10)
    return _finish(fig, path)


# ---------------------------------------------------------------- Figs. 6 and 8


def _ra_range(ra_range_deg):
    """``(start, width)`` in degrees of an eastward RA range (``width`` in (0, 360])."""
    start, stop = (float(x) for x in ra_range_deg)
    width = stop - start
    if width >= 360.0:
        return start, 360.0
    width %= 360.0
    return start, (360.0 if width == 0.0 else width)


def _default_window(ra_deg, smooth_deg: float = 3.0) -> int:
    """Odd number of ring pixels closest to ``smooth_deg`` (at least 1)."""
    n = max(len(ra_deg), 1)
    k = smooth_deg / (360.0 / n)
    return max(1, 2 * int(round((k - 1.0) / 2.0)) + 1)


def plot_frac_slices(
    curves,
    path,
    *,
    fwhm_deg: float,
    ra_range_deg: Sequence[float],
    window: int | None = None,
    passes: int = 2,
    title: str | None = None,
    ra_limits: Sequence[float] | None = None,
    yscale: str = "auto",
    dec_deg: float | None = None,
) -> str:
    """|Fractional difference| of posterior means along the beam-centre ring vs RA (paper Figs. 6, 8).

    Each curve is the raw ring slice (:func:`gcrsky.paper.metrics.ring_slice` of
    ``|mean - truth| / |truth|``); it is smoothed here by ``passes`` circular moving
    averages of ``window`` ring pixels (:func:`gcrsky.paper.metrics.moving_average`, the
    paper's "pair of moving average filters") and drawn in percent.

    x axis (bottom): RA in degrees of the *reference* observed range
    ``ra_range_deg``, unwrapped so that the range is contiguous (RA 240-360, i.e.
    LST 16-24 h, is drawn from 240 to 360 and continues to 380 beyond; tick labels
    are taken modulo 360).  Shading, relative to the reference range: light over the
    FWHM-wide margins just outside it (``[start - FWHM, start]`` and
    ``[stop, stop + FWHM]``), dark beyond them (outside the primary beam); dotted
    verticals at the range's ends.  Dashed grey lines at 5% and 10%.

    Runs observed over other RA ranges (the paper's C2, C3, C5): pass the curve as
    ``(label, ra_deg, absfrac, run_ra_range_deg)``.  It is aligned with the
    reference by the *start* of its range (x = reference start + RA offset from
    the run's own start, i.e. equal LST offsets line up), and an extra x axis below
    the main one gives that run's own RA (as the paper's "additional x-axes").  A
    run whose range is wider than the reference (C5, 0-16 h vs 0-8 h) keeps the
    reference's shading; its own range end is marked by a dotted line in its colour
    where it falls inside the plotted window.

    Args:
        curves: sequence of ``(label, ra_deg, absfrac)`` or
            ``(label, ra_deg, absfrac, run_ra_range_deg)``; ``ra_deg`` and
            ``absfrac`` ``(npix_ring,)`` (RA in degrees, any order covering the full
            ring; ``absfrac`` dimensionless, e.g. 0.05 = 5%).
        path: output PNG path.
        fwhm_deg: beam FWHM (degrees), width of the light shading.
        ra_range_deg: reference observed ``(start, stop)`` RA in degrees (eastwards,
            wrapping as in :func:`gcrsky.paper.metrics.ra_in_range`); ``RA = 15 LST``.
        window: odd box-car width in ring pixels; default per curve: the odd pixel
            count closest to 3 deg (5 pixels at nside 128; 1, i.e. none, at nside 32).
        passes: number of box cars (2 = the paper's pair).
        title: optional title.
        ra_limits: ``(lo, hi)`` of the x axis in the unwrapped RA coordinate
            (e.g. ``(-30, 150)``); default: the reference range +- 2 FWHM (at most
            360 deg in all).
        yscale: ``"linear"``, ``"log"`` or ``"auto"`` (log when a smoothed curve
            exceeds 50% inside the window, e.g. the high-noise B cases; else linear
            from 0 to the largest value, at least 12%).
        dec_deg: declination of the slice, only for the axis label.
    """
    from matplotlib.ticker import FuncFormatter

    plt = _plt()
    start, width = _ra_range(ra_range_deg)
    full = width >= 360.0
    lo, hi = _slice_window(start, width, fwhm_deg, ra_limits)
    fig, ax = plt.subplots(figsize=(10, 4.6), constrained_layout=True)
    fmt = FuncFormatter(lambda v, _pos: f"{v % 360:g}")
    vis_max, extra_axes = _plot_slice_curves(ax, curves, start, width, lo, hi, window, passes)
    if not full:
        _shade_reference(ax, start, width, float(fwhm_deg), lo, hi)
    _slice_yscale(ax, yscale, vis_max)
    for ref in (5.0, 10.0):
        ax.axhline(ref, color="0.35", ls="--", lw=0.9, zorder=1)
    ax.set_xlim(lo, hi)
    ax.xaxis.set_major_formatter(fmt)
    where = f" at dec {dec_deg:.2f}$^\\circ$" if dec_deg is not None else " (beam-centre ring)"
    ax.set_ylabel(f"|mean $-$ truth| / truth [%]{where}")
    ax.set_xlabel(
        f"RA [deg], observed {start % 360:g}$-${(start + width) % 360 or 360:g}$^\\circ$"
        + (f";  light: 1 FWHM ({float(fwhm_deg):.1f}$^\\circ$) margins, dark: outside the primary beam" if not full else "")
    )
    for j, (shift, label, color) in enumerate(extra_axes):
        sec = ax.secondary_xaxis(-0.22 * (j + 1), functions=(lambda v, s=shift: v + s, lambda v, s=shift: v - s))
        sec.xaxis.set_major_formatter(fmt)
        sec.set_xlabel(f"RA [deg] of {label}", color=color, fontsize=9)
        sec.tick_params(axis="x", colors=color, labelsize=8)
    ax.legend(loc="best", fontsize=8, ncol=1 if len(curves) < 5 else 2, framealpha=0.9)
    smooth = (f"{passes} moving averages of {int(window)} ring pixels" if window is not None
              else f"{passes} moving averages of ~3$^\\circ$") if passes else "no smoothing"
    ax.set_title(f"{title}\n({smooth})" if title else f"|fractional difference| along the beam-centre ring ({smooth})",
                 fontsize=10)
    return _finish(fig, path)


def _slice_window(start: float, width: float, fwhm_deg, ra_limits) -> tuple[float, float]:
    """``(lo, hi)`` of the slice's x axis: ``ra_limits``, else the range +- 2 FWHM (at most 360 deg)."""
    if ra_limits is not None:
        lo, hi = (float(x) for x in ra_limits)
        return lo, hi
    pad = 2.0 * float(fwhm_deg)
    if width >= 360.0 or width + 2 * pad >= 360.0:
        return start + width / 2 - 180.0, start + width / 2 + 180.0
    return start - pad, start + width + pad


def _slice_curve(cv, start: float, width: float, window, passes: int):
    """One curve of :func:`plot_frac_slices`: ``(label, x, smoothed y, own range or None)``, sorted by x."""
    from .metrics import moving_average

    if len(cv) not in (3, 4):
        raise ValueError("each curve must be (label, ra_deg, absfrac) or (label, ra_deg, absfrac, ra_range_deg)")
    label, ra, y = cv[0], np.asarray(cv[1], np.float64), np.asarray(cv[2], np.float64)
    if ra.shape != y.shape or ra.ndim != 1:
        raise ValueError(f"curve {label!r}: ra_deg and absfrac must be equal-length 1-d arrays")
    own = len(cv) == 4 and cv[3] is not None
    c_start, c_width = _ra_range(cv[3]) if own else (start, width)
    order = np.argsort(ra % 360.0, kind="stable")  # ring order for the circular filter
    ra, y = ra[order] % 360.0, y[order]
    w = _default_window(ra) if window is None else int(window)
    ys = moving_average(y, w, passes) if ra.size else y
    # offset from the run's own start, unwrapped so [0, width] is contiguous and the
    # unobserved rest of the circle is split evenly before and after it
    o = (ra - c_start) % 360.0
    o = np.where(o >= c_width + (360.0 - c_width) / 2.0, o - 360.0, o) if c_width < 360.0 else o
    x = start + o
    k = np.argsort(x)
    return label, x[k], ys[k], ((c_start, c_width) if own else None)


def _plot_slice_curves(ax, curves, start: float, width: float, lo: float, hi: float, window, passes: int):
    """Draw the curves; returns (largest smoothed value inside ``[lo, hi]``, extra RA axes to add)."""
    extra_axes = []
    vis_max = 0.0
    for i, cv in enumerate(curves):
        label, x, ys, own = _slice_curve(cv, start, width, window, passes)
        line, = ax.plot(x, 100.0 * ys, lw=1.5, label=str(label), color="k" if i == 0 else f"C{(i - 1) % 10}")
        inwin = (x >= lo) & (x <= hi) & np.isfinite(ys)
        if inwin.any():
            vis_max = max(vis_max, float(np.max(ys[inwin])))
        if own is not None:
            c_start, c_width = own
            if abs(c_width - width) > 1e-6 and c_width < 360.0 and lo <= start + c_width <= hi:
                ax.axvline(start + c_width, color=line.get_color(), ls=":", lw=1.2)
            shift = ((c_start - start + 180.0) % 360.0) - 180.0
            if abs(shift) > 1e-9:
                extra_axes.append((shift, str(label), line.get_color()))
    return vis_max, extra_axes


def _shade_reference(ax, start: float, width: float, f: float, lo: float, hi: float) -> None:
    """Light shading over the FWHM margins of the reference range, dark beyond them, dotted ends."""
    stop = start + width
    for a, b in ((start - f, start), (stop, stop + f)):
        ax.axvspan(a, b, color="0.85", zorder=0, lw=0)
    for a, b in ((lo - 360.0, start - f), (stop + f, hi + 360.0)):
        ax.axvspan(a, b, color="0.6", zorder=0, lw=0)
    for r in (start, stop):
        ax.axvline(r, color="0.3", ls=":", lw=1.0)


def _slice_yscale(ax, yscale: str, vis_max: float) -> None:
    """``"auto"``: log when a smoothed curve exceeds 50% in the window, else linear from 0."""
    if yscale == "auto":
        yscale = "log" if vis_max > 0.50 else "linear"
    if yscale == "log":
        from matplotlib.ticker import LogFormatter

        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(LogFormatter(labelOnlyBase=False))
        ax.yaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False))
    elif yscale == "linear":
        ax.set_ylim(0.0, max(12.0, 105.0 * vis_max))
    else:
        raise ValueError(f"yscale must be 'auto', 'linear' or 'log', got {yscale!r}")


# ---------------------------------------------------------------- Fig. 7


def _lm_sorted_real(ell, m, is_imag):
    """Indices of the real-part entries ordered by (l, m), with their l and m."""
    ell, m, is_imag = (np.asarray(a) for a in (ell, m, is_imag))
    idx = np.flatnonzero(~is_imag.astype(bool))
    idx = idx[np.lexsort((m[idx], ell[idx]))]
    return idx, ell[idx], m[idx]


def _l_ticks(ls, ax, axis, min_sep):
    """Tick each degree's first mode on a matrix axis, skipping degrees closer than ``min_sep`` modes."""
    firsts = [int(np.flatnonzero(ls == l)[0]) for l in np.unique(ls)]
    lvals = [int(l) for l in np.unique(ls)]
    pos, lab, last = [], [], -np.inf
    for p, l in zip(firsts, lvals):
        if p - last >= min_sep:
            pos.append(p)
            lab.append(str(l))
            last = p
    if axis == "x":
        ax.set_xticks(np.asarray(pos) - 0.5, lab, fontsize=7)
    else:
        ax.set_yticks(np.asarray(pos) - 0.5, lab, fontsize=7)
    return firsts


def plot_correlation_matrix(
    draws,
    ell,
    m,
    is_imag,
    path,
    *,
    zoom_lmax: int = 9,
    title: str | None = None,
    max_lmax: int = 40,
) -> str:
    """Posterior correlation matrix of the real parts of the coefficients (paper Fig. 7, top right).

    ``corr = corrcoef(draws[:, real])`` with the real-part modes ordered by ``(l, m)``
    (ticks at ``m = 0`` of each ``l``; thin lines separate degrees).  Left: all real
    modes; right: zoom on ``l <= zoom_lmax`` (outlined on the left panel).  Modes with
    zero spread in the draws (no correlation defined) are grey.  Colour scale -1..1.

    Args:
        draws: ``(ndraws, n)`` realified draws of one frequency (``ndraws >= 2``).
        ell, m, is_imag: ``(n,)`` mode table (:func:`gcrsky.sphere.mode_table`).
        path: output PNG path.
        zoom_lmax: largest degree in the zoom panel.
        title: optional title.
        max_lmax: largest degree shown (the matrix has ~(l + 1)^2 / 2 rows: at the lmax a real
            file's baselines reach, 145, all of them would take 3.6 GB and a picture of 10^4
            rows no screen resolves).
    """
    plt = _plt()
    draws = np.asarray(draws, np.float64)
    if draws.ndim != 2 or draws.shape[0] < 2:
        raise ValueError(f"draws must be (ndraws >= 2, n), got shape {draws.shape}")
    idx, ls, ms = _lm_sorted_real(ell, m, is_imag)
    full_lmax = int(ls.max())
    keep = ls <= max_lmax
    idx, ls, ms = idx[keep], ls[keep], ms[keep]
    x = draws[:, idx]
    x = x - x.mean(axis=0)
    sd = np.sqrt(np.mean(x**2, axis=0))
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = x / sd
        corr = (xn.T @ xn) / x.shape[0]
    corr[:, sd == 0] = np.nan
    corr[sd == 0, :] = np.nan
    cmap = plt.get_cmap("RdBu_r").with_extremes(bad="0.7")
    lmax = int(ls.max())
    zl = int(min(max(zoom_lmax, 0), lmax))
    nz = int(np.sum(ls <= zl))
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.6), constrained_layout=True,
                             gridspec_kw={"width_ratios": [1, 1]})
    for ax, (sub, lsub, sep, name) in zip(
        axes,
        (
            (corr, ls, corr.shape[0] / 30.0, f"real parts, $\\ell \\leq {lmax}$ ({corr.shape[0]} modes"
             + (f" of $\\ell \\leq {full_lmax}$)" if full_lmax > lmax else ")")),
            (corr[:nz, :nz], ls[:nz], nz / 30.0, f"zoom on $\\ell \\leq {zl}$ ({nz} modes)"),
        ),
    ):
        im = ax.imshow(np.ma.masked_invalid(sub), cmap=cmap, vmin=-1, vmax=1, interpolation="nearest",
                       origin="upper", extent=(-0.5, sub.shape[1] - 0.5, sub.shape[0] - 0.5, -0.5))
        firsts = _l_ticks(lsub, ax, "x", sep)
        _l_ticks(lsub, ax, "y", sep)
        for p in firsts[1:]:
            ax.axvline(p - 0.5, color="0.5", lw=0.3 if sub is corr else 0.6)
            ax.axhline(p - 0.5, color="0.5", lw=0.3 if sub is corr else 0.6)
        ax.set_xlabel(r"mode, ordered by ($\ell$, $m$); ticks at $m = 0$ of $\ell$")
        ax.set_ylabel(r"mode ($\ell$)")
        ax.set_title(name, fontsize=10)
    axes[0].add_patch(plt.Rectangle((-0.5, -0.5), nz, nz, fill=False, ec="k", lw=1.2))
    cb = fig.colorbar(im, ax=axes, shrink=0.85, pad=0.01)
    cb.set_label(f"correlation ({draws.shape[0]} draws)")
    if title:
        fig.suptitle(title)
    return _finish(fig, path)


def _credible_levels(h, fracs=(0.393, 0.865)):
    """Density thresholds of a 2-D histogram enclosing the given probability masses (increasing)."""
    flat = np.sort(h.ravel())[::-1]
    cum = np.cumsum(flat)
    if cum[-1] <= 0:
        return []
    cum /= cum[-1]
    lev = sorted({float(flat[min(np.searchsorted(cum, f), flat.size - 1)]) for f in fracs})
    return [v for v in lev if v > 0]


def plot_corner(
    draws,
    truth,
    ell,
    m,
    is_imag,
    path,
    *,
    m_value: int = 2,
    ells: Sequence[int] | None = None,
    title: str | None = None,
) -> str:
    """1-D and 2-D marginals of ``draws / truth`` for a few ``l`` at one ``m`` (paper Fig. 7, bottom left).

    Lower-triangle corner plot over the chosen degrees ``l``: on the diagonal the
    histograms of ``a_lm / a_lm^true`` for each ``l``; below it the 2-D marginals of
    pairs of degrees (contours enclosing ~39% and ~86% of the draws, i.e. 1 and 2
    sigma in 2-D, over the draws as faint points).  Real parts in purple, imaginary
    parts (``m >= 1``) in orange, overlaid on the same axes; dashed coloured lines
    mark the medians, black lines the truth (1 after normalisation).  A ratio is
    only formed where the truth is nonzero.

    Args:
        draws: ``(ndraws, n)`` realified draws of one frequency.
        truth: ``(n,)`` true realified coefficients.
        ell, m, is_imag: ``(n,)`` mode table (:func:`gcrsky.sphere.mode_table`).
        path: output PNG path.
        m_value: the fixed order ``m`` (the paper uses 2).
        ells: degrees to show (each ``>= m_value``, ``<= lmax``); default
            ``2, 5, 10, 15, 20`` clipped to ``[m_value, lmax]`` (duplicates dropped).
        title: optional title.
    """
    plt = _plt()
    draws = np.asarray(draws, np.float64)
    truth = np.asarray(truth, np.float64)
    ell, m, is_imag = (np.asarray(a) for a in (ell, m, is_imag))
    is_imag = is_imag.astype(bool)
    if draws.ndim != 2 or draws.shape[1] != truth.shape[-1] or truth.ndim != 1:
        raise ValueError(f"need draws (ndraws, n) and truth (n,), got {draws.shape} and {truth.shape}")
    ells = _corner_ells(int(ell.max()), m_value, ells)
    parts = [(False, "Re", "C4")] + ([(True, "Im", "C1")] if m_value >= 1 else [])

    def column(l, imag):
        j = np.flatnonzero((ell == l) & (m == m_value) & (is_imag == imag))
        if j.size != 1 or truth[j[0]] == 0:
            return None
        return draws[:, j[0]] / truth[j[0]]

    cols = {(l, imag): column(l, imag) for l in ells for imag, _, _ in parts}
    lims = _corner_limits(cols, ells)
    k = len(ells)
    size = max(1.9, min(2.6, 12.0 / k))
    fig, axes = plt.subplots(k, k, figsize=(size * k + 0.6, size * k + 0.4), squeeze=False)
    nd = draws.shape[0]
    for i, li in enumerate(ells):
        for j, lj in enumerate(ells):
            if j > i:
                axes[i, j].set_visible(False)
                continue
            for part in parts:
                _corner_part(axes[i, j], part, cols[(li, part[0])], cols[(lj, part[0])], lims[li], lims[lj],
                             diagonal=i == j, nd=nd)
            _corner_frame(axes[i, j], i, j, k, li, lj, m_value, lims)
    h0, l0 = axes[0, 0].get_legend_handles_labels()
    from matplotlib.lines import Line2D

    h0 = h0 + [Line2D([], [], color="0.3", ls="--"), Line2D([], [], color="k")]
    l0 = l0 + ["median", "truth"]
    fig.legend(h0, l0, loc="upper right", fontsize=9, frameon=False, bbox_to_anchor=(0.98, 0.98))
    fig.suptitle(title if title else f"posterior marginals at $m = {m_value}$, normalised by the truth ({nd} draws)",
                 fontsize=11)
    fig.subplots_adjust(wspace=0.08, hspace=0.08, top=1.0 - 0.45 / fig.get_figheight())
    return _finish(fig, path)


def _corner_ells(lmax: int, m_value: int, ells) -> list[int]:
    """The corner plot's degrees: ``ells`` checked, or ``2, 5, 10, 15, 20`` clipped to ``[m_value, lmax]``."""
    if not 0 <= m_value <= lmax:
        raise ValueError(f"m_value must be in [0, {lmax}], got {m_value}")
    if ells is None:
        ells = list(dict.fromkeys(int(min(max(l, m_value), lmax)) for l in (2, 5, 10, 15, 20)))
    ells = [int(l) for l in ells]
    bad = [l for l in ells if not m_value <= l <= lmax]
    if bad or not ells:
        raise ValueError(f"ells must be non-empty with m_value <= l <= lmax ({m_value}..{lmax}), got {ells}")
    return ells


def _corner_limits(cols: dict, ells) -> dict:
    """One axis range per l covering both parts (central 99% of the draws, and the truth)."""
    lims = {}
    for l in ells:
        vals = [c for (ll, _), c in cols.items() if ll == l and c is not None]
        if vals:
            v = np.concatenate(vals)
            a, b = np.percentile(v, [0.5, 99.5])
            a, b = min(a, 1.0), max(b, 1.0)
        else:
            a, b = 0.0, 2.0
        pad = 0.08 * (b - a if b > a else 1.0)
        lims[l] = (a - pad, b + pad)
    return lims


def _corner_part(ax, part, ci, cj, lim_i, lim_j, *, diagonal: bool, nd: int) -> None:
    """One part (real or imaginary) of a corner panel: a histogram on the diagonal, else points and contours."""
    _, name, color = part
    if diagonal:
        if ci is None:
            return
        bins = np.linspace(*lim_i, 31)
        ax.hist(np.clip(ci, *lim_i), bins=bins, histtype="step", color=color, lw=1.4, density=True,
                label=f"{name} $a_{{\\ell m}}$")
        ax.axvline(np.median(ci), color=color, ls="--", lw=1.1)
        return
    if ci is None or cj is None:
        return
    ax.plot(cj, ci, ".", ms=1.5, color=color, alpha=0.25 if nd > 200 else 0.5, rasterized=True)
    if nd >= 50:
        h, xe, ye = np.histogram2d(cj, ci, bins=20, range=[lim_j, lim_i])
        lev = _credible_levels(h)
        if len(lev) >= 1:
            xc, yc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])
            ax.contour(xc, yc, h.T, levels=lev, colors=[color], linewidths=1.1)
    ax.plot(np.median(cj), np.median(ci), "+", color=color, ms=9, mew=1.6)


def _corner_frame(ax, i: int, j: int, k: int, li: int, lj: int, m_value: int, lims: dict) -> None:
    """Truth lines, limits, ticks and labels of corner panel ``(i, j)`` of ``k x k``."""
    ax.axvline(1.0, color="k", lw=1.0)
    if i != j:
        ax.axhline(1.0, color="k", lw=1.0)
        ax.set_ylim(*lims[li])
    else:
        ax.set_yticks([])
    ax.set_xlim(*lims[lj])
    ax.tick_params(labelsize=7)
    if i == k - 1:
        ax.set_xlabel(f"$a_{{{lj},{m_value}}}$ / truth", fontsize=9)
    else:
        ax.set_xticklabels([])
    if j == 0 and i > 0:
        ax.set_ylabel(f"$a_{{{li},{m_value}}}$ / truth", fontsize=9)
    elif j > 0:
        ax.set_yticklabels([])
