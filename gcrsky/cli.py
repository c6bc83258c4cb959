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
import logging
import math
import os
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
    """The argument parser (defaults of the physics options come from :class:`gcrsky.sim.Config`)."""
    from .sim.config import Config

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


# ---------------------------------------------------------------- terminal


class _StageBar:
    """A tqdm bar over the named stages of a run (the terminal is the CLI's)."""

    def __init__(self, names, disable):
        from tqdm.auto import tqdm

        self.bar = tqdm(total=len(names), desc="gcrsky", unit="stage", disable=disable, leave=False, position=0,
                        bar_format="{desc}: {n_fmt}/{total_fmt} stages |{bar}| {elapsed}")

    def __call__(self, name: str, event: str) -> None:
        if event == "start":
            self.bar.set_description(f"gcrsky: {name}")
        else:
            self.bar.update(1)

    def close(self):
        self.bar.close()


def _batch_bar(disable):
    from tqdm.auto import tqdm

    return lambda it: tqdm(it, desc="draw batches", unit="batch", disable=disable, leave=False, position=1)


# ---------------------------------------------------------------- the run command


def _setup_jax():
    from .parallel.runtime import use_safe_cpu_threading

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
    from .paper.scenarios import scenario
    from .sim.config import Config

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
    from .paper.pipeline import run_problem
    from .sim.config import Config
    from .sim.standard import problem_from_config

    fields, nsamples, method, scen, tol = _run_settings(args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    disable_bars = True if args.no_progress else None  # tqdm's None: bars only on a terminal
    t0 = time.perf_counter()
    prob = problem_from_config(Config(**fields).validate())
    build_s = time.perf_counter() - t0
    plots = not args.no_plots
    bar = _StageBar(["wiener", "draws", "maps"] + (["plots"] if plots else []) + ["write"], disable_bars)
    try:
        summary, _ = run_problem(
            prob, out, nsamples=nsamples, seed=args.seed, batch=args.batch, method=method, plots=plots,
            build_s=build_s, argv=getattr(args, "_argv", None), scenario_name=scen, tol=tol,
            on_stage=bar, progress=_batch_bar(disable_bars),
        )
    finally:
        bar.close()
    _print_summary(summary, out)
    for w in summary["warnings"]:
        print(w, file=sys.stderr)
    if not summary["draws_finite"]:
        print("gcrsky: the draws contain NaN/inf; exiting with status 1 (results written for diagnosis).",
              file=sys.stderr)
        return 1
    return 0


def _scenarios(args) -> int:
    from .paper.scenarios import SCENARIOS

    if args.list:
        for sc in SCENARIOS.values():
            extra = ", ".join(f"{k}={v}" for k, v in sc.overrides) or "-"
            print(f"{sc.name:9s} {sc.varies:28s} draws {sc.nsamples:5d}  method {sc.method:5s}  Config: {extra}")
        return 0
    from .paper.suite import run_suite, suite_names

    names = suite_names(args.names)
    _setup_jax()
    from tqdm.auto import tqdm

    disable_bars = True if args.no_progress else None
    bar = {}

    def progress(it):
        bar["bar"] = tqdm(it, desc="scenarios", unit="run", disable=disable_bars, leave=False)
        return bar["bar"]

    def on_result(name, row, summary):
        tqdm.write(
            f"{name:9s} centre {100 * row['centre_median']:7.2f}%  +-1 FWHM {100 * row['fwhm_median']:7.2f}%  "
            f"sky<10% {100 * row['sky_within_10pct']:5.1f}%  |z|>15: {row['z_beyond_15']:3d}  "
            f"{row['wall_s']:6.1f} s" + ("" if summary["solver"]["all_converged"] else "  (NOT CONVERGED)")
        )

    res = run_suite(names, args.out, nside=args.nside, nsamples=args.nsamples, seed=args.seed, batch=args.batch,
                    plots=not args.no_plots, argv=getattr(args, "_argv", None), progress=progress,
                    on_result=on_result)
    if "bar" in bar:
        bar["bar"].close()
    print(res.markdown)
    print(res.claims_markdown)
    print(f"wrote {args.out}/results.md, results.csv, claims.md, suite.json"
          + (", " + ", ".join(res.figures) if res.figures else ""))
    return 0


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
    from .base.extras import require

    require("tqdm", "cli", "the gcrsky command line")
    parser = build_parser()
    args = parser.parse_args(argv)
    args._argv = list(sys.argv[1:] if argv is None else argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("gcrsky").setLevel(level)
    if args.command == "scenarios":
        from tqdm.contrib.logging import logging_redirect_tqdm

        from .paper.suite import suite_names

        try:
            suite_names(args.names)
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
        from .sim.config import Config

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
