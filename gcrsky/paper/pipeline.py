"""One run of the paper's pipeline on a simulated problem: sample, summarise, plot, write.

:func:`run_problem` is what ``gcrsky run`` (and each scenario of ``gcrsky scenarios``)
does, in library steps:

1. :func:`gcrsky.prepare` (set-up and Wiener filter) and
   :func:`gcrsky.inference.draw_batches` (the documented key scheme);
2. :func:`solver_summary`: iterations, errors, convergence, warnings;
3. :func:`map_summary`: truth / mean / std maps and the paper's beam-region metrics;
4. :func:`run_figures`: the paper's per-run figures (Figs. 3-7);
5. :func:`gcrsky.io.write_results_h5` and :func:`gcrsky.io.write_json`.

Stage timings are recorded by a :class:`StageTimer`; the caller may watch the stages
(``on_stage``) and the draw batches (``progress``) to drive its own progress display:
nothing here prints.
"""

from __future__ import annotations

import json
import logging
import os
import platform
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import numpy as np

from ..inference.api import prepare
from ..inference.batches import KEY_SCHEME, draw_batches
from ..instrument.beams import beam_fwhm_rad
from ..io.results import json_default, write_json, write_results_h5
from ..sim.standard import beam_for_config
from ..sphere.maps import alm_to_map, posterior_maps
from . import metrics as M

__all__ = [
    "MapSummary",
    "RunProducts",
    "StageTimer",
    "info_stats",
    "map_summary",
    "run_figures",
    "run_problem",
    "solver_summary",
    "versions",
]

log = logging.getLogger(__name__)


class StageTimer:
    """Wall-clock seconds of named stages; ``on_stage(name, "start" | "stop")`` is called around each."""

    def __init__(self, on_stage: Callable[[str, str], None] | None = None):
        self.times: dict[str, float] = {}
        self._on = on_stage
        self._name: str | None = None
        self._t0 = 0.0

    def start(self, name: str) -> None:
        self._name, self._t0 = name, time.perf_counter()
        log.info("stage %s ...", name)
        if self._on:
            self._on(name, "start")

    def stop(self) -> None:
        dt = time.perf_counter() - self._t0
        self.times[self._name] = dt
        log.info("stage %s done in %.2f s", self._name, dt)
        if self._on:
            self._on(self._name, "stop")


def info_stats(info) -> dict:
    """Summary numbers of a :class:`~gcrsky.solvers.SolveInfo` (iterations, worst error, convergence)."""
    it = np.asarray(info.iterations)
    err = np.asarray(info.err_sigma, np.float64)
    conv = np.asarray(info.converged, bool)
    return {
        "n_solves": int(conv.size),
        "iterations_mean": float(it.mean()) if it.size else 0.0,
        "iterations_median": float(np.median(it)) if it.size else 0.0,
        "iterations_max": int(it.max()) if it.size else 0,
        "err_sigma_max": float(np.nanmax(err)) if err.size and np.isfinite(err).any() else float("nan"),
        "n_not_converged": int((~conv).sum()),
        "all_converged": bool(conv.all()),
    }


def versions() -> dict:
    """Versions of gcrsky and the packages a run's numbers depend on."""
    import h5py
    import healpy

    from .. import __version__

    out = {
        "gcrsky": __version__,
        "jax": jax.__version__,
        "jaxlib": getattr(getattr(jax, "lib", None), "__version__", None) or _pkg_version("jaxlib"),
        "numpy": np.__version__,
        "healpy": healpy.__version__,
        "h5py": h5py.__version__,
        "matplotlib": _pkg_version("matplotlib"),
        "python": platform.python_version(),
        "jax_backend": jax.default_backend(),
    }
    return out


def _pkg_version(name: str):
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:  # noqa: BLE001
        return None


