"""The ``gcrsky`` command line (also ``python -m gcrsky``).

``gcrsky run`` reproduces the paper's standard case (or a scenario of its Table 1,
``--scenario NAME``, or a variant through options mirroring :class:`gcrsky.Config`):
simulate, Wiener-filter, draw GCR samples, and write ``results.h5`` (draws
appended batch by batch), the standard products ``posterior_mean.fits`` /
``posterior_std.fits`` (HEALPix maps), ``posterior_mean_alm.fits`` (healpy alm) and
``posterior_mean.skyh5`` (pyradiosky), ``summary.json`` and the paper's per-run
figures (Figs. 3-7: mode z-scores, sky maps, beam region, beam-centre slice,
correlation matrix and corner plot); see :mod:`gcrsky.paper.pipeline`.

An output directory that already holds a run's files is refused unless
``--overwrite`` (delete them, start again) or ``--resume`` (continue the run recorded
in its ``results.h5`` from its first missing batch, ending with exactly the draws of
an uninterrupted run; the options must equal the recorded ones, else it refuses and
names the differing settings; a complete run only gets its missing files rewritten)
is given.  ``--resume`` into a directory without a run starts a new one.

``gcrsky scenarios [NAME ...]`` runs the whole suite (or a subset) into
``--out/NAME/``, reusing the response between scenarios with the same
instrument, and writes ``results.md`` / ``results.csv`` (one row per scenario),
``claims.md`` (the paper's qualitative claims, checked with these numbers),
``suite.json`` and the overlaid slice figures (Figs. 6 and 8).  A scenario
directory that already holds a run's files is refused, before anything runs,
unless ``--overwrite`` is given (the suite-level tables and figures are derived and
always rewritten).  There is no ``--resume`` for the suite (its tables need every
scenario in one process); a killed scenario is continued with ``gcrsky run --scenario
NAME --resume --out OUT/NAME`` and the suite's ``--nside``, ``--nsamples``, ``--seed``
and ``--batch`` (the same settings), then ``gcrsky scenarios --overwrite`` rebuilds the
tables (re-running every scenario).

Reproducibility: the simulated data and the prior mean depend on ``--data-seed``
(``Config.seed``); the draws on ``--seed`` and ``--batch``.  Draws are made in
batches of ``--batch``; batch ``b`` uses the key
``jax.random.fold_in(jax.random.PRNGKey(seed), b)`` and always draws a *full*
batch (the last one is truncated to ``--nsamples``).  So with the same seed and
batch size, draw ``i`` is the same whatever ``--nsamples`` is (``--nsamples 20``
gives the first 20 draws of ``--nsamples 200``), and one compiled program serves
every batch.  Changing ``--batch`` changes the draws (not their distribution).

Compilation: the command turns on JAX's persistent compilation cache (in
``$GCRSKY_COMPILE_CACHE``, else ``$JAX_COMPILATION_CACHE_DIR``, else
``$XDG_CACHE_HOME/gcrsky/jax`` or ``~/.cache/gcrsky/jax``; ``--compile-cache DIR`` chooses,
``--no-compile-cache`` turns it off), so only the first run of a configuration
compiles its XLA programs; later processes load them (:func:`gcrsky.parallel.use_compile_cache`).
``summary.json`` records the run's compile seconds and cache hits and misses
(``timings_s.compile_s``, ``cache_hits``, ``cache_misses``; ``compile``).

Exit status: 0 on success, also when some solves did not converge (a warning is
printed and ``summary.json`` records it: check ``solver.all_converged``), and for a
``--resume`` of a run that was already complete; 1 if the draws contain non-finite
values (results are still written for diagnosis); 2 for bad arguments (argparse);
3 when the output directory holds results that the command refuses to touch
(neither ``--resume`` nor ``--overwrite``) or ``--resume`` cannot continue
(different settings or inputs, unreadable ``results.h5``).
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
#: Exit status when the output directory's results are not ours to touch (module doc).
EXIT_REFUSED = 3


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
        "Wiener filter, draw GCR samples and write results.h5, the posterior mean / std products (FITS, "
        "healpy alm, pyradiosky skyh5), summary.json and figures to --out.",
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
    r.add_argument("--dish-diameter", type=_positive_float("dish-diameter"), default=None,
                   help=f"dish diameter in metres (Gaussian beam, Airy-matched FWHM; default {d.dish_diameter:g} "
                   "for simulations; with --data, the beam if no --beam)")
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
    r.add_argument("--method", choices=("auto", "cg", "cholesky", "eigh", "mmode", "dataspace"), default=None,
                   help="GCR solver (default auto: m-mode for uniform full-day coverage, else the cheaper of dense "
                   "Cholesky and data space (fewer data values than parameters) where they fit, else matrix-free "
                   "CG; or the scenario's: eigh where S^-1 = 0 makes P singular)")
    r.add_argument("--tol", type=_positive_float("tol"), default=None,
                   help="CG tolerance in posterior-sigma units (default 1e-6, or the scenario's)")
    r.add_argument("--batch", type=_int_at_least(1, "batch"), default=DEFAULT_BATCH,
                   help="draws per batch (part of the draws' seed: see the module doc)")
    r.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    r.add_argument("--no-progress", action="store_true", help="no progress bars")
    r.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    _add_compile_cache_options(r)
    _add_channel_options(r)
    dg = r.add_argument_group(
        "your own data", "sample the sky of a visibility file (any file pyuvdata reads) instead of simulating: "
        "--data FILE with --beam FILE or --dish-diameter D; --lmax, --nside, --prior-scale, --method, --tol and the "
        "draw options apply, the simulation's options do not")
    _add_data_options(dg, with_data=True)
    ex = r.add_mutually_exclusive_group()
    ex.add_argument("--resume", action="store_true",
                    help="continue the run recorded in --out (killed or complete) from its first missing batch; "
                    "the options must equal the recorded ones; missing products are rewritten")
    ex.add_argument("--overwrite", action="store_true",
                    help="delete the run files already in --out (results.h5, summary.json, products, figures) and "
                    "start again")

    ins = sub.add_parser(
        "inspect",
        help="print what 'gcrsky run --data FILE' would use (antennas, baselines, LSTs, products, units, flags, "
        "noise, memory) without solving",
        description="Read a visibility file's selection and report what the ingest would use, without building "
        "the response or solving.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    ins.add_argument("file", help="visibility file (UVH5, or UVFITS / MS where pyuvdata's readers are installed)")
    ins.add_argument("--lmax", type=_int_at_least(1, "lmax"), default=d.lmax, help="maximum degree l (for the sizes)")
    ins.add_argument("--nside", type=_nside, default=d.nside, help="HEALPix nside (for the sizes)")
    ins.add_argument("--json", action="store_true", help="print the report as JSON")
    ins.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    _add_data_options(ins, with_data=False)

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
    sc.add_argument("--overwrite", action="store_true",
                    help="replace the run files already in the scenarios' directories (else they are refused)")
    _add_compile_cache_options(sc)
    return p


def _add_channel_options(p) -> None:
    """``--by-channel``, ``--devices K`` and the ``jax.distributed`` options (:mod:`gcrsky.parallel.channels`)."""
    g = p.add_argument_group(
        "channels", "solve the frequency channels independently (their own key scheme: other, equally exact draws "
        "than a joint run), with a progress bar over channels: one at a time (--by-channel), split over devices "
        "(--devices K) or over processes (--coordinator/--num-processes/--process-id: start the same command once "
        "per process, e.g. once per host; process 0 writes the outputs)")
    g.add_argument("--by-channel", action="store_true",
                   help="one channel at a time (memory of one channel's solver)")
    g.add_argument("--devices", type=_int_at_least(1, "devices"), default=None, metavar="K",
                   help="split the channels over K devices (on a CPU: K forced host devices, set before JAX starts)")
    g.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="jax.distributed coordinator address (process 0 listens there)")
    g.add_argument("--num-processes", type=_int_at_least(1, "num-processes"), default=None, metavar="N")
    g.add_argument("--process-id", type=_int_at_least(0, "process-id"), default=None, metavar="I")


def _channel_mode(args) -> str | None:
    """``run_problem``'s ``channels`` for the options: "processes", "devices", "loop" or None (joint)."""
    if getattr(args, "coordinator", None):
        return "processes"
    if (getattr(args, "devices", None) or 1) > 1:
        return "devices"
    return "loop" if getattr(args, "by_channel", False) else None


