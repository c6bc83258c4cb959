"""The ``gcrsky`` command line (also ``python -m gcrsky``).

``gcrsky run`` reproduces the paper's standard case (or a scenario of its Table 1,
``--scenario NAME``, or a variant through options mirroring :class:`gcrsky.Config`):
simulate, Wiener-filter, draw GCR samples, and write ``results.h5``,
``summary.json`` and the paper's per-run figures (Figs. 3-7: mode z-scores, sky
maps, beam region, beam-centre slice, correlation matrix and corner plot).

``gcrsky scenarios [NAME ...]`` runs the whole suite (or a subset) into
``--out/NAME/``, reusing the response between scenarios with the same
instrument, and writes ``results.md`` / ``results.csv`` (one row per scenario),
``claims.md`` (the paper's qualitative claims, checked with these numbers),
``suite.json`` and the overlaid slice figures (Figs. 6 and 8).

Reproducibility: the simulated data and the prior mean depend on ``--data-seed``
(``Config.seed``); the draws on ``--seed`` and ``--batch``.  Draws are made in
batches of ``--batch``; batch ``b`` uses the key
``jax.random.fold_in(jax.random.PRNGKey(seed), b)`` and always draws a *full*
batch (the last one is truncated to ``--nsamples``).  So with the same seed and
batch size, draw ``i`` is the same whatever ``--nsamples`` is (``--nsamples 20``
gives the first 20 draws of ``--nsamples 200``), and one compiled program serves
every batch.  Changing ``--batch`` changes the draws (not their distribution).

Exit status: 0 on success, also when some solves did not converge (a warning is
printed and ``summary.json`` records it: check ``solver.all_converged``); 1 if the
draws contain non-finite values (results are still written for diagnosis); 2 for
bad arguments (argparse).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import sys
import time
from pathlib import Path

__all__ = ["main", "build_parser"]

log = logging.getLogger("gcrsky.cli")

DEFAULT_OUT = os.path.join("runs", "standard")
DEFAULT_SUITE_OUT = os.path.join("runs", "paper")
DEFAULT_NSAMPLES = 200
DEFAULT_BATCH = 50


# ---------------------------------------------------------------- argument types


def _int_at_least(lo: int, what: str):
    def conv(s: str) -> int:
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be an integer, got {s!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"{what} must be >= {lo}, got {v}")
        return v

    return conv


def _positive_float(what: str):
    def conv(s: str) -> float:
        try:
            v = float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number, got {s!r}") from None
        if not (v > 0 and math.isfinite(v)):
            raise argparse.ArgumentTypeError(f"{what} must be a positive finite number, got {s!r}")
        return v

    return conv


def _finite_float(what: str):
    def conv(s: str) -> float:
        try:
            v = float(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number, got {s!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"{what} must be finite, got {s!r}")
        return v

    return conv


def _nside(s: str) -> int:
    v = _int_at_least(1, "nside")(s)
    if v & (v - 1):
        raise argparse.ArgumentTypeError(f"nside must be a power of 2, got {v}")
    return v


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (defaults of the physics options come from :class:`gcrsky.Config`)."""
    from .problem import Config

    d = Config()
    p = argparse.ArgumentParser(
        prog="gcrsky",
        description="Full-sky maps with honest uncertainties: Gaussian constrained realisations "
        "of spherical-harmonic skies from drift-scan visibilities (Glasscock et al. 2024).",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    r = sub.add_parser(
        "run",
        help="simulate the paper's standard case (or a variant), sample the posterior, write results",
        description="Simulate the standard case (options override its configuration), compute the "
        "Wiener filter, draw GCR samples and write results.h5, summary.json and figures to --out.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    r.add_argument("--scenario", default=None, metavar="NAME",
                   help="start from a scenario of the paper's Table 1 (standard, A1, B1-B8, C1-C5, D1; see "
                   "'gcrsky scenarios --list'); other options change it further, unless they contradict it")
    r.add_argument("--out", default=DEFAULT_OUT, help="output directory (created if needed)")
    r.add_argument("--nsamples", type=_int_at_least(1, "nsamples"), default=None,
                   help=f"number of posterior draws (default {DEFAULT_NSAMPLES}, or the scenario's)")
    r.add_argument("--seed", type=_int_at_least(0, "seed"), default=0,
                   help="seed of the posterior draws (see --batch)")
    r.add_argument("--data-seed", type=_int_at_least(0, "data-seed"), default=d.seed,
                   help="seed of the simulated noise and prior mean (Config.seed)")
    r.add_argument("--lmax", type=_int_at_least(1, "lmax"), default=d.lmax, help="maximum degree l")
    r.add_argument("--nside", type=_nside, default=d.nside, help="HEALPix nside of the response quadrature and maps")
    r.add_argument("--lst-start", type=_finite_float("lst-start"), default=d.lst_range_hours[0],
                   help="first LST (sidereal hours)")
    r.add_argument("--lst-stop", type=_finite_float("lst-stop"), default=d.lst_range_hours[1],
                   help="last LST (sidereal hours, >= --lst-start; to wrap through 0 h use e.g. 22 to 26)")
    r.add_argument("--n-lst", type=_int_at_least(1, "n-lst"), default=d.n_lst,
                   help="number of LSTs, evenly spaced from start to stop inclusive")
    r.add_argument("--dish-diameter", type=_positive_float("dish-diameter"), default=d.dish_diameter,
                   help="dish diameter in metres (Gaussian beam, Airy-matched FWHM)")
    r.add_argument("--noise-scale", type=_positive_float("noise-scale"), default=d.noise_scale,
                   help="factor on the noise variance")
    r.add_argument("--prior-scale", type=_positive_float("prior-scale"), default=d.prior_scale,
                   help="factor on the prior variance")
    r.add_argument("--flat-prior", action="store_true", default=d.flat_prior,
                   help="no prior (S^-1 = 0; the posterior may be improper)")
    r.add_argument("--zero-prior-mean", action="store_true", default=d.zero_prior_mean,
                   help="prior mean a0 = 0 instead of a draw around the truth")
    r.add_argument("--date", default=d.obs_date, metavar="YYYY-MM-DD",
                   help="observe on this UTC date at the real times whose local Earth rotation angle is each "
                   "LST (sky in ICRS, exact ICRS -> CIRS-of-date frame map); default: the paper's idealised LSTs")
    r.add_argument("--method", choices=("auto", "cg", "cholesky", "eigh", "mmode"), default=None,
                   help="GCR solver (default auto: m-mode for uniform full-day coverage, else dense Cholesky "
                   "where P fits, else matrix-free CG; or the scenario's: eigh where S^-1 = 0 makes P singular)")
    r.add_argument("--tol", type=_positive_float("tol"), default=None,
                   help="CG tolerance in posterior-sigma units (default 1e-6, or the scenario's)")
    r.add_argument("--batch", type=_int_at_least(1, "batch"), default=DEFAULT_BATCH,
                   help="draws per batch (part of the draws' seed: see the module doc)")
    r.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    r.add_argument("--no-progress", action="store_true", help="no progress bars")
    r.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")

    sc = sub.add_parser(
        "scenarios",
        help="run the paper's scenario suite (Table 1) and write the results table and figures",
        description="Run the named scenarios (default: all 16 of the paper's Table 1) into --out/NAME/, "
        "reusing the response wherever the instrument is shared, then write results.md, results.csv, "
        "claims.md and the cross-run figures (Figs. 6-8) to --out.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    sc.add_argument("names", nargs="*", metavar="NAME", help="scenarios to run (default: all)")
    sc.add_argument("--list", action="store_true", help="list the scenarios and exit")
    sc.add_argument("--out", default=DEFAULT_SUITE_OUT, help="output directory")
    sc.add_argument("--nsamples", type=_int_at_least(1, "nsamples"), default=None,
                    help="draws per scenario (default: 200, 5000 for A1)")
    sc.add_argument("--nside", type=_nside, default=d.nside, help="HEALPix nside (quick runs: 32)")
    sc.add_argument("--seed", type=_int_at_least(0, "seed"), default=0, help="seed of the posterior draws")
    sc.add_argument("--batch", type=_int_at_least(1, "batch"), default=DEFAULT_BATCH, help="draws per batch")
    sc.add_argument("--no-plots", action="store_true", help="skip all PNG figures")
    sc.add_argument("--no-progress", action="store_true", help="no progress bars")
    sc.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    return p


# ---------------------------------------------------------------- helpers


def _stats(info) -> dict:
    import numpy as np

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


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


def _clean_json(x):
    """Replace non-finite floats by None so summary.json is strict JSON."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean_json(v) for v in x]
    return x


def _versions() -> dict:
    import h5py
    import healpy
    import jax
    import matplotlib
    import numpy

    from . import __version__

    return {
        "gcrsky": __version__,
        "jax": jax.__version__,
        "jaxlib": getattr(getattr(jax, "lib", None), "__version__", None) or _pkg_version("jaxlib"),
        "numpy": numpy.__version__,
        "healpy": healpy.__version__,
        "h5py": h5py.__version__,
        "matplotlib": matplotlib.__version__,
        "python": platform.python_version(),
        "jax_backend": jax.default_backend(),
    }


def _pkg_version(name: str):
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:  # noqa: BLE001
        return None


class _Stages:
    """Wall-clock timer of named stages with an optional tqdm bar over them."""

    def __init__(self, names, disable):
        from tqdm.auto import tqdm

        self.bar = tqdm(total=len(names), desc="gcrsky", unit="stage", disable=disable, leave=False, position=0,
                        bar_format="{desc}: {n_fmt}/{total_fmt} stages |{bar}| {elapsed}")
        self.times: dict[str, float] = {}
        self._t0 = None
        self._name = None

    def start(self, name: str):
        self._name, self._t0 = name, time.perf_counter()
        self.bar.set_description(f"gcrsky: {name}")
        log.info("stage %s ...", name)

    def stop(self):
        dt = time.perf_counter() - self._t0
        self.times[self._name] = dt
        log.info("stage %s done in %.2f s", self._name, dt)
        self.bar.update(1)

    def close(self):
        self.bar.close()


# ---------------------------------------------------------------- the run command


def _setup_jax():
    from .runtime import use_safe_cpu_threading

    use_safe_cpu_threading()  # before the first JAX computation (see gcrsky/runtime.py)
    import jax

    jax.config.update("jax_enable_x64", True)


#: ``gcrsky run`` options that map to :class:`gcrsky.Config` fields.
_PHYSICS = ("lmax", "nside", "n_lst", "lst_range_hours", "dish_diameter", "noise_scale", "prior_scale",
            "flat_prior", "zero_prior_mean", "seed", "obs_date")


def _run_settings(args):
    """(Config fields, nsamples, method, scenario name or None, tol) from ``gcrsky run`` arguments.

    With ``--scenario``, options left at the standard case's value keep the scenario's
    setting; an option that changes a field the scenario also sets, to another value,
    is an error.
    """
    from .problem import Config
    from .scenarios import scenario

    fields = dict(
        lmax=args.lmax, nside=args.nside, n_lst=args.n_lst, lst_range_hours=(args.lst_start, args.lst_stop),
        dish_diameter=args.dish_diameter, noise_scale=args.noise_scale, prior_scale=args.prior_scale,
        flat_prior=args.flat_prior, zero_prior_mean=args.zero_prior_mean, seed=args.data_seed, obs_date=args.date,
    )
    if args.scenario is None:
        return fields, args.nsamples or DEFAULT_NSAMPLES, args.method or "auto", None, args.tol or 1e-6
    sc = scenario(args.scenario)
    d = Config()
    user = {k: v for k, v in fields.items() if v != getattr(d, k)}
    mine = dict(sc.overrides)
    clash = sorted(k for k in user if k in mine and user[k] != mine[k])
    if clash:
        raise ValueError(
            f"scenario {sc.name} sets {', '.join(f'{k}={mine[k]!r}' for k in clash)}; the options ask for "
            f"{', '.join(f'{k}={user[k]!r}' for k in clash)} (drop --scenario to customise freely)"
        )
    return {**mine, **user}, args.nsamples or sc.nsamples, args.method or sc.method, sc.name, args.tol or sc.tol


def _run(args) -> int:
    _setup_jax()
    from .problem import Config, problem_from_config

    fields, nsamples, method, scen, tol = _run_settings(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    disable_bars = True if args.no_progress else None  # tqdm's None: bars only on a terminal
    t0 = time.perf_counter()
    prob = problem_from_config(Config(**fields).validate())
    build_s = time.perf_counter() - t0
    summary, _ = _execute(
        prob, out, nsamples=nsamples, seed=args.seed, batch=args.batch, method=method, plots=not args.no_plots,
        disable_bars=disable_bars, build_s=build_s, argv=getattr(args, "_argv", None), scenario_name=scen, tol=tol,
    )
    _print_summary(summary, out)
    for w in summary["warnings"]:
        print(w, file=sys.stderr)
    if not summary["draws_finite"]:
        print("gcrsky: the draws contain NaN/inf; exiting with status 1 (results written for diagnosis).",
              file=sys.stderr)
        return 1
    return 0


class RunProducts(dict):
    """In-memory products of one run that the suite reuses (first frequency): the
    truth / mean / std maps, per-mode z-scores, the draws and the mode table."""


def _execute(prob, out: Path, *, nsamples: int, seed: int, batch: int, method: str, plots: bool,
             disable_bars, build_s: float, argv=None, scenario_name=None, tol: float = 1e-6):
    """Sample ``prob`` and write results.h5, summary.json and figures to ``out``.

    Returns (summary dict, :class:`RunProducts`).
    """
    import jax
    import numpy as np
    from tqdm.auto import tqdm

    import h5py

    from . import maps as M
    from .api import prepare
    from .instrument import beam_fwhm_rad
    from .layout import alm_to_map
    from .problem import Config, beam_for_config
    from .sampler import draw

    stage_names = ["wiener", "draws", "maps"] + (["plots"] if plots else []) + ["write"]
    st = _Stages(stage_names, disable_bars)
    st.times["build"] = build_s
    warnings: list[str] = []
    cfg: Config = prob.config
    lmax, nside = prob.lmax, prob.nside
    freqs = np.asarray(prob.freqs_hz)
    nf, n = np.asarray(prob.prior.mean).shape

    # ---- Wiener filter (compile included)
    st.start("wiener")
    prepared = prepare(prob, method=method, tol=tol, ndraws=batch)  # P, factor/preconditioner, Wiener filter: once
    method = prepared.method  # what "auto" chose
    a_wf, winfo = np.asarray(jax.block_until_ready(prepared.a_wf)), prepared.wiener
    st.stop()

    # ---- draws, in full batches keyed by fold_in(seed key, batch index)
    st.start("draws")
    key = jax.random.PRNGKey(seed)
    nbatch = -(-nsamples // batch)
    chunks, dinfos, batch_times = [], [], []
    for b in tqdm(range(nbatch), desc="draw batches", unit="batch", disable=disable_bars, leave=False, position=1):
        tb = time.perf_counter()
        d, info = draw(jax.random.fold_in(key, b), prepared, batch, tol=tol)
        d = np.asarray(jax.block_until_ready(d))
        take = min(batch, nsamples - b * batch)
        chunks.append(d[:, :take])
        dinfos.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:, :take], info["draws"]))
        batch_times.append(time.perf_counter() - tb)
    draws = np.concatenate(chunks, axis=1)  # (Nf, nsamples, n)
    dinfo = jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *dinfos)
    st.stop()

    finite = bool(np.isfinite(draws).all())
    solver = {"method": method, "tol_sigma": tol, "wiener": _stats(winfo), "draws": _stats(dinfo)}
    if prepared.rank is not None:
        rank = [int(r) for r in np.asarray(prepared.rank)]
        solver["rank"] = rank
        if min(rank) < n:
            warnings.append(
                f"NOTE: P is singular (improper posterior, e.g. S^-1 = 0): {n - min(rank)} of {n} directions carry "
                f"no information and are pinned at 0; draws and the mean cover the {min(rank)} the data inform."
            )
    solver["all_converged"] = solver["wiener"]["all_converged"] and solver["draws"]["all_converged"]
    if not solver["all_converged"]:
        msg = (
            f"WARNING: {solver['wiener']['n_not_converged']} Wiener-filter and "
            f"{solver['draws']['n_not_converged']} draw solves did not converge "
            f"(worst error {max(solver['wiener']['err_sigma_max'], solver['draws']['err_sigma_max']):.3g} "
            "posterior sigma); results are written but may be inaccurate (exit status stays 0)."
        )
        warnings.append(msg)
    if not finite:
        warnings.append(f"ERROR: {int((~np.isfinite(draws)).sum())} non-finite values in the draws.")

    # ---- maps and metrics
    st.start("maps")
    truth = np.asarray(prob.a_true)
    truth_maps = alm_to_map(truth, lmax, nside)
    wf_maps = alm_to_map(a_wf, lmax, nside)
    if finite:
        mean_maps, std_maps = M.posterior_maps(draws, lmax, nside)
    else:
        mean_maps = std_maps = np.full_like(truth_maps, np.nan)
    z = M.mode_z_scores(draws, truth)  # (Nf, n)
    centre_dec = float(cfg.latitude_deg)
    ra_range = (15.0 * cfg.lst_range_hours[0], 15.0 * cfg.lst_range_hours[1])
    per_freq = []
    for f in range(nf):
        fwhm = float(np.rad2deg(beam_fwhm_rad(beam_for_config(cfg), float(freqs[f]))))
        m = {"freq_hz": float(freqs[f]), "fwhm_deg": fwhm}
        m.update(M.summary_metrics(mean_maps[f], truth_maps[f], centre_dec, fwhm, ra_range, std_map=std_maps[f]))
        wfm = M.summary_metrics(wf_maps[f], truth_maps[f], centre_dec, fwhm, ra_range)
        m["wiener_frac_diff_centre_median"] = wfm["frac_diff_centre_median"]
        m["wiener_frac_diff_fwhm_median"] = wfm["frac_diff_fwhm_median"]
        m["mode_z"] = M.z_score_stats(z[f])
        per_freq.append(m)
    st.stop()

    # ---- plots (first frequency, as in the paper)
    fig_paths = {}
    if plots:
        st.start("plots")
        if finite:
            from . import plots as P

            modes = prob.modes
            f0 = per_freq[0]
            lab = (f"{scenario_name}: " if scenario_name else "") + f"{freqs[0] / 1e6:g} MHz, {nsamples} draws"
            fig_paths["fig3"] = P.plot_alm_residuals(
                z[0], modes.ell, modes.m, modes.is_imag, out / "fig3_alm_residuals.png",
                title=f"(posterior mean $-$ truth) / posterior std per mode, {lab}",
            )
            region = (centre_dec, f0["fwhm_deg"], ra_range)
            fig_paths["fig4"] = P.plot_sky_maps(
                truth_maps[0], mean_maps[0], std_maps[0], out / "fig4_sky_maps.png", region=region,
                title=f"{lab}; green: $\\pm$1 FWHM band over the observed LSTs",
            )
            fig_paths["fig5"] = P.plot_beam_region(
                M.frac_diff_map(mean_maps[0], truth_maps[0]), out / "fig5_beam_region.png",
                centre_dec_deg=centre_dec, fwhm_deg=f0["fwhm_deg"], ra_range_deg=ra_range,
                title=f"(posterior mean $-$ truth) / truth near the beam, {lab}\nmedian |frac|: "
                f"{f0['frac_diff_centre_median']:.2%} on the centre ring, {f0['frac_diff_fwhm_median']:.2%} within "
                f"$\\pm$1 FWHM (observed RA range)",
            )
            absfrac = np.abs(M.frac_diff_map(mean_maps[0], truth_maps[0]))
            ra_ring, vals = M.ring_slice(absfrac, nside, centre_dec)
            fig_paths["fig6"] = P.plot_frac_slices(
                [(scenario_name or "this run", ra_ring, vals)], out / "fig6_slice.png", fwhm_deg=f0["fwhm_deg"],
                ra_range_deg=ra_range, dec_deg=centre_dec, title=f"|mean $-$ truth| / truth along the beam centre, {lab}",
            )
            if nsamples >= 2:
                fig_paths["fig7_correlation"] = P.plot_correlation_matrix(
                    draws[0], modes.ell, modes.m, modes.is_imag, out / "fig7_correlation.png",
                    title=f"posterior correlation (real parts), {lab}",
                )
                fig_paths["fig7_corner"] = P.plot_corner(
                    draws[0], truth[0], modes.ell, modes.m, modes.is_imag, out / "fig7_corner.png", m_value=2,
                    title=f"marginal posteriors / truth at m = 2, {lab}",
                )
            fig_paths = {k: os.path.basename(v) for k, v in fig_paths.items()}
        st.stop()

    # ---- write
    st.start("write")
    cfg_json = json.dumps(cfg.to_dict(), default=_json_default)
    with h5py.File(out / "results.h5", "w") as h:
        h.attrs["config_json"] = cfg_json
        h.attrs["sky_note"] = prob.sky_note
        h.attrs["gcrsky_version"] = _versions()["gcrsky"]
        h.attrs["seed"] = seed
        h.attrs["batch"] = batch
        h.attrs["method"] = method
        h.attrs["scenario"] = scenario_name or ""
        h.attrs["key_scheme"] = "batch b: jax.random.fold_in(jax.random.PRNGKey(seed), b); full batches, last truncated"
        h.attrs["units"] = "coefficients and maps in K; data in K sr; freqs Hz; lsts rad"
        h.attrs["layout"] = "realified: [Re a_lm (l, m>=0) healpy order] ++ [Im a_lm (m>=1) healpy order]"
        ds = h.create_dataset("draws", data=draws)
        ds.attrs["shape"] = "(nfreq, ndraws, nparams)"
        h["truth"] = truth
        h["wiener_filter"] = a_wf
        h["prior_mean"] = np.asarray(prob.prior.mean)
        h["prior_inv_var"] = np.asarray(prob.prior.inv_var)
        modes = prob.modes
        h["modes/ell"] = modes.ell
        h["modes/m"] = modes.m
        h["modes/is_imag"] = modes.is_imag
        h["freqs_hz"] = freqs
        h["lsts_rad"] = np.asarray(prob.lsts_rad)
        h["antpairs"] = np.asarray(prob.antpairs)
        h["data"] = np.asarray(prob.data)
        h["sigma"] = np.asarray(prob.sigma)
        h["mode_z"] = z
        g = h.create_group("maps")
        g.attrs["note"] = "HEALPix RING, equatorial, K; mean/std over the draws"
        for name, arr in (("truth", truth_maps), ("mean", mean_maps), ("std", std_maps)):
            g.create_dataset(name, data=arr.astype(np.float32), compression="gzip", compression_opts=4)
    st.stop()
    st.close()

    timings = dict(st.times)
    timings["total"] = float(sum(v for v in st.times.values()))
    timings["draw_batches_s"] = batch_times
    timings["note"] = (
        "wall-clock seconds; 'wiener' and the first draw batch include JIT compilation; "
        "the set-up (P, its Cholesky factor or CG preconditioner, the Wiener filter) is done once, in 'wiener'"
    )
    summary = {
        "frac_diff_centre_median": per_freq[0]["frac_diff_centre_median"],
        "frac_diff_fwhm_median": per_freq[0]["frac_diff_fwhm_median"],
        "metrics": dict(per_freq[0]),
        "metrics_note": (
            "metrics at the first frequency; |mean - truth|/|truth| of the posterior-mean map (sample mean of the "
            "draws) over the beam-centre ring (the HEALPix ring nearest dec = site latitude) and the +-1 FWHM band, "
            "both within RA = 15 x LST range; FWHM measured from the simulated beam's power pattern; "
            "per_frequency has every channel; the two top-level frac_diff_* keys repeat the first channel's"
        ),
        "per_frequency": per_freq,
        "region": {"centre_dec_deg": centre_dec, "ra_range_deg": list(ra_range),
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
        "versions": _versions(),
        "exit_status": 0 if finite else 1,
    }
    with open(out / "summary.json", "w") as fh:
        json.dump(_clean_json(summary), fh, indent=2, default=_json_default)
    products = RunProducts(
        truth_map=truth_maps[0], mean_map=mean_maps[0], std_map=std_maps[0], z=z[0], draws=draws[0],
        truth=truth[0], modes=prob.modes, fwhm_deg=per_freq[0]["fwhm_deg"], centre_dec_deg=centre_dec,
        ra_range_deg=ra_range,
    )
    return summary, products


#: Groups of runs overlaid in the slice figures (the paper's Figs. 6 and 8).
_SLICE_GROUPS = (
    ("A", "fig6_slices_A1.png", ("standard", "A1")),
    ("B", "fig6_slices_B.png", ("standard", "B1", "B2", "B3", "B4", "B5", "B6", "B7", "B8")),
    ("C", "fig8_slices_C.png", ("standard", "C1", "C2", "C3", "C4", "C5")),
    ("D", "fig8_slices_D1.png", ("standard", "D1")),
)


def _scenarios(args) -> int:
    from .scenarios import (
        SCENARIOS,
        claims_markdown,
        evaluate_claims,
        result_row,
        results_csv,
        results_markdown,
        scenario,
        scenario_config,
    )

    if args.list:
        for sc in SCENARIOS.values():
            extra = ", ".join(f"{k}={v}" for k, v in sc.overrides) or "-"
            print(f"{sc.name:9s} {sc.varies:28s} draws {sc.nsamples:5d}  method {sc.method:5s}  Config: {extra}")
        return 0
    names = _suite_names(args)
    _setup_jax()
    from tqdm.auto import tqdm

    from . import maps as M
    from .problem import problem_from_config

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    disable_bars = True if args.no_progress else None
    cache: dict = {}
    rows, prods = {}, {}
    t_suite = time.perf_counter()
    bar = tqdm(names, desc="scenarios", unit="run", disable=disable_bars, leave=False)
    for name in bar:
        bar.set_description(f"scenario {name}")
        sc = scenario(name)
        t0 = time.perf_counter()
        prob = problem_from_config(scenario_config(name, nside=args.nside), response_cache=cache)
        build_s = time.perf_counter() - t0
        nsamples = args.nsamples or sc.nsamples
        summary, prod = _execute(
            prob, out / name, nsamples=nsamples, seed=args.seed, batch=args.batch, method=sc.method,
            plots=not args.no_plots, disable_bars=True, build_s=build_s, argv=getattr(args, "_argv", None),
            scenario_name=name, tol=sc.tol,
        )
        row = result_row(name, summary, prod["z"])
        reg = M.summary_metrics(prod["mean_map"], prod["truth_map"], prod["centre_dec_deg"], prod["fwhm_deg"],
                                (0.0, 120.0))
        row["fwhm_median_0_8h"] = reg["frac_diff_fwhm_median"]
        rows[name] = row
        prod.pop("draws")  # keep the suite's memory small
        prods[name] = prod
        tqdm.write(
            f"{name:9s} centre {100 * row['centre_median']:7.2f}%  +-1 FWHM {100 * row['fwhm_median']:7.2f}%  "
            f"sky<10% {100 * row['sky_within_10pct']:5.1f}%  |z|>15: {row['z_beyond_15']:3d}  "
            f"{row['wall_s']:6.1f} s" + ("" if summary["solver"]["all_converged"] else "  (NOT CONVERGED)")
        )
    bar.close()
    total = time.perf_counter() - t_suite
    table = [rows[n] for n in names]
    claims = evaluate_claims(rows)
    head = (
        f"# gcrsky scenario suite\n\n{len(names)} scenarios, nside {args.nside}, seed {args.seed}; "
        f"wall time {total:.0f} s in all (one process, JIT compilation included).  Metrics at the first "
        "frequency (100 MHz): |posterior mean - truth| / |truth| of the maps along the beam-centre ring and "
        "in the +-1 FWHM band over the observed RA range, the fraction of the whole sky within 10%, and "
        "per-mode z = (mean - truth) / std of the draws.  CG iterations are per draw (0: dense sampler).\n\n"
    )
    (out / "results.md").write_text(head + results_markdown(table))
    (out / "results.csv").write_text(results_csv(table))
    (out / "claims.md").write_text("# The paper's claims, checked by this suite\n\n" + claims_markdown(claims))
    figures = []
    if not args.no_plots:
        figures = _slice_figures(prods, out)
    with open(out / "suite.json", "w") as fh:
        json.dump(_clean_json({"scenarios": names, "rows": table, "claims": [c._asdict() for c in claims],
                               "wall_s": total, "nside": args.nside, "seed": args.seed, "figures": figures,
                               "versions": _versions()}), fh, indent=2, default=_json_default)
    print(head + results_markdown(table))
    print(claims_markdown(claims))
    print(f"wrote {out}/results.md, results.csv, claims.md, suite.json" + (", " + ", ".join(figures) if figures else ""))
    return 0


def _suite_names(args) -> list[str]:
    """The scenarios to run, canonical names; ValueError for unknown or repeated ones."""
    from .scenarios import SCENARIOS, scenario

    names = [scenario(n).name for n in args.names] or list(SCENARIOS)
    if len(set(names)) != len(names):
        raise ValueError(f"scenario names repeat: {names}")
    return names


def _slice_figures(prods: dict, out: Path) -> list[str]:
    """The slice figures of every group with at least two runs present."""
    import numpy as np

    from . import maps as M
    from . import plots as P

    written = []
    for _, fname, members in _SLICE_GROUPS:
        have = [n for n in members if n in prods]
        if len(have) < 2 and not (len(have) == 1 and len(members) == 1):
            continue
        ref = prods["standard"] if "standard" in prods else prods[have[0]]
        curves = []
        for n in have:
            p = prods[n]
            nside = int(np.sqrt(p["mean_map"].size / 12))
            absfrac = np.abs(M.frac_diff_map(p["mean_map"], p["truth_map"]))
            ra, vals = M.ring_slice(absfrac, nside, p["centre_dec_deg"])
            same = tuple(p["ra_range_deg"]) == tuple(ref["ra_range_deg"])
            curves.append((n, ra, vals) if same else (n, ra, vals, p["ra_range_deg"]))
        P.plot_frac_slices(curves, out / fname, fwhm_deg=ref["fwhm_deg"], ra_range_deg=ref["ra_range_deg"],
                           dec_deg=ref["centre_dec_deg"],
                           title="|posterior mean - truth| / truth along the beam-centre declination")
        written.append(fname)
    return written


def _print_summary(s: dict, out: Path) -> None:
    m = s["metrics"]
    t = s["timings_s"]
    sv = s["solver"]
    pct = lambda x: "nan" if x is None or not math.isfinite(x) else f"{100 * x:.2f}%"  # noqa: E731
    lines = [
        f"gcrsky run -> {out}",
        f"  sky: {s['sky_note'].split('. ')[0][:160]}",
        f"  {s['run']['nsamples']} draws ({sv['method']}), lmax {s['config']['lmax']}, nside {s['config']['nside']}, "
        f"{len(s['per_frequency'])} channels",
        f"  at {m['freq_hz'] / 1e6:g} MHz (FWHM {m['fwhm_deg']:.2f} deg, centre dec {s['region']['centre_dec_deg']:.3f}):",
        f"    median |mean-truth|/truth  centre ring {pct(m['frac_diff_centre_median'])}  "
        f"(90th pct {pct(m['frac_diff_centre_p90'])}, within 5%: {pct(m['frac_diff_centre_within_5pct'])})",
        f"                               +-1 FWHM    {pct(m['frac_diff_fwhm_median'])}  "
        f"(90th pct {pct(m['frac_diff_fwhm_p90'])}, within 10%: {pct(m['frac_diff_fwhm_within_10pct'])})",
        f"    per-mode z: rms {m['mode_z']['rms']:.2f}, |z|<=2 for {pct(m['mode_z']['within_2'])}",
        f"  solver: Wiener {sv['wiener']['iterations_max']} it max; draws {sv['draws']['iterations_mean']:.0f} it mean / "
        f"{sv['draws']['iterations_max']} max; worst err {max(sv['wiener']['err_sigma_max'], sv['draws']['err_sigma_max']):.2g} "
        f"sigma; all converged: {sv['all_converged']}",
        f"  time: build {t['build']:.1f} s, wiener {t['wiener']:.1f} s, draws {t['draws']:.1f} s (compile included), "
        f"maps {t['maps']:.1f} s" + (f", plots {t['plots']:.1f} s" if "plots" in t else ""),
        "  wrote results.h5, summary.json" + (", " + ", ".join(s["figures"].values()) if s["figures"] else ""),
    ]
    print("\n".join(lines))


# ---------------------------------------------------------------- entry point


def main(argv=None) -> int:
    """Entry point of the ``gcrsky`` command; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    args._argv = list(sys.argv[1:] if argv is None else argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("gcrsky").setLevel(level)
    if args.command == "scenarios":
        from tqdm.contrib.logging import logging_redirect_tqdm

        try:
            _suite_names(args)
        except ValueError as e:
            parser.error(str(e))
        with logging_redirect_tqdm():
            return _scenarios(args)
    if args.command == "run":
        if args.lst_stop < args.lst_start:
            parser.error(
                f"--lst-stop ({args.lst_stop:g} h) is before --lst-start ({args.lst_start:g} h); to wrap "
                f"through 0 h give a stop beyond 24 h (e.g. --lst-start 22 --lst-stop 26)"
            )
        from .problem import Config

        try:
            Config(lmax=args.lmax, nside=args.nside, n_lst=args.n_lst,
                   lst_range_hours=(args.lst_start, args.lst_stop), obs_date=args.date).validate()
            fields = _run_settings(args)[0]
            Config(**fields).validate()
        except ValueError as e:
            parser.error(str(e))
        from tqdm.contrib.logging import logging_redirect_tqdm

        with logging_redirect_tqdm():
            return _run(args)
    parser.error(f"unknown command {args.command!r}")
    return 2


if __name__ == "__main__":
    sys.exit(main())