def solver_summary(method: str, tol: float, winfo, dinfo, prepared, n: int) -> tuple[dict, list[str]]:
    """The ``solver`` block of ``summary.json`` and the run's solver warnings.

    Args:
        method: the path that ran; tol: the CG tolerance asked for.
        winfo, dinfo: SolveInfo of the Wiener solve and of the draws.
        prepared: the prepared path (the eigen path reports its rank).
        n: number of parameters.
    """
    warnings: list[str] = []
    solver = {"method": method, "tol_sigma": tol, "wiener": info_stats(winfo), "draws": info_stats(dinfo)}
    rank = getattr(prepared, "rank", None)
    if rank is not None:
        rank = [int(r) for r in np.asarray(rank)]
        solver["rank"] = rank
        if min(rank) < n:
            warnings.append(
                f"NOTE: P is singular (improper posterior, e.g. S^-1 = 0): {n - min(rank)} of {n} directions carry "
                f"no information and are pinned at 0; draws and the mean cover the {min(rank)} the data inform."
            )
    solver["all_converged"] = solver["wiener"]["all_converged"] and solver["draws"]["all_converged"]
    if not solver["all_converged"]:
        warnings.append(
            f"WARNING: {solver['wiener']['n_not_converged']} Wiener-filter and "
            f"{solver['draws']['n_not_converged']} draw solves did not converge "
            f"(worst error {max(solver['wiener']['err_sigma_max'], solver['draws']['err_sigma_max']):.3g} "
            "posterior sigma); results are written but may be inaccurate (exit status stays 0)."
        )
    return solver, warnings


class MapSummary(NamedTuple):
    """Maps (Nf, Npix) and the paper's metrics of one run (:func:`map_summary`)."""

    truth_maps: np.ndarray
    mean_maps: np.ndarray
    std_maps: np.ndarray
    mode_z: np.ndarray
    per_freq: list
    centre_dec_deg: float
    ra_range_deg: tuple


def map_summary(prob, draws: np.ndarray, a_wf: np.ndarray) -> MapSummary:
    """Truth, posterior mean and std maps and the beam-region metrics at every frequency.

    The beam centre is the site latitude, the observed RA range ``15 x`` the LST range
    and the FWHM that of the configuration's beam (:func:`gcrsky.sim.beam_for_config`);
    see :func:`gcrsky.paper.metrics.summary_metrics`.  Non-finite draws give NaN maps.
    """
    cfg = prob.config
    lmax, nside = prob.lmax, prob.nside
    freqs = np.asarray(prob.freqs_hz)
    truth = np.asarray(prob.a_true)
    truth_maps = alm_to_map(truth, lmax, nside)
    wf_maps = alm_to_map(a_wf, lmax, nside)
    if bool(np.isfinite(draws).all()):
        mean_maps, std_maps = posterior_maps(draws, lmax, nside)
    else:
        mean_maps = std_maps = np.full_like(truth_maps, np.nan)
    z = M.mode_z_scores(draws, truth)  # (Nf, n)
    centre_dec = float(cfg.latitude_deg)
    ra_range = (15.0 * cfg.lst_range_hours[0], 15.0 * cfg.lst_range_hours[1])
    per_freq = []
    for f in range(freqs.size):
        fwhm = float(np.rad2deg(beam_fwhm_rad(beam_for_config(cfg), float(freqs[f]))))
        m = {"freq_hz": float(freqs[f]), "fwhm_deg": fwhm}
        m.update(M.summary_metrics(mean_maps[f], truth_maps[f], centre_dec, fwhm, ra_range, std_map=std_maps[f]))
        wfm = M.summary_metrics(wf_maps[f], truth_maps[f], centre_dec, fwhm, ra_range)
        m["wiener_frac_diff_centre_median"] = wfm["frac_diff_centre_median"]
        m["wiener_frac_diff_fwhm_median"] = wfm["frac_diff_fwhm_median"]
        m["mode_z"] = M.z_score_stats(z[f])
        per_freq.append(m)
    return MapSummary(truth_maps, mean_maps, std_maps, z, per_freq, centre_dec, ra_range)