def _check_channel_options(parser, args) -> None:
    dist = [args.coordinator, args.num_processes, args.process_id]
    if any(v is not None for v in dist) and any(v is None for v in dist):
        parser.error("--coordinator, --num-processes and --process-id go together")
    if args.process_id is not None and args.process_id >= args.num_processes:
        parser.error(f"--process-id {args.process_id} must be below --num-processes {args.num_processes}")


def _channel_bar(disable):
    from tqdm.auto import tqdm

    return lambda total: tqdm(total=total, desc="channels", unit="channel", disable=disable, leave=False,
                              position=1).update


def _add_compile_cache_options(p) -> None:
    """``--compile-cache DIR`` / ``--no-compile-cache`` (JAX's persistent compilation cache)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--compile-cache", default=None, metavar="DIR",
                   help="directory of JAX's persistent compilation cache, so that later runs load the compiled "
                   "programs instead of compiling them (default: $GCRSKY_COMPILE_CACHE, else "
                   "$JAX_COMPILATION_CACHE_DIR, else $XDG_CACHE_HOME/gcrsky/jax or ~/.cache/gcrsky/jax; "
                   "GCRSKY_COMPILE_CACHE=off turns it off)")
    g.add_argument("--no-compile-cache", action="store_true",
                   help="compile every program afresh and write no compilation cache")


def _csv(what: str, conv):
    def parse(s: str):
        try:
            return [conv(x) for x in s.split(",") if x.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a comma-separated list, got {s!r}") from None

    return parse


def _antenna(x: str):
    x = x.strip()
    return int(x) if x.lstrip("-").isdigit() else x


def _add_data_options(g, *, with_data: bool) -> None:
    """The options of a run on a visibility file (``run --data``) and of ``inspect``."""
    if with_data:
        g.add_argument("--data", default=None, metavar="FILE", help="visibility file (UVH5; UVFITS, MS where "
                       "pyuvdata's readers are installed)")
        g.add_argument("--beam", default=None, metavar="FILE",
                       help="beam file UVBeam reads (beamfits, CST, MWA; E-field or power), the same for every antenna")
        g.add_argument("--prior", default="gsm", metavar="gsm|flat|FILE",
                       help="prior: gsm (isotropic, zero mean, the GSM's C_l at the data's frequencies, times "
                       "--prior-scale), flat, a C_l file (.npy, or text: l then C_l per frequency) or a HEALPix map "
                       "/ alm FITS file (the prior mean; variance the GSM's C_l)")
        g.add_argument("--noise", choices=("autos", "diff"), default="autos",
                       help="noise: radiometer equation on the file's autos, or time-adjacent differences")
        g.add_argument("--no-compress", action="store_true", help="keep every baseline (no redundant compression)")
    g.add_argument("--pol", default="pI", metavar="pI|xx|yy|xx,yy",
                   help="modelled product: pseudo-Stokes I (xx + yy), one feed product, or xx and yy jointly")
    g.add_argument("--freq-range", nargs=2, type=_positive_float("freq-range"), default=None, metavar=("LO", "HI"),
                   help="keep channels in [LO, HI] MHz")
    g.add_argument("--chans", type=_csv("chans", int), default=None, metavar="I,J,...", help="channel indices to keep")
    g.add_argument("--lst-range", nargs=2, type=_finite_float("lst-range"), default=None, metavar=("START", "STOP"),
                   help="keep integrations with LST in [START, STOP] hours (START > STOP wraps through 0 h)")
    g.add_argument("--antennas", type=_csv("antennas", _antenna), default=None, metavar="A,B,...",
                   help="antenna numbers or names to keep")


def _data_kwargs(args) -> dict:
    """from_uvdata / inspect_uvdata selection keywords from the parsed options."""
    return dict(
        freq_chans=args.chans,
        freq_range_hz=None if args.freq_range is None else tuple(1e6 * x for x in args.freq_range),
        lst_range_hours=None if args.lst_range is None else tuple(args.lst_range),
        antennas=args.antennas,
        pol=tuple(args.pol.split(",")) if "," in args.pol else args.pol,
    )


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


def _setup_jax(args=None):
    """Process settings before JAX's first computation: the safe CPU pool, float64, the compilation cache.

    Returns the :func:`gcrsky.parallel.compile_stats` snapshot to count the command's compilation from.
    """
    from .parallel.runtime import compile_stats, use_host_devices, use_safe_cpu_threading

    if (getattr(args, "devices", None) or 1) > 1:
        use_host_devices(args.devices)  # CPU devices; on a GPU host the GPUs are the devices anyway
    use_safe_cpu_threading()  # before the first JAX computation (see gcrsky/parallel/runtime.py)
    import jax

    jax.config.update("jax_enable_x64", True)
    _setup_compile_cache(args)
    if getattr(args, "coordinator", None):
        from .parallel.channels import init_distributed

        init_distributed(args.coordinator, args.num_processes, args.process_id)
    return compile_stats()


def _setup_compile_cache(args) -> None:
    """JAX's persistent compilation cache as the options (``--compile-cache``, ``--no-compile-cache``) ask."""
    from .parallel.runtime import disable_compile_cache, use_compile_cache

    if args is not None and getattr(args, "no_compile_cache", False):
        disable_compile_cache()
        return
    want = getattr(args, "compile_cache", None)
    try:
        where = use_compile_cache(want)
    except OSError as e:  # e.g. a read-only home: run without the cache rather than fail
        log.warning("no compilation cache (%s); every program is compiled afresh", e)
        disable_compile_cache()
        return
    log.info("compilation cache: %s", where or "off")


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
        dish_diameter=Config().dish_diameter if args.dish_diameter is None else args.dish_diameter,
        noise_scale=args.noise_scale, prior_scale=args.prior_scale,
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


