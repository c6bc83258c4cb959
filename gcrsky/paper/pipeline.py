"""One run of the paper's pipeline on a problem: sample, summarise, plot, write; resumable.

:func:`run_problem` is what ``gcrsky run`` (and each scenario of ``gcrsky scenarios``)
does, in library steps:

1. :func:`check_output`: an output directory that already holds a run's files is
   refused (``existing="refuse"``), cleared (``"overwrite"``: :func:`remove_run_files`)
   or continued (``"resume"``: the settings recorded in its ``results.h5`` must equal
   this run's, :func:`run_settings`, and so must the problem's inputs);
2. :func:`gcrsky.prepare` (set-up and Wiener filter), then the draws batch by batch
   with the documented key scheme (:func:`draw_batch`, as
   :func:`gcrsky.inference.draw_batches`), each batch appended to ``results.h5``
   (:func:`gcrsky.io.append_batch`) as soon as it is drawn; a resumed run starts at
   the first missing batch and so ends with exactly the draws of an uninterrupted one;
3. :func:`solver_summary`: iterations, errors, convergence, warnings;
4. :func:`map_summary`: truth / mean / std / Wiener maps and the paper's beam-region
   metrics (those that need a truth only when the problem has one);
5. :func:`run_figures`: the paper's per-run figures (Figs. 3-7; needs a truth);
6. :func:`write_products`: ``posterior_mean.fits`` and ``posterior_std.fits``
   (HEALPix maps), ``posterior_mean_alm.fits`` (healpy alm) and
   ``posterior_mean.skyh5`` (pyradiosky); then :func:`gcrsky.io.finalize_results_h5`
   (maps into ``results.h5``) and ``summary.json``.

The posterior mean in the products is the Wiener filter (the exact posterior mean,
no Monte Carlo noise); the std map is the per-pixel standard deviation over the
draws; ``results.h5``'s ``maps/mean`` (the draws' mean, which the paper's metrics
use) differs from the Wiener map by Monte Carlo noise.  Every file is written
atomically (temporary name, then rename; :mod:`gcrsky.io.atomic`); a resumed run
writes only the files that are missing.

Stage timings are recorded by a :class:`StageTimer`, and the run's XLA compilation (seconds,
persistent-cache hits and misses) by :func:`gcrsky.parallel.compile_stats`; the caller may watch the stages
(``on_stage``) and the draw batches (``progress``) to drive its own progress display:
nothing here prints.

Test hook: when the environment variable ``GCRSKY_TEST_KILL_AFTER_BATCH`` is ``k``,
the process kills itself with SIGKILL as soon as ``results.h5`` records ``k``
complete batches (an abrupt death, as a killed job; ``tests/test_resume.py`` uses
it).  It is meant for tests only.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import platform
import signal
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import numpy as np

from ..inference.api import prepare
from ..inference.batches import KEY_SCHEME, batch_key
from ..inference.posterior import draw_exactly as draw
from ..instrument.beams import beam_fwhm_rad
from ..io.atomic import atomic_path, is_temporary
from ..io.fits import write_alm_fits, write_healpix_fits
from ..io.results import (
    append_batch,
    clean_json,
    create_results_h5,
    finalize_results_h5,
    inputs_fingerprint,
    json_default,
    read_draws,
    read_results_state,
    write_json,
)
from ..io.skymodel import write_skyh5
from ..parallel.channels import (
    CHANNEL_KEY_SCHEME,
    distributed_channels,
    resolve_channel_path,
    sample_channels,
    sample_channels_sharded,
)
from ..parallel.runtime import CompileStats, compile_cache_dir, compile_stats
from ..sim.standard import beam_for_config
from ..solvers.plan import choose_path
from ..solvers.registry import method_of, options_for
from ..sphere.maps import alm_to_map, posterior_maps
from . import metrics as M

__all__ = [
    "EXISTING",
    "FIGURE_FILES",
    "PRODUCT_FILES",
    "RESULTS_FILE",
    "RUN_FILES",
    "SUMMARY_FILE",
    "MapSummary",
    "ResumeError",
    "RunExistsError",
    "RunProducts",
    "StageTimer",
    "check_output",
    "draw_batch",
    "existing_run_files",
    "info_stats",
    "map_summary",
    "parameter_frame",
    "remove_run_files",
    "run_figures",
    "data_figures",
    "run_problem",
    "run_settings",
    "settings_differences",
    "solver_summary",
    "versions",
    "write_products",
]

log = logging.getLogger(__name__)

#: The appendable HDF5 file of a run (:mod:`gcrsky.io.results`).
RESULTS_FILE = "results.h5"
#: The run's summary (written last: its presence means the run finished).
SUMMARY_FILE = "summary.json"
#: The standard products: ``{key: file name}`` (:func:`write_products`).
PRODUCT_FILES = {
    "posterior_mean_fits": "posterior_mean.fits",
    "posterior_std_fits": "posterior_std.fits",
    "posterior_mean_alm": "posterior_mean_alm.fits",
    "posterior_mean_skyh5": "posterior_mean.skyh5",
}
#: The per-run figures: ``{key: file name}`` (:func:`run_figures`).
FIGURE_FILES = {
    "fig3": "fig3_alm_residuals.png",
    "fig4": "fig4_sky_maps.png",
    "fig5": "fig5_beam_region.png",
    "fig6": "fig6_slice.png",
    "fig7_correlation": "fig7_correlation.png",
    "fig7_corner": "fig7_corner.png",
}
#: Every file a run writes into its directory (what :func:`existing_run_files` looks for).
RUN_FILES = (RESULTS_FILE, SUMMARY_FILE, *PRODUCT_FILES.values(), *FIGURE_FILES.values())
#: What :func:`run_problem` may do with a directory that holds a run's files.
EXISTING = ("refuse", "overwrite", "resume")
#: Environment variable of the kill test hook (module doc).
_KILL_HOOK = "GCRSKY_TEST_KILL_AFTER_BATCH"


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
        "pyradiosky": _pkg_version("pyradiosky"),
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


def solver_summary(method: str, tol: float, winfo, dinfo, prepared=None, n: int = 0, *, rank=None
                   ) -> tuple[dict, list[str]]:
    """The ``solver`` block of ``summary.json`` and the run's solver warnings.

    Args:
        method: the path that ran; tol: the CG tolerance asked for.
        winfo, dinfo: SolveInfo of the Wiener solve and of the draws.
        prepared: the prepared path (the eigen path reports its rank), or None.
        n: number of parameters.
        rank: the eigen path's ``(Nf,)`` rank, when ``prepared`` is not at hand
            (e.g. read back from ``results.h5``).
    """
    warnings: list[str] = []
    solver = {"method": method, "tol_sigma": tol, "wiener": info_stats(winfo), "draws": info_stats(dinfo)}
    if rank is None:
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


# ---------------------------------------------------------------- the output directory


class RunExistsError(FileExistsError):
    """The output directory already holds a run's files (and neither resume nor overwrite was asked for).

    Attributes:
        out: the directory; files: the run files found in it.
    """

    def __init__(self, out, files, message: str | None = None):
        self.out, self.files = Path(out), list(files)
        super().__init__(message or (
            f"{out} already holds results of a run ({', '.join(self.files)}); resume it or overwrite it"
        ))


class ResumeError(ValueError):
    """The run in the output directory cannot be resumed by this one.

    Attributes:
        out: the directory.
        differences: ``[(setting, recorded, requested)]`` where the settings differ
            (:func:`settings_differences`; empty when the reason is another one).
    """

    def __init__(self, out, message: str, differences=()):
        self.out, self.differences = Path(out), list(differences)
        super().__init__(message)


def run_settings(
    config,
    *,
    nsamples: int,
    seed: int,
    batch: int,
    method: str,
    tol: float,
    scenario: str | None = None,
    extra: dict | None = None,
) -> dict:
    """What identifies a run's draws: recorded in ``results.h5`` and compared on resume.

    Args:
        config: the problem's :class:`~gcrsky.sim.Config` (or its ``to_dict()``), or
            None for a problem that has none (then ``extra`` should identify the inputs).
        nsamples, seed, batch: the draws (key scheme :data:`gcrsky.inference.batches.KEY_SCHEME`).
        method: the path asked for (``"auto"`` included; a resumed run uses the path
            the recorded run chose); tol: CG tolerance, posterior sigma.
        scenario: the paper scenario, if any.
        extra: further settings (e.g. the input file of a run on real data).

    Returns:
        a JSON-able dict (``config``, ``nsamples``, ``seed``, ``batch``, ``method``,
        ``tol``, ``scenario``, ``key_scheme`` and ``extra``'s keys).
    """
    if config is not None and not isinstance(config, dict):
        config = config.to_dict()
    out = {
        "config": config, "nsamples": int(nsamples), "seed": int(seed), "batch": int(batch), "method": str(method),
        "tol": float(tol), "scenario": scenario, "key_scheme": KEY_SCHEME,
    }
    for k, v in (extra or {}).items():
        if k in out:
            raise ValueError(f"extra setting {k!r} clashes with a standard one")
        out[k] = v
    return json.loads(json.dumps(clean_json(out), default=json_default))  # canonical: lists, plain numbers


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def settings_differences(recorded: dict, requested: dict) -> list[tuple[str, object, object]]:
    """``[(setting, recorded value, requested value)]`` where two :func:`run_settings` differ.

    Nested settings are named with dots (``config.lmax``); a setting missing on one
    side is reported with the value ``None`` there.
    """
    a = _flatten(json.loads(json.dumps(recorded, default=json_default)))
    b = _flatten(json.loads(json.dumps(requested, default=json_default)))
    return [(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


def existing_run_files(out) -> list[str]:
    """The run files (:data:`RUN_FILES`) present in ``out``, in that order."""
    out = Path(out)
    return [f for f in RUN_FILES if (out / f).exists()]


def _temporaries(out: Path) -> list[Path]:
    if not out.is_dir():
        return []
    return [p for p in out.iterdir() if any(is_temporary(p, f) for f in RUN_FILES)]


def remove_run_files(out) -> list[str]:
    """Delete the run files (:data:`RUN_FILES`) in ``out`` and any temporary files a killed writer left.

    Nothing else in ``out`` is touched.  Returns the names removed.
    """
    out = Path(out)
    gone = []
    for f in existing_run_files(out):
        (out / f).unlink()
        gone.append(f)
    for p in _temporaries(out):
        p.unlink(missing_ok=True)
        gone.append(p.name)
    return gone


def check_output(out, settings: dict, existing: str = "refuse"):
    """Decide what a run with ``settings`` may do in ``out``; raises if it may not.

    Args:
        out: the output directory (need not exist).
        settings: this run's :func:`run_settings`.
        existing: ``"refuse"`` (a directory holding run files is an error),
            ``"overwrite"`` (it will be cleared) or ``"resume"`` (its run is continued).

    Returns:
        the :class:`gcrsky.io.ResultsState` to continue (``"resume"`` with a
        ``results.h5``), else None (a new run).

    Raises:
        RunExistsError: ``"refuse"`` and run files are present; or ``"resume"``, no
            ``results.h5`` but other run files.
        ResumeError: ``"resume"`` and the recorded run cannot be continued: its
            settings differ (:attr:`ResumeError.differences`), it records none (an older
            layout), or ``results.h5`` cannot be read.
    """
    if existing not in EXISTING:
        raise ValueError(f"existing must be one of {EXISTING}, got {existing!r}")
    out = Path(out)
    files = existing_run_files(out)
    if existing == "overwrite" or not files:
        return None
    if existing == "refuse":
        raise RunExistsError(out, files)
    h5 = out / RESULTS_FILE
    if not h5.exists():
        raise RunExistsError(out, files, f"{out} holds {', '.join(files)} but no {RESULTS_FILE}: nothing to resume "
                                         "from; overwrite it to start again")
    try:
        state = read_results_state(h5)
    except ValueError as e:
        raise ResumeError(out, f"cannot resume: {e}") from e
    if state.settings is None:
        raise ResumeError(out, f"cannot resume: {h5} records no run settings (written by an older gcrsky)")
    diffs = settings_differences(state.settings, settings)
    if diffs:
        what = "; ".join(f"{k}: recorded {a!r}, now {b!r}" for k, a, b in diffs)
        raise ResumeError(out, f"cannot resume the run in {out}: its settings differ: {what}", diffs)
    return state


def parameter_frame(prob) -> str:
    """The frame of ``prob``'s sky coefficients: ``"icrs"`` (real observing times) or
    ``"idealised"`` (the paper's idealised LSTs: the co-rotating equatorial frame)."""
    return "idealised" if prob.frame is None else "icrs"


# ---------------------------------------------------------------- draws, maps, figures, products


def draw_batch(key: jax.Array, prepared, b: int, batch: int, nsamples: int):
    """Batch ``b`` of the key scheme (:mod:`gcrsky.inference.batches`): host arrays.

    A full batch is drawn with ``fold_in(key, b)`` and truncated to the draws that
    exist (the last batch), exactly as :func:`gcrsky.inference.draw_batches` does.

    Returns:
        ``(draws (Nf, take, n), SolveInfo over (Nf, take))``, ``take = min(batch, nsamples - b * batch)``.
    """
    d, info = draw(batch_key(key, b), prepared, batch)
    d = np.asarray(jax.block_until_ready(d))
    take = min(batch, nsamples - b * batch)
    return d[:, :take], jax.tree_util.tree_map(lambda a: np.asarray(a)[:, :take], info.draws)


class MapSummary(NamedTuple):
    """Maps (Nf, Npix) and the paper's metrics of one run (:func:`map_summary`).

    ``truth_maps`` and ``mode_z`` are None for a problem without a truth;
    ``centre_dec_deg`` / ``ra_range_deg`` None without a configuration.
    """

    truth_maps: np.ndarray | None
    mean_maps: np.ndarray
    std_maps: np.ndarray
    mode_z: np.ndarray | None
    per_freq: list
    centre_dec_deg: float | None
    ra_range_deg: tuple | None
    wiener_maps: np.ndarray | None = None


def map_summary(prob, draws: np.ndarray, a_wf: np.ndarray, *, maps: dict | None = None) -> MapSummary:
    """Truth, posterior mean, std and Wiener maps and the beam-region metrics at every frequency.

    The beam centre is the site latitude, the observed RA range ``15 x`` the LST range
    and the FWHM that of the configuration's beam (:func:`gcrsky.sim.beam_for_config`);
    see :func:`gcrsky.paper.metrics.summary_metrics`.  Non-finite draws give NaN mean
    and std maps.  Without a truth (``prob.a_true`` None) the metrics are left out;
    without a configuration (``prob.config`` None) so are the beam and region.
    ``maps``: the ``{"truth", "mean", "std", "wiener"}`` maps of these draws when
    already at hand (a finished ``results.h5``'s ``maps`` group), not recomputed.
    """
    cfg = prob.config
    lmax, nside = prob.lmax, prob.nside
    freqs = np.asarray(prob.freqs_hz)
    truth = None if prob.a_true is None else np.asarray(prob.a_true)
    maps = maps or {}
    truth_maps = None if truth is None else maps.get("truth")
    if truth is not None and truth_maps is None:
        truth_maps = alm_to_map(truth, lmax, nside)
    wf_maps = maps["wiener"] if "wiener" in maps else alm_to_map(a_wf, lmax, nside)
    if "mean" in maps and "std" in maps:
        mean_maps, std_maps = maps["mean"], maps["std"]
    elif bool(np.isfinite(draws).all()):
        mean_maps, std_maps = posterior_maps(draws, lmax, nside)
    else:
        mean_maps = std_maps = np.full_like(wf_maps, np.nan)
    z = None if truth is None else M.mode_z_scores(draws, truth)  # (Nf, n)
    centre_dec = ra_range = None
    if cfg is not None:
        centre_dec = float(cfg.latitude_deg)
        ra_range = (15.0 * cfg.lst_range_hours[0], 15.0 * cfg.lst_range_hours[1])
    per_freq = []
    for f in range(freqs.size):
        m = {"freq_hz": float(freqs[f])}
        if cfg is not None:
            m["fwhm_deg"] = fwhm = _fwhm_deg(cfg, f, float(freqs[f]))
            if bool(np.isfinite(std_maps[f]).all()):  # metrics that need no truth: where the data constrain the sky
                m.update(M.std_metrics(std_maps[f], centre_dec, fwhm, ra_range))
        if truth is not None and cfg is not None:
            m.update(M.summary_metrics(mean_maps[f], truth_maps[f], centre_dec, fwhm, ra_range, std_map=std_maps[f]))
            wfm = M.summary_metrics(wf_maps[f], truth_maps[f], centre_dec, fwhm, ra_range)
            m["wiener_frac_diff_centre_median"] = wfm["frac_diff_centre_median"]
            m["wiener_frac_diff_fwhm_median"] = wfm["frac_diff_fwhm_median"]
        if z is not None:
            m["mode_z"] = M.z_score_stats(z[f])
        per_freq.append(m)
    return MapSummary(truth_maps, mean_maps, std_maps, z, per_freq, centre_dec, ra_range, wf_maps)


def _fwhm_deg(cfg, f: int, freq_hz: float) -> float:
    """The beam FWHM (degrees) of channel ``f``: recorded by a data run's configuration, else the simulation's beam."""
    recorded = getattr(cfg, "fwhm_deg", None)
    if recorded is not None:
        return float(recorded[f])
    return float(np.rad2deg(beam_fwhm_rad(beam_for_config(cfg), freq_hz)))


def _atomic_figure(out: Path, key: str, plot: Callable[[Path], object], only_missing: bool) -> str:
    """Write figure ``FIGURE_FILES[key]`` through ``plot(path)`` atomically (unless present and ``only_missing``)."""
    name = FIGURE_FILES[key]
    target = out / name
    if not (only_missing and target.exists()):
        with atomic_path(target) as tmp:
            plot(tmp)
    return name


def run_figures(out: Path, prob, draws: np.ndarray, ms: MapSummary, *, scenario_name=None,
                only_missing: bool = False) -> dict:
    """The paper's per-run figures (first frequency): Figs. 3-7 as PNG files in ``out`` (each written atomically).

    Needs a truth and a configuration (``ms.truth_maps``, ``ms.centre_dec_deg``).

    Args:
        only_missing: keep figures already in ``out`` (a resumed run).

    Returns:
        ``{figure key: file name}`` (:data:`FIGURE_FILES`).
    """
    from . import figures as P

    if ms.truth_maps is None or ms.centre_dec_deg is None:
        raise ValueError("the per-run figures compare with a truth and need the configuration's region")
    out = Path(out)
    freqs = np.asarray(prob.freqs_hz)
    nsamples = draws.shape[1]
    modes = prob.modes
    f0 = ms.per_freq[0]
    truth = np.asarray(prob.a_true)
    truth_map, mean_map, std_map = ms.truth_maps[0], ms.mean_maps[0], ms.std_maps[0]
    centre_dec, ra_range = ms.centre_dec_deg, ms.ra_range_deg
    lab = (f"{scenario_name}: " if scenario_name else "") + f"{freqs[0] / 1e6:g} MHz, {nsamples} draws"
    fig = lambda key, plot: _atomic_figure(out, key, plot, only_missing)  # noqa: E731
    names = {}
    names["fig3"] = fig("fig3", lambda p: P.plot_alm_residuals(
        ms.mode_z[0], modes.ell, modes.m, modes.is_imag, p,
        title=f"(posterior mean $-$ truth) / posterior std per mode, {lab}",
    ))
    region = (centre_dec, f0["fwhm_deg"], ra_range)
    names["fig4"] = fig("fig4", lambda p: P.plot_sky_maps(
        truth_map, mean_map, std_map, p, region=region,
        title=f"{lab}; green: $\\pm$1 FWHM band over the observed LSTs",
    ))
    names["fig5"] = fig("fig5", lambda p: P.plot_beam_region(
        M.frac_diff_map(mean_map, truth_map), p,
        centre_dec_deg=centre_dec, fwhm_deg=f0["fwhm_deg"], ra_range_deg=ra_range,
        title=f"(posterior mean $-$ truth) / truth near the beam, {lab}\nmedian |frac|: "
        f"{f0['frac_diff_centre_median']:.2%} on the centre ring, {f0['frac_diff_fwhm_median']:.2%} within "
        f"$\\pm$1 FWHM (observed RA range)",
    ))
    absfrac = np.abs(M.frac_diff_map(mean_map, truth_map))
    ra_ring, vals = M.ring_slice(absfrac, prob.nside, centre_dec)
    names["fig6"] = fig("fig6", lambda p: P.plot_frac_slices(
        [(scenario_name or "this run", ra_ring, vals)], p, fwhm_deg=f0["fwhm_deg"],
        ra_range_deg=ra_range, dec_deg=centre_dec, title=f"|mean $-$ truth| / truth along the beam centre, {lab}",
    ))
    if nsamples >= 2:
        names["fig7_correlation"] = fig("fig7_correlation", lambda p: P.plot_correlation_matrix(
            draws[0], modes.ell, modes.m, modes.is_imag, p,
            title=f"posterior correlation (real parts), {lab}",
        ))
        names["fig7_corner"] = fig("fig7_corner", lambda p: P.plot_corner(
            draws[0], truth[0], modes.ell, modes.m, modes.is_imag, p, m_value=2,
            title=f"marginal posteriors / truth at m = 2, {lab}",
        ))
    return names


def data_figures(out: Path, prob, draws: np.ndarray, ms: MapSummary, *, only_missing: bool = False) -> dict:
    """The figures of a run without a truth (real data), first frequency: the posterior mean and std
    maps with the observed strip outlined (``fig4``) and the posterior correlation (``fig7_correlation``)."""
    from . import figures as P

    out = Path(out)
    freqs = np.asarray(prob.freqs_hz)
    f0 = ms.per_freq[0]
    lab = f"{freqs[0] / 1e6:g} MHz, {draws.shape[1]} draws"
    region = (ms.centre_dec_deg, f0["fwhm_deg"], ms.ra_range_deg)
    fig = lambda key, plot: _atomic_figure(out, key, plot, only_missing)  # noqa: E731
    names = {"fig4": fig("fig4", lambda p: P.plot_posterior_maps(
        ms.wiener_maps[0], ms.std_maps[0], p, region=region,
        title=f"{lab}; green: $\\pm$1 FWHM band over the observed LSTs",
    ))}
    if draws.shape[1] >= 2:
        modes = prob.modes
        names["fig7_correlation"] = fig("fig7_correlation", lambda p: P.plot_correlation_matrix(
            draws[0], modes.ell, modes.m, modes.is_imag, p, title=f"posterior correlation (real parts), {lab}"))
    return names


def write_products(
    out,
    *,
    wiener_filter,
    wiener_maps,
    std_maps,
    freqs_hz,
    lmax: int,
    frame: str,
    ndraws: int,
    method: str,
    seed: int | None = None,
    only_missing: bool = False,
) -> dict:
    """The standard products of a run (:data:`PRODUCT_FILES`), each written atomically into ``out``.

    - ``posterior_mean.fits``: the map of the Wiener filter (the exact posterior mean),
      HEALPix RING, one column per frequency (:func:`gcrsky.io.write_healpix_fits`);
    - ``posterior_std.fits``: the per-pixel standard deviation over the draws (ddof 1);
    - ``posterior_mean_alm.fits``: the Wiener filter as complex healpy-ordered alm, one
      HDU per frequency (:func:`gcrsky.io.write_alm_fits`);
    - ``posterior_mean.skyh5``: a pyradiosky ``SkyModel`` of the posterior-mean map,
      with the std map as ``stokes_error`` (:func:`gcrsky.io.write_skyh5`).

    All in kelvin, in the frame of the coefficients (``frame``: :func:`parameter_frame`).

    Args:
        out: output directory.
        wiener_filter: ``(Nf, n)`` realified posterior mean; wiener_maps, std_maps: ``(Nf, Npix)``.
        freqs_hz: ``(Nf,)``; lmax: maximum degree; frame: ``"icrs"`` or ``"idealised"``.
        ndraws, method, seed: recorded in the headers / history.
        only_missing: keep products already in ``out``.

    Returns:
        ``{product key: file name}`` of the files written now.
    """
    from .. import __version__

    out = Path(out)
    common = [("NDRAWS", int(ndraws), "posterior draws of the run"), ("METHOD", str(method), "GCR solver path"),
              ("ORIGIN", f"gcrsky {__version__}", "software")]
    if seed is not None:
        common.append(("SEED", int(seed), "seed of the draws"))
    mean_what = "posterior mean: the Wiener filter (exact)"
    writers = {
        "posterior_mean_fits": lambda p: write_healpix_fits(
            p, wiener_maps, freqs_hz, frame=frame, lmax=lmax, content=mean_what,
            extra_header=common + [("MEANTYPE", "WIENER", "exact posterior mean (not the draws' mean)")]),
        "posterior_std_fits": lambda p: write_healpix_fits(
            p, std_maps, freqs_hz, frame=frame, lmax=lmax, content="posterior std: per pixel over the draws (ddof 1)",
            extra_header=common + [("DDOF", 1, "std over draws: divisor NDRAWS - 1")]),
        "posterior_mean_alm": lambda p: write_alm_fits(
            p, wiener_filter, lmax, freqs_hz, frame=frame, content=mean_what,
            extra_header=common + [("MEANTYPE", "WIENER", "exact posterior mean (not the draws' mean)")]),
        "posterior_mean_skyh5": lambda p: write_skyh5(
            p, wiener_maps, freqs_hz, frame=frame, std_maps=std_maps,
            history=f"gcrsky {__version__}: posterior mean (the Wiener filter, exact) of a GCR run ({method}, "
            f"{ndraws} draws, lmax {lmax}); stokes_error: per-pixel posterior std over the draws (ddof 1)."),
    }
    written = {}
    for key, write in writers.items():
        path = out / PRODUCT_FILES[key]
        if only_missing and path.exists():
            continue
        write(path)
        written[key] = PRODUCT_FILES[key]
    return written


class RunProducts(dict):
    """In-memory products of one run that the suite reuses (first frequency): the
    truth / mean / std maps, per-mode z-scores, the draws and the mode table; and
    ``resumed_at_batch`` (None for a new run), ``written`` (the files written by
    this call) and ``already_complete`` (a resumed run that had nothing left to draw
    or finalise)."""


_METRICS_NOTE = (
    "metrics at the first frequency; |mean - truth|/|truth| of the posterior-mean map (sample mean of the "
    "draws) over the beam-centre ring (the HEALPix ring nearest dec = site latitude) and the +-1 FWHM band, "
    "both within RA = 15 x LST range; FWHM measured from the simulated beam's power pattern; "
    "per_frequency has every channel; the two top-level frac_diff_* keys repeat the first channel's"
)
_TIMINGS_NOTE = (
    "wall-clock seconds; 'wiener' and the first draw batch include JIT compilation; "
    "compile_s: XLA compilation in all stages (build included when the caller counted from before it), a "
    "program loaded from JAX's persistent compilation cache counting its loading time; cache_hits / "
    "cache_misses: programs loaded from / compiled despite that cache (both 0 when it is off; see 'compile'); "
    "the set-up (P, its Cholesky factor or CG preconditioner, the Wiener filter) is done once, in 'wiener'; "
    "a resumed run times only its own stages (draw_batches_s covers every batch)"
)
_COMPILE_NOTE = (
    "this run's JAX compilation (gcrsky.parallel.compile_stats): compile_s backend compilation or loading from "
    "the persistent cache (cache_dir; null: off), trace_s tracing, lower_s lowering to MLIR (seconds, inside the "
    "stages' wall-clock times); programs compiled or loaded, cache_hits loaded from the cache, cache_misses "
    "compiled with the cache on, cache_writes entries written"
)
_PRODUCTS_NOTE = (
    "posterior_mean.* are the Wiener filter (the exact posterior mean), not the draws' mean; posterior_std.fits "
    "(and the skyh5's stokes_error) is the per-pixel std over the draws (ddof 1); HEALPix RING, K, frame: "
    "'icrs' for real observing times, 'idealised' for the co-rotating frame of idealised LSTs (COORDSYS 'C')"
)


def _options_json(options) -> str:
    """The resolved options of a solver path as JSON (``results.h5``'s ``solver_options_json``)."""
    return json.dumps({"method": method_of(options), "fields": dataclasses.asdict(options)}, default=json_default)


def _options_from_json(text: str):
    """The options object :func:`_options_json` wrote."""
    d = json.loads(text)
    return type(options_for(d["method"]))(**d["fields"])


def _stored_maps(h5: Path) -> dict:
    """The ``maps`` group of a finished ``results.h5`` (empty if it has none)."""
    import h5py

    with h5py.File(h5, "r") as h:
        return {k: h["maps"][k][()] for k in h["maps"]} if "maps" in h else {}


def _kill_hook(complete: int) -> None:
    """The test hook of the module doc: SIGKILL this process once ``complete`` batches are in results.h5."""
    at = os.environ.get(_KILL_HOOK)
    if at is not None and at.strip() and int(at) == complete:
        os.kill(os.getpid(), getattr(signal, "SIGKILL", signal.SIGTERM))


def _results_attrs(prob, settings, *, seed, batch, method, options, tol, scenario_name, key_scheme) -> dict:
    """The attributes :func:`run_problem` records in a new ``results.h5``."""
    cfg = prob.config
    return {
        "config_json": json.dumps(cfg.to_dict() if cfg is not None else None, default=json_default),
        "sky_note": prob.sky_note,
        "gcrsky_version": versions()["gcrsky"],
        "seed": seed,
        "batch": batch,
        "method": method,
        "method_requested": settings["method"],
        "solver_options_json": _options_json(options),
        "tol": tol,
        "scenario": scenario_name or "",
        "key_scheme": key_scheme,
        "frame": parameter_frame(prob),
    }


def _channel_progress(progress, total: int):
    return None if progress is None else progress(total)


def _sample_by_channel(mode, key, system, nsamples, options, batch, update):
    """All channels of ``system`` by :data:`~gcrsky.parallel.channels.CHANNEL_KEY_SCHEME` (``mode``: how)."""
    kw = dict(options=options, batch=batch, progress=update)
    if mode == "loop":
        return sample_channels(key, system, nsamples, **kw)
    if mode == "devices":
        return sample_channels_sharded(key, system, nsamples, **kw)
    return distributed_channels(key, system, nsamples, sharded=len(jax.local_devices()) > 1, **kw)


def _worker_channels(prob, *, nsamples, seed, batch, method, tol, progress) -> None:
    """A ``jax.distributed`` process other than 0: its share of the channels, gathered to process 0."""
    system = prob.system()
    options = resolve_channel_path(system, method, tol=tol, ndraws=batch)
    update = _channel_progress(progress, prob.data.shape[0])
    _sample_by_channel("processes", jax.random.PRNGKey(seed), system, nsamples, options, batch, update)


def _channel_run(prob, h5, state, settings, st, *, key, nsamples, batch, method, tol, start, nbatch, mode,
                 scenario_name, progress) -> str:
    """``run_problem``'s set-up and draws with independent channels (``channels=mode``); returns the path.

    Every channel is prepared and drawn (:mod:`gcrsky.parallel.channels`), then ``results.h5``
    is created (or, resumed, checked) and the batches from ``start`` appended.  Starts the
    ``"draws"`` stage and leaves it running (the caller stops it).
    """
    system = prob.system()
    st.start("wiener")  # only the path here: the channels' set-up runs with their draws
    if state is None:
        options = resolve_channel_path(system, method, tol=tol, ndraws=batch)
    else:
        options = _options_from_json(state.attrs["solver_options_json"])
    st.stop()
    st.start("draws")
    if start >= nbatch:
        return str(state.attrs["method"])
    update = _channel_progress(progress, prob.data.shape[0])
    t0 = time.perf_counter()
    res = _sample_by_channel(mode, key, system, nsamples, options, batch, update)
    per_batch = (time.perf_counter() - t0) / nbatch
    chosen = method_of(options)
    if state is None:
        attrs = _results_attrs(prob, settings, seed=int(settings["seed"]), batch=batch, method=chosen,
                               options=options, tol=tol, scenario_name=scenario_name, key_scheme=CHANNEL_KEY_SCHEME)
        create_results_h5(h5, prob, res.a_wf, nsamples=nsamples, batch=batch, settings=settings,
                          wiener_info=res.wiener, rank=None, attrs=attrs)
    else:
        recorded = read_draws(h5).wiener_filter
        if not np.array_equal(recorded, res.a_wf, equal_nan=True):
            log.warning("the resumed channels' Wiener filter differs from the recorded one by up to %.3g K",
                        float(np.nanmax(np.abs(recorded - res.a_wf))))
    for b in range(start, nbatch):
        sl = slice(b * batch, min((b + 1) * batch, nsamples))
        info = jax.tree_util.tree_map(lambda a: np.asarray(a)[:, sl], res.info)
        complete = append_batch(h5, b, res.draws[:, sl], info, seconds=per_batch)
        _kill_hook(complete)
    return chosen


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
    existing: str = "refuse",
    extra_settings: dict | None = None,
    compile_since: CompileStats | None = None,
    channels: str | None = None,
    channel_progress=None,
) -> tuple[dict, RunProducts]:
    """Sample ``prob`` and write ``results.h5``, the products, figures and ``summary.json`` to ``out``.

    Args:
        prob: a :class:`~gcrsky.model.Problem`; with a truth and a
            :class:`~gcrsky.sim.Config` (from :func:`gcrsky.sim.problem_from_config`)
            the paper's metrics and figures are made too, without them only the draws,
            maps and products.
        out: output directory (created if needed).
        nsamples, seed, batch: the draws (key ``PRNGKey(seed)``, batches of ``batch``;
            :mod:`gcrsky.inference.batches`).
        method: exact path (``"auto"`` chooses); tol: CG tolerance, posterior sigma.
        plots: write the figures.
        build_s: seconds spent building ``prob`` (recorded).
        argv: the command line (recorded).
        scenario_name: the paper scenario, if any (recorded, and in figure titles).
        on_stage: called with ``(stage, "start" | "stop")`` around each stage.
        progress: wrapper of the batch iterable (e.g. a tqdm bar).
        existing: what to do if ``out`` holds a run's files (:func:`check_output`):
            ``"refuse"`` (raise :class:`RunExistsError`), ``"overwrite"`` (delete them
            first) or ``"resume"`` (continue that run: same settings and inputs, else
            :class:`ResumeError`; the recorded path is reused even if ``method`` is
            ``"auto"``; files already present are kept, missing ones written).
        extra_settings: further settings that identify the run (:func:`run_settings`).
        compile_since: the :func:`gcrsky.parallel.compile_stats` snapshot to count the
            run's compilation from (e.g. taken before building ``prob``); default: now.
        channels: None (default): one joint system, draws in batches as above.  Else the
            channels are solved independently (:mod:`gcrsky.parallel.channels`, key scheme
            :data:`~gcrsky.parallel.channels.CHANNEL_KEY_SCHEME`: other, equally exact
            draws than the joint run's): ``"loop"`` one at a time (memory of one
            channel), ``"devices"`` split over this process's devices, ``"processes"``
            split over the processes of ``jax.distributed`` (initialised by the caller;
            every process calls this function, only process 0 touches ``out``; the others
            return ``(None, None)``).  The set-up and draws of every channel run before
            ``results.h5`` is written (its batches are then appended at once), so a killed
            channel run resumes by recomputing the channels; the draws are the same.
        channel_progress: with ``channels``: a callable ``total -> update`` (e.g. a tqdm
            bar's ``update``), called once; ``update(1)`` after each channel.

    Returns:
        (the summary dict in ``summary.json``, :class:`RunProducts`).
    """
    compile0 = compile_stats() if compile_since is None else compile_since
    if channels not in (None, "loop", "devices", "processes"):
        raise ValueError(f"channels must be None, 'loop', 'devices' or 'processes', got {channels!r}")
    if channels == "processes" and jax.process_index() != 0:
        _worker_channels(prob, nsamples=nsamples, seed=seed, batch=batch, method=method, tol=tol,
                         progress=channel_progress)
        return None, None
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = prob.config
    n = prob.n
    if channels is not None:
        extra_settings = {**(extra_settings or {}), "channels": channels, "channel_key_scheme": CHANNEL_KEY_SCHEME}
    settings = run_settings(cfg, nsamples=nsamples, seed=seed, batch=batch, method=method, tol=tol,
                            scenario=scenario_name, extra=extra_settings)
    state = check_output(out, settings, existing)
    if existing == "overwrite":
        removed = remove_run_files(out)
        if removed:
            log.info("overwrite: removed %s from %s", ", ".join(removed), out)
    for p in _temporaries(out):  # left by a killed writer
        p.unlink(missing_ok=True)
    h5 = out / RESULTS_FILE
    if state is not None:
        if "solver_options_json" not in state.attrs:
            raise ResumeError(out, f"cannot resume: {h5} does not record its solver options (not written by "
                                   "run_problem)")
        fp = inputs_fingerprint(prob)
        if state.attrs.get("inputs_sha256") != fp:
            raise ResumeError(out, f"cannot resume the run in {out}: the problem's inputs (data, noise, prior, "
                                   "times or frequencies) differ bit for bit from those recorded, e.g. another "
                                   "sky model is on disk now, or another machine or software version")
        if state.attrs.get("gcrsky_version") != versions()["gcrsky"]:
            log.warning("resuming a run of gcrsky %s with gcrsky %s", state.attrs.get("gcrsky_version"),
                        versions()["gcrsky"])
    st = StageTimer(on_stage)
    st.times["build"] = build_s
    key = jax.random.PRNGKey(seed)
    nbatch = -(-int(nsamples) // int(batch))
    start = 0 if state is None else state.batches_complete
    already_complete = state is not None and state.draws_done and state.complete
    before = set(existing_run_files(out))
    finalized = False

    if channels is not None:  # set-up and draws of every channel; leaves the "draws" stage running
        method = _channel_run(prob, h5, state, settings, st, key=key, nsamples=nsamples, batch=batch,
                              method=method, tol=tol, start=start, nbatch=nbatch, mode=channels,
                              scenario_name=scenario_name, progress=channel_progress)
    else:
        st.start("wiener")  # set-up once: P, factor / preconditioner, Wiener filter (compile included)
        prepared = None
        if start < nbatch:
            if state is None:  # resolve "auto" here, so that the exact options can be recorded
                options = choose_path(prob.system(), method, tol=tol, ndraws=batch)
            else:  # a resumed run keeps the recorded path and its options (auto's CG is matrix-free, "cg"'s dense)
                options = _options_from_json(state.attrs["solver_options_json"])
            prepared = prepare(prob, options=options, ndraws=batch)
            method = prepared.method  # what "auto" chose
            a_wf, winfo = np.asarray(jax.block_until_ready(prepared.a_wf)), prepared.wiener
            if state is None:
                attrs = _results_attrs(prob, settings, seed=seed, batch=batch, method=method, options=options,
                                       tol=tol, scenario_name=scenario_name, key_scheme=KEY_SCHEME)
                create_results_h5(h5, prob, a_wf, nsamples=nsamples, batch=batch, settings=settings, wiener_info=winfo,
                                  rank=getattr(prepared, "rank", None), attrs=attrs)
            else:
                recorded = read_draws(h5).wiener_filter
                if not np.array_equal(recorded, a_wf, equal_nan=True):
                    log.warning("the resumed set-up's Wiener filter differs from the recorded one by up to %.3g K: the "
                                "remaining draws will not be bit-identical to an uninterrupted run's",
                                float(np.nanmax(np.abs(recorded - a_wf))))
        else:
            method = str(state.attrs["method"])
        st.stop()

        st.start("draws")
        batches = range(start, nbatch)
        for b in progress(batches) if progress is not None else batches:
            t0 = time.perf_counter()
            d, info = draw_batch(key, prepared, b, batch, nsamples)
            complete = append_batch(h5, b, d, info, seconds=time.perf_counter() - t0)
            _kill_hook(complete)
    stored = read_draws(h5)
    draws, a_wf = stored.draws, stored.wiener_filter
    st.stop()

    finite = bool(np.isfinite(draws).all())
    solver, warnings = solver_summary(method, tol, stored.wiener_info, stored.info, None, n, rank=stored.rank)
    if not finite:
        warnings.append(f"ERROR: {int((~np.isfinite(draws)).sum())} non-finite values in the draws.")

    st.start("maps")
    ms = map_summary(prob, draws, a_wf, maps=_stored_maps(h5) if already_complete else None)
    st.stop()

    fig_names = {}
    if plots:
        st.start("plots")
        if finite and ms.truth_maps is not None and ms.centre_dec_deg is not None:
            fig_names = run_figures(out, prob, draws, ms, scenario_name=scenario_name, only_missing=True)
        elif finite and ms.truth_maps is None and ms.centre_dec_deg is not None:
            fig_names = data_figures(out, prob, draws, ms, only_missing=True)
        elif ms.truth_maps is None:
            warnings.append("NOTE: no figures: this problem has neither a truth nor a region (configuration).")
        st.stop()

    st.start("write")
    write_products(out, wiener_filter=a_wf, wiener_maps=ms.wiener_maps, std_maps=ms.std_maps,
                   freqs_hz=np.asarray(prob.freqs_hz), lmax=prob.lmax, frame=parameter_frame(prob),
                   ndraws=draws.shape[1], method=method, seed=seed, only_missing=True)
    if not read_results_state(h5).complete:
        maps = {"truth": ms.truth_maps, "mean": ms.mean_maps, "std": ms.std_maps, "wiener": ms.wiener_maps}
        finalize_results_h5(h5, mode_z=ms.mode_z, maps=maps)
        finalized = True
    st.stop()

    timings = dict(st.times)
    timings["total"] = float(sum(v for v in st.times.values()))
    timings["draw_batches_s"] = stored.batch_seconds
    compiled = compile_stats().since(compile0)
    timings["compile_s"] = compiled.compile_s
    timings["cache_hits"] = compiled.cache_hits
    timings["cache_misses"] = compiled.cache_misses
    timings["note"] = _TIMINGS_NOTE
    cache_dir = compile_cache_dir()
    per_freq = ms.per_freq
    f0 = per_freq[0]
    summary = {
        "frac_diff_centre_median": f0.get("frac_diff_centre_median"),
        "frac_diff_fwhm_median": f0.get("frac_diff_fwhm_median"),
        "metrics": dict(f0),
        "metrics_note": _METRICS_NOTE,
        "per_frequency": per_freq,
        "region": None if ms.centre_dec_deg is None else {
            "centre_dec_deg": ms.centre_dec_deg, "ra_range_deg": list(ms.ra_range_deg),
            "fwhm_deg": [m["fwhm_deg"] for m in per_freq]},
        "solver": solver,
        "draws_finite": finite,
        "warnings": warnings,
        "timings_s": timings,
        "compile": {**compiled._asdict(), "cache_dir": None if cache_dir is None else str(cache_dir),
                    "note": _COMPILE_NOTE},
        "run": {"nsamples": nsamples, "seed": seed, "batch": batch, "method": method, "scenario": scenario_name,
                "argv": argv, "resumed_at_batch": None if state is None else start, "frame": parameter_frame(prob)},
        "figures": fig_names,
        "products": {**PRODUCT_FILES, "results": RESULTS_FILE},
        "products_note": _PRODUCTS_NOTE,
        "config": cfg.to_dict() if cfg is not None else None,
        "sky_note": prob.sky_note,
        "versions": versions(),
        "exit_status": 0 if finite else 1,
    }
    if (out / SUMMARY_FILE).exists():  # a resumed run keeps the summary its run wrote
        summary = json.loads((out / SUMMARY_FILE).read_text())
    else:
        write_json(out / SUMMARY_FILE, summary)
    written = [f for f in existing_run_files(out) if f not in before or (f == RESULTS_FILE and finalized)]
    products = RunProducts(
        truth_map=None if ms.truth_maps is None else ms.truth_maps[0], mean_map=ms.mean_maps[0],
        std_map=ms.std_maps[0], z=None if ms.mode_z is None else ms.mode_z[0], draws=draws[0],
        truth=None if prob.a_true is None else np.asarray(prob.a_true)[0], modes=prob.modes,
        fwhm_deg=f0.get("fwhm_deg"), centre_dec_deg=ms.centre_dec_deg, ra_range_deg=ms.ra_range_deg,
        resumed_at_batch=None if state is None else start, written=written, already_complete=already_complete,
    )
    return summary, products