def run_figures(out: Path, prob, draws: np.ndarray, ms: MapSummary, *, scenario_name=None) -> dict:
    """The paper's per-run figures (first frequency): Figs. 3-7 as PNG files in ``out``.

    Returns:
        ``{figure key: file name}``.
    """
    from . import figures as P

    out = Path(out)
    freqs = np.asarray(prob.freqs_hz)
    nsamples = draws.shape[1]
    modes = prob.modes
    f0 = ms.per_freq[0]
    truth = np.asarray(prob.a_true)
    truth_map, mean_map, std_map = ms.truth_maps[0], ms.mean_maps[0], ms.std_maps[0]
    centre_dec, ra_range = ms.centre_dec_deg, ms.ra_range_deg
    lab = (f"{scenario_name}: " if scenario_name else "") + f"{freqs[0] / 1e6:g} MHz, {nsamples} draws"
    paths = {}
    paths["fig3"] = P.plot_alm_residuals(
        ms.mode_z[0], modes.ell, modes.m, modes.is_imag, out / "fig3_alm_residuals.png",
        title=f"(posterior mean $-$ truth) / posterior std per mode, {lab}",
    )
    region = (centre_dec, f0["fwhm_deg"], ra_range)
    paths["fig4"] = P.plot_sky_maps(
        truth_map, mean_map, std_map, out / "fig4_sky_maps.png", region=region,
        title=f"{lab}; green: $\\pm$1 FWHM band over the observed LSTs",
    )
    paths["fig5"] = P.plot_beam_region(
        M.frac_diff_map(mean_map, truth_map), out / "fig5_beam_region.png",
        centre_dec_deg=centre_dec, fwhm_deg=f0["fwhm_deg"], ra_range_deg=ra_range,
        title=f"(posterior mean $-$ truth) / truth near the beam, {lab}\nmedian |frac|: "
        f"{f0['frac_diff_centre_median']:.2%} on the centre ring, {f0['frac_diff_fwhm_median']:.2%} within "
        f"$\\pm$1 FWHM (observed RA range)",
    )
    absfrac = np.abs(M.frac_diff_map(mean_map, truth_map))
    ra_ring, vals = M.ring_slice(absfrac, prob.nside, centre_dec)
    paths["fig6"] = P.plot_frac_slices(
        [(scenario_name or "this run", ra_ring, vals)], out / "fig6_slice.png", fwhm_deg=f0["fwhm_deg"],
        ra_range_deg=ra_range, dec_deg=centre_dec, title=f"|mean $-$ truth| / truth along the beam centre, {lab}",
    )
    if nsamples >= 2:
        paths["fig7_correlation"] = P.plot_correlation_matrix(
            draws[0], modes.ell, modes.m, modes.is_imag, out / "fig7_correlation.png",
            title=f"posterior correlation (real parts), {lab}",
        )
        paths["fig7_corner"] = P.plot_corner(
            draws[0], truth[0], modes.ell, modes.m, modes.is_imag, out / "fig7_corner.png", m_value=2,
            title=f"marginal posteriors / truth at m = 2, {lab}",
        )
    return {k: os.path.basename(v) for k, v in paths.items()}


class RunProducts(dict):
    """In-memory products of one run that the suite reuses (first frequency): the
    truth / mean / std maps, per-mode z-scores, the draws and the mode table."""


_METRICS_NOTE = (
    "metrics at the first frequency; |mean - truth|/|truth| of the posterior-mean map (sample mean of the "
    "draws) over the beam-centre ring (the HEALPix ring nearest dec = site latitude) and the +-1 FWHM band, "
    "both within RA = 15 x LST range; FWHM measured from the simulated beam's power pattern; "
    "per_frequency has every channel; the two top-level frac_diff_* keys repeat the first channel's"
)
_TIMINGS_NOTE = (
    "wall-clock seconds; 'wiener' and the first draw batch include JIT compilation; "
    "the set-up (P, its Cholesky factor or CG preconditioner, the Wiener filter) is done once, in 'wiener'"
)