#: The command-line option behind each recorded run setting (for --resume's messages).
_OPTION_OF = {
    "config.lmax": "--lmax", "config.nside": "--nside", "config.n_lst": "--n-lst",
    "config.lst_range_hours": "--lst-start/--lst-stop", "config.dish_diameter": "--dish-diameter",
    "config.noise_scale": "--noise-scale", "config.prior_scale": "--prior-scale", "config.flat_prior": "--flat-prior",
    "config.zero_prior_mean": "--zero-prior-mean", "config.seed": "--data-seed", "config.obs_date": "--date",
    "nsamples": "--nsamples", "seed": "--seed", "batch": "--batch", "method": "--method", "tol": "--tol",
    "scenario": "--scenario",
}


def _refusal_message(e, *, resume: bool) -> str:
    """The message of a refused run (:class:`~gcrsky.paper.pipeline.RunExistsError` / ``ResumeError``)."""
    from .paper.pipeline import ResumeError

    if isinstance(e, ResumeError) and e.differences:
        what = ", ".join(f"{_OPTION_OF.get(k, k)} (recorded {a!r}, now {b!r})" for k, a, b in e.differences)
        return (f"gcrsky: --resume: the run in {e.out} was made with other settings: {what}. Give the recorded "
                f"options to resume it, or --overwrite to start again (or choose another --out).")
    if isinstance(e, ResumeError):
        return f"gcrsky: --resume: {e}. --overwrite starts again (or choose another --out)."
    if resume:
        return f"gcrsky: --resume: {e} (--overwrite)."
    return (f"gcrsky: {e.out} already holds results of a run ({', '.join(e.files)}); pass --resume to continue "
            f"that run or --overwrite to replace it (or choose another --out).")


