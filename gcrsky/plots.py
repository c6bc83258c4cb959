"""Figures in the style of Glasscock et al. (2024): Figs. 3, 4 and 5.

Each function takes plain arrays and an output path, writes a PNG and returns the
path.  matplotlib is imported lazily; if pyplot is not imported yet, the
non-interactive Agg backend is selected (a caller's existing pyplot setup is left
alone).  Nothing is shown on screen; figures are closed after saving.  Angles are in degrees; maps are HEALPix RING, equatorial
(see :mod:`gcrsky.maps`).
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

__all__ = ["plot_alm_residuals", "plot_sky_maps", "plot_beam_region"]


def _plt():
    """pyplot, selecting the Agg backend unless the caller already set pyplot up."""
    import sys

    import matplotlib

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
        z: ``(n,)`` z-scores of the realified modes (:func:`gcrsky.maps.mode_z_scores`).
        ell, m, is_imag: ``(n,)`` mode table (:func:`gcrsky.layout.mode_table`).
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

    from .maps import frac_diff_map

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