def run_problem(
    prob,
    out,
    *,
    nsamples: int,
    seed: int,
    batch: int,
    method: str,
    plots: bool,
    build_s: float,
    tol: float = 1e-6,
    argv=None,
    scenario_name: str | None = None,
    on_stage: Callable[[str, str], None] | None = None,
    progress=None,
) -> tuple[dict, RunProducts]:
    """Sample a simulated ``prob`` and write ``results.h5``, ``summary.json`` and figures to ``out``.

    Args:
        prob: a :class:`~gcrsky.model.Problem` with a truth and a
            :class:`~gcrsky.sim.Config` (from :func:`gcrsky.sim.problem_from_config`).
        out: output directory (must exist).
        nsamples, seed, batch: the draws (key ``PRNGKey(seed)``, batches of ``batch``;
            :mod:`gcrsky.inference.batches`).
        method: exact path (``"auto"`` chooses); tol: CG tolerance, posterior sigma.
        plots: write the figures.
        build_s: seconds spent building ``prob`` (recorded).
        argv: the command line (recorded).
        scenario_name: the paper scenario, if any (recorded, and in figure titles).
        on_stage: called with ``(stage, "start" | "stop")`` around each stage.
        progress: wrapper of the batch iterable (e.g. a tqdm bar).

    Returns:
        (the summary dict written to ``summary.json``, :class:`RunProducts`).
    """
    out = Path(out)
    st = StageTimer(on_stage)
    st.times["build"] = build_s
    cfg = prob.config
    n = prob.n

    st.start("wiener")  # set-up once: P, factor / preconditioner, Wiener filter (compile included)
    prepared = prepare(prob, method=method, tol=tol, ndraws=batch)
    method = prepared.method  # what "auto" chose
    a_wf, winfo = np.asarray(jax.block_until_ready(prepared.a_wf)), prepared.wiener
    st.stop()

    st.start("draws")
    bd = draw_batches(jax.random.PRNGKey(seed), prepared, nsamples, batch, progress=progress)
    draws = bd.draws
    st.stop()

    finite = bool(np.isfinite(draws).all())
    solver, warnings = solver_summary(method, tol, winfo, bd.info, prepared, n)
    if not finite:
        warnings.append(f"ERROR: {int((~np.isfinite(draws)).sum())} non-finite values in the draws.")

    st.start("maps")
    ms = map_summary(prob, draws, a_wf)
    st.stop()

    fig_paths = {}
    if plots:
        st.start("plots")
        if finite:
            fig_paths = run_figures(out, prob, draws, ms, scenario_name=scenario_name)
        st.stop()

    st.start("write")
    vers = versions()
    attrs = {
        "config_json": json.dumps(cfg.to_dict(), default=json_default),
        "sky_note": prob.sky_note,
        "gcrsky_version": vers["gcrsky"],
        "seed": seed,
        "batch": batch,
        "method": method,
        "scenario": scenario_name or "",
        "key_scheme": KEY_SCHEME,
    }
    maps = {"truth": ms.truth_maps, "mean": ms.mean_maps, "std": ms.std_maps}
    write_results_h5(out / "results.h5", prob, draws, a_wf, mode_z=ms.mode_z, maps=maps, attrs=attrs)
    st.stop()

    timings = dict(st.times)
    timings["total"] = float(sum(v for v in st.times.values()))
    timings["draw_batches_s"] = bd.batch_seconds
    timings["note"] = _TIMINGS_NOTE
    per_freq = ms.per_freq
    summary = {
        "frac_diff_centre_median": per_freq[0]["frac_diff_centre_median"],
        "frac_diff_fwhm_median": per_freq[0]["frac_diff_fwhm_median"],
        "metrics": dict(per_freq[0]),
        "metrics_note": _METRICS_NOTE,
        "per_frequency": per_freq,
        "region": {"centre_dec_deg": ms.centre_dec_deg, "ra_range_deg": list(ms.ra_range_deg),
                   "fwhm_deg": [m["fwhm_deg"] for m in per_freq]},
        "solver": solver,
        "draws_finite": finite,
        "warnings": warnings,
        "timings_s": timings,
        "run": {"nsamples": nsamples, "seed": seed, "batch": batch, "method": method, "scenario": scenario_name,
                "argv": argv},
        "figures": fig_paths,
        "config": cfg.to_dict(),
        "sky_note": prob.sky_note,
        "versions": vers,
        "exit_status": 0 if finite else 1,
    }
    write_json(out / "summary.json", summary)
    products = RunProducts(
        truth_map=ms.truth_maps[0], mean_map=ms.mean_maps[0], std_map=ms.std_maps[0], z=ms.mode_z[0],
        draws=draws[0], truth=np.asarray(prob.a_true)[0], modes=prob.modes, fwhm_deg=per_freq[0]["fwhm_deg"],
        centre_dec_deg=ms.centre_dec_deg, ra_range_deg=ms.ra_range_deg,
    )
    return summary, products