def _run(args) -> int:
    compile0 = _setup_jax(args)
    from .paper.pipeline import ResumeError, RunExistsError, check_output, run_settings
    from .sim.config import Config
    from .sim.standard import problem_from_config

    fields, nsamples, method, scen, tol = _run_settings(args)
    out = Path(args.out)
    existing = "resume" if args.resume else ("overwrite" if args.overwrite else "refuse")
    config = Config(**fields).validate()
    mode = _channel_mode(args)
    worker = bool(args.process_id)  # a jax.distributed process other than 0: computes, writes nothing
    extra = None if mode is None else {"channels": mode, "channel_key_scheme": _channel_key_scheme()}
    # refuse (or resume) before the problem is built: the check needs only the settings
    settings = run_settings(config, nsamples=nsamples, seed=args.seed, batch=args.batch, method=method, tol=tol,
                            scenario=scen, extra=extra)
    try:
        state = None if worker else check_output(out, settings, existing)
    except (RunExistsError, ResumeError) as e:
        print(_refusal_message(e, resume=args.resume), file=sys.stderr)
        return EXIT_REFUSED
    if args.resume:
        if state is None:
            print(f"gcrsky: --resume: no run in {out} to resume; starting a new one")
        elif state.draws_done:
            print(f"gcrsky: --resume: the run in {out} has all its {state.ndraws_complete} draws"
                  + (" and is complete; writing any missing files" if state.complete else "; finishing it"))
        else:
            print(f"gcrsky: --resume: continuing the run in {out} at batch {state.batches_complete} of "
                  f"{state.n_batches} ({state.ndraws_complete} of {state.nsamples} draws done)")
    if not worker:
        out.mkdir(parents=True, exist_ok=True)
    disable_bars = True if args.no_progress else None  # tqdm's None: bars only on a terminal
    t0 = time.perf_counter()
    prob = problem_from_config(config)
    build_s = time.perf_counter() - t0
    plots = not args.no_plots
    bar = _StageBar(["wiener", "draws", "maps"] + (["plots"] if plots else []) + ["write"], disable_bars)
    done = _sample_and_write(args, prob, out, bar, disable_bars, mode, nsamples=nsamples, method=method,
                             plots=plots, build_s=build_s, scenario_name=scen, tol=tol, existing=existing,
                             compile_since=compile0)
    if isinstance(done, int):
        return done
    summary, products = done
    if products["already_complete"]:
        missing = products["written"]
        print(f"gcrsky: the run in {out} was already complete; "
              + (f"rewrote the missing {', '.join(missing)}" if missing else "no file was missing"))
    _print_summary(summary, out, products["written"])
    for w in summary["warnings"]:
        print(w, file=sys.stderr)
    if not summary["draws_finite"]:
        print("gcrsky: the draws contain NaN/inf; exiting with status 1 (results written for diagnosis).",
              file=sys.stderr)
        return 1
    return 0


def _channel_key_scheme() -> str:
    from .parallel.channels import CHANNEL_KEY_SCHEME

    return CHANNEL_KEY_SCHEME


def _sample_and_write(args, prob, out, bar, disable_bars, mode, **kw):
    """``run_problem`` with the command's bars, seed and batch: ``(summary, products)``, or an exit status
    (a refused run; a ``jax.distributed`` process other than 0, which writes nothing)."""
    from .paper.pipeline import ResumeError, RunExistsError, run_problem

    try:
        summary, products = run_problem(
            prob, out, seed=args.seed, batch=args.batch, argv=getattr(args, "_argv", None), on_stage=bar,
            progress=_batch_bar(disable_bars), channels=mode, channel_progress=_channel_bar(disable_bars), **kw,
        )
    except (RunExistsError, ResumeError) as e:  # e.g. the inputs differ from the recorded ones
        print(_refusal_message(e, resume=args.resume), file=sys.stderr)
        return EXIT_REFUSED
    finally:
        bar.close()
    if summary is None:
        return _worker_done(args)
    return summary, products


def _worker_done(args) -> int:
    print(f"gcrsky: process {args.process_id} of {args.num_processes}: computed its channels; process 0 writes "
          f"the results to {args.out}")
    return 0


#: ``gcrsky run`` options of a simulation that a run on a file does not use (dest, option).
_SIM_ONLY = (("scenario", "--scenario"), ("lst_start", "--lst-start"), ("lst_stop", "--lst-stop"),
             ("n_lst", "--n-lst"), ("noise_scale", "--noise-scale"), ("flat_prior", "--flat-prior"),
             ("zero_prior_mean", "--zero-prior-mean"), ("date", "--date"), ("data_seed", "--data-seed"))


def _check_data_options(parser, args) -> None:
    """A run on a file takes its beam from --beam or --dish-diameter and refuses the simulation's options."""
    defaults = build_parser().parse_args(["run"])
    used = [opt for dest, opt in _SIM_ONLY if getattr(args, dest) != getattr(defaults, dest)]
    if used:
        parser.error(f"{', '.join(used)} describe a simulation; with --data the file says what was observed")
    if (args.beam is None) == (args.dish_diameter is None):
        parser.error("with --data give the beam: --beam FILE (any file UVBeam reads) or --dish-diameter D (a "
                     "Gaussian beam of that dish), one of them")
    if args.prior not in ("gsm", "flat") and not Path(args.prior).exists():
        parser.error(f"--prior {args.prior!r}: neither 'gsm', 'flat' nor an existing file")
    if not Path(args.data).exists():
        parser.error(f"--data {args.data!r}: no such file")


def _file_digest(path) -> str:
    """SHA-256 of a file (what a resumed run on a file must find unchanged)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _run_data(args) -> int:
    """``gcrsky run --data FILE``: the posterior of a visibility file's sky (no truth: no truth metrics)."""
    compile0 = _setup_jax(args)
    from .io.uvdata import from_uvdata
    from .paper.pipeline import RunExistsError, existing_run_files

    out = Path(args.out)
    existing = "resume" if args.resume else ("overwrite" if args.overwrite else "refuse")
    nsamples, method, tol = args.nsamples or DEFAULT_NSAMPLES, args.method or "auto", args.tol or 1e-6
    kw = _data_kwargs(args)
    extra = {"data_file": str(Path(args.data).resolve()), "data_sha256": _file_digest(args.data),
             "beam": args.beam, "dish_diameter": args.dish_diameter, "prior": args.prior,
             "prior_scale": args.prior_scale, "noise": args.noise, "compress": not args.no_compress,
             "lmax": args.lmax, "nside": args.nside,
             "selection": {k: (list(v) if isinstance(v, tuple) else v) for k, v in kw.items()}}
    mode = _channel_mode(args)
    if existing == "refuse" and not args.process_id:  # refuse before reading the file; --resume is checked once the problem is built
        # (its recorded settings include what the file said: conventions, selection, beam, prior)
        taken = existing_run_files(out)
        if taken:
            print(_refusal_message(RunExistsError(out, taken), resume=False), file=sys.stderr)
            return EXIT_REFUSED
    disable_bars = True if args.no_progress else None
    t0 = time.perf_counter()
    beam = None
    if args.beam is not None:
        from .instrument.beams import load_beam

        beam = load_beam(args.beam)
    prob = from_uvdata(args.data, lmax=args.lmax, nside=args.nside, beam=beam, dish_diameter_m=args.dish_diameter,
                       prior=args.prior, prior_scale=args.prior_scale, noise=args.noise,
                       compress=not args.no_compress, **kw)
    build_s = time.perf_counter() - t0
    cfg = prob.config
    print(f"gcrsky: {args.data}: {len(cfg.conventions['antenna_numbers'])} antennas, {prob.data.shape[2]} rows "
          f"({'compressed' if cfg.compressed else 'all baselines'}), {prob.data.shape[1]} times, "
          f"{prob.data.shape[0]} channels, {cfg.pol}; prior: {cfg.prior}")
    plots = not args.no_plots
    bar = _StageBar(["wiener", "draws", "maps"] + (["plots"] if plots else []) + ["write"], disable_bars)
    done = _sample_and_write(args, prob, out, bar, disable_bars, mode, nsamples=nsamples, method=method,
                             plots=plots, build_s=build_s, tol=tol, existing=existing, extra_settings=extra,
                             compile_since=compile0)
    if isinstance(done, int):
        return done
    summary, products = done
    if products["already_complete"]:
        print(f"gcrsky: the run in {out} was already complete")
    _print_summary(summary, out, products["written"])
    for w in summary["warnings"]:
        print(w, file=sys.stderr)
    return 0 if summary["draws_finite"] else 1


def _inspect(args) -> int:
    """``gcrsky inspect FILE``: what a run on the file would use."""
    import json

    from .base.memory import format_bytes
    from .io.uvdata import inspect_uvdata

    info = inspect_uvdata(args.file, lmax=args.lmax, nside=args.nside, **_data_kwargs(args))
    if args.json:
        print(json.dumps(info, indent=1))
        return 0
    c = info["conventions"]
    lines = [
        f"gcrsky inspect {info['source']}",
        f"  antennas      {info['n_antennas']}: {', '.join(str(a) for a in info['antennas'][:20])}"
        + (" ..." if info["n_antennas"] > 20 else ""),
        f"  baselines     {info['n_baselines']} ({info['n_unique_baselines']} unique by separation)",
        f"  times         {info['n_times']}, LST {info['lst_range_hours'][0]:.3f} - {info['lst_range_hours'][1]:.3f} h",
        f"  channels      {info['n_channels']}, {info['freq_range_hz'][0] / 1e6:.4f} - "
        f"{info['freq_range_hz'][1] / 1e6:.4f} MHz, width {info['channel_width_hz'] / 1e3:.3g} kHz",
        f"  products      file {', '.join(info['file_polarizations'])}; modelled {', '.join(info['modelled_products'])}",
        f"  conventions   {c['vis_units']}, pol_convention {c['pol_convention']}, {c['phase']}",
        f"  flagged       {100 * info['flagged_fraction']:.2f}% of the samples used",
        "  noise         " + (f"radiometer (autos): median sigma {info['noise_sigma_median_k_sr']:.4g} K sr per component"
                               if info["has_autos"] else "no autocorrelations: use --noise diff"),
        f"  memory        read {format_bytes(info['read_bytes'])}; dense P at lmax {args.lmax}: "
        f"{format_bytes(info['dense_precision_bytes'])}; response {format_bytes(info.get('response_bytes', 0))}",
        f"  site          lat {info['site_lat_lon_deg'][0]:.4f} deg, lon {info['site_lat_lon_deg'][1]:.4f} deg",
    ]
    lines += [f"  note          {n}" for n in info["notes"]]
    print("\n".join(lines))
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
    compile0 = _setup_jax(args)
    from .paper.pipeline import existing_run_files, remove_run_files

    taken = {n: existing_run_files(Path(args.out) / n) for n in names}
    taken = {n: f for n, f in taken.items() if f}
    if taken and not args.overwrite:
        what = "; ".join(f"{Path(args.out) / n}: {', '.join(f)}" for n, f in taken.items())
        print(f"gcrsky: scenario directories already hold results ({what}); pass --overwrite to replace them "
              f"(or choose another --out; to continue one killed scenario: gcrsky run --scenario NAME --resume "
              f"--out {Path(args.out) / 'NAME'} with the suite's --nside, --nsamples, --seed and --batch).",
              file=sys.stderr)
        return EXIT_REFUSED
    for n in taken:
        remove_run_files(Path(args.out) / n)
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
    print(_compile_line(_compile_of(compile0), "compile (all scenarios)"))
    return 0


def _compile_of(since) -> dict:
    """The compilation since a snapshot, with the cache directory (as ``summary.json``'s ``compile``)."""
    from .parallel.runtime import compile_cache_dir, compile_stats

    d = compile_stats().since(since)._asdict()
    where = compile_cache_dir()
    d["cache_dir"] = None if where is None else str(where)
    return d


def _compile_line(c: dict, label: str = "compile") -> str:
    """``compile 8.0 s (39 programs; cache DIR: 0 hits, 39 misses)``, from a ``compile`` block."""
    if c.get("cache_dir"):
        cache = f"cache {c['cache_dir']}: {c['cache_hits']} hits, {c['cache_misses']} misses"
    else:
        cache = "compilation cache off"
    return f"  {label} {c['compile_s']:.1f} s ({c['programs']} programs; {cache})"


def _print_summary(s: dict, out: Path, written=None) -> None:
    t = s["timings_s"]
    sv = s["solver"]
    pct = lambda x: "nan" if x is None or not math.isfinite(x) else f"{100 * x:.2f}%"  # noqa: E731
    cfg = s.get("config") or {}
    lines = [f"gcrsky run -> {out}"]
    if s.get("sky_note"):
        lines.append(f"  sky: {s['sky_note'].split('. ')[0][:160]}")
    lines.append(
        f"  {s['run']['nsamples']} draws ({sv['method']})"
        + (f", lmax {cfg['lmax']}, nside {cfg['nside']}" if cfg else "") + f", {len(s['per_frequency'])} channels"
    )
    m = s["metrics"]
    if m.get("frac_diff_centre_median") is not None or "frac_diff_centre_p90" in m:
        lines += [
            f"  at {m['freq_hz'] / 1e6:g} MHz (FWHM {m['fwhm_deg']:.2f} deg, centre dec "
            f"{s['region']['centre_dec_deg']:.3f}):",
            f"    median |mean-truth|/truth  centre ring {pct(m['frac_diff_centre_median'])}  "
            f"(90th pct {pct(m['frac_diff_centre_p90'])}, within 5%: {pct(m['frac_diff_centre_within_5pct'])})",
            f"                               +-1 FWHM    {pct(m['frac_diff_fwhm_median'])}  "
            f"(90th pct {pct(m['frac_diff_fwhm_p90'])}, within 10%: {pct(m['frac_diff_fwhm_within_10pct'])})",
        ]
    if "mode_z" in m:
        lines.append(f"    per-mode z: rms {m['mode_z']['rms']:.2f}, |z|<=2 for {pct(m['mode_z']['within_2'])}")
    worst = [x for x in (sv["wiener"]["err_sigma_max"], sv["draws"]["err_sigma_max"]) if x is not None]
    lines += [
        f"  solver: Wiener {sv['wiener']['iterations_max']} it max; draws {sv['draws']['iterations_mean']:.0f} it mean / "
        f"{sv['draws']['iterations_max']} max; worst err {max(worst) if worst else float('nan'):.2g} "
        f"sigma; all converged: {sv['all_converged']}",
        f"  time: build {t['build']:.1f} s, wiener {t['wiener']:.1f} s, draws {t['draws']:.1f} s (compile included), "
        f"maps {t['maps']:.1f} s" + (f", plots {t['plots']:.1f} s" if "plots" in t else ""),
    ]
    if "compile" in s:  # not in the summary of a run made before it was recorded
        lines.append(_compile_line(s["compile"]))
    if written is None:
        written = ["results.h5", "summary.json", *s.get("figures", {}).values()]
    lines.append("  wrote " + (", ".join(written) if written else "nothing (every file was there)"))
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
    if args.command == "inspect":
        try:
            return _inspect(args)
        except (ValueError, FileNotFoundError) as e:
            print(f"gcrsky inspect: {e}", file=sys.stderr)
            return 2
    if args.command == "run":
        _check_channel_options(parser, args)
    if args.command == "run" and args.data is not None:
        _check_data_options(parser, args)
        from tqdm.contrib.logging import logging_redirect_tqdm

        with logging_redirect_tqdm():
            try:
                return _run_data(args)
            except (ValueError, FileNotFoundError) as e:  # the file or the options: a message, not a traceback
                print(f"gcrsky run --data: {e}", file=sys.stderr)
                return 2
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
