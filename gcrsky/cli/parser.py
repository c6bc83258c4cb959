"""The ``gcrsky`` argument parser: one builder per command, each setting the command's function (``func``)."""

from __future__ import annotations

import argparse

from ..solvers import registry
from ..solvers.options import DEFAULT_TOL
from .options import (
    DEFAULT_BATCH,
    DEFAULT_NSAMPLES,
    DEFAULT_OUT,
    DEFAULT_SUITE_OUT,
    MAX_SEED,
    add_beam_options,
    add_channel_options,
    add_compile_cache_options,
    add_data_options,
    add_frequency_options,
    add_gain_options,
    add_run_flags,
    finite_float,
    int_at_least,
    nside_arg,
    positive_float,
)

__all__ = ["build_parser"]


def _sci(x: float) -> str:
    """``1e-06`` as ``1e-6``."""
    mant, exp = f"{x:.0e}".split("e")
    return f"{mant}e{int(exp)}"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (defaults of the physics options come from :class:`gcrsky.sim.Config`)."""
    p = argparse.ArgumentParser(
        prog="gcrsky",
        description="Full-sky maps with honest uncertainties: Gaussian constrained realisations "
        "of spherical-harmonic skies from drift-scan visibilities (Glasscock et al. 2024).",
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    _add_run_parser(sub)
    _add_inspect_parser(sub)
    _add_scenarios_parser(sub)
    return p


def _defaults():
    from ..sim.config import Config

    return Config()


def _command(sub, name: str, func, help: str, description: str):
    """A subcommand whose function is ``func(args, parser)``, with its defaults in the help."""
    p = sub.add_parser(name, help=help, description=description, formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.set_defaults(func=func)
    return p


def _add_run_parser(sub) -> None:
    """``gcrsky run``: a simulation (options mirroring :class:`gcrsky.sim.Config`) or a file (``--data``)."""
    from .cmd_run import run_command

    r = _command(
        sub, "run", run_command,
        help="simulate the paper's standard case (or a variant), sample the posterior, write results",
        description="Simulate the standard case (options override its configuration), compute the "
        "Wiener filter, draw GCR samples and write results.h5, the posterior mean / std products (FITS, "
        "healpy alm, pyradiosky skyh5), summary.json and figures to --out.",
    )
    r.add_argument("--scenario", default=None, metavar="NAME",
                   help="start from a scenario of the paper's Table 1 (standard, A1, B1-B8, C1-C5, D1; see "
                   "'gcrsky scenarios --list'); other options change it further, unless they contradict it")
    r.add_argument("--out", default=DEFAULT_OUT, help="output directory (created if needed)")
    r.add_argument("--nsamples", type=int_at_least(1, "nsamples"), default=None,
                   help=f"number of posterior draws (default {DEFAULT_NSAMPLES}, or the scenario's)")
    r.add_argument("--seed", type=int_at_least(0, "seed", MAX_SEED), default=0,
                   help="seed of the posterior draws (see --batch)")
    _add_simulation_options(r, _defaults())
    r.add_argument("--method", choices=("auto", *registry.PATHS), default=None,
                   help="GCR solver (default auto: m-mode for uniform full-day coverage, else the cheaper of dense "
                   "Cholesky and data space (fewer data values than parameters) where they fit, else matrix-free "
                   "CG; or the scenario's: eigh where S^-1 = 0 makes P singular)")
    r.add_argument("--tol", type=positive_float("tol"), default=None,
                   help=f"CG tolerance in posterior-sigma units (default {_sci(DEFAULT_TOL)}, or the scenario's)")
    r.add_argument("--batch", type=int_at_least(1, "batch"), default=DEFAULT_BATCH,
                   help="draws per batch (part of the draws' seed: see the module doc)")
    add_run_flags(r, plots_help="skip the PNG figures")
    r.add_argument("--strict", action="store_true",
                   help="exit with status 6 when the run completes but the goodness of fit rejects the model in "
                   "some channel (everything is still written); without it a rejected fit is a WARNING, status 0")
    add_compile_cache_options(r)
    add_channel_options(r)
    dg = r.add_argument_group(
        "your own data", "sample the sky of a visibility file (any file pyuvdata reads) instead of simulating: "
        "--data FILE with --beam FILE or --dish-diameter D; --lmax, --nside, --prior-scale, --method, --tol and the "
        "draw options apply, the simulation's options do not")
    add_data_options(dg, with_data=True)
    add_gain_options(r.add_argument_group(
        "gains sampled with the sky", "--data only: per-antenna complex gains (a few smooth modes in frequency and "
        "time) and the overall amplitude sampled jointly with the sky (docs/gains.md); the draws are then a Markov "
        "chain's, and the posterior-mean gains are written as gains.calh5"))
    add_beam_options(r.add_argument_group(
        "beams sampled with the sky", "--data only: every antenna's beam perturbed by a few Zernike modes over its "
        "main lobe (pointing, width, ellipticity), sampled jointly with the sky (docs/beams.md); the draws are then a "
        "Markov chain's, and the posterior-mean beams are written as beams/ant<N>.beamfits"))
    add_frequency_options(r.add_argument_group(
        "frequency prior", "one prior over all channels, coupling them (docs/frequency.md): the channels are sampled "
        "jointly, and fully flagged channels are inpainted through their neighbours (marked in summary.json)"))
    ex = r.add_mutually_exclusive_group()
    ex.add_argument("--resume", action="store_true",
                    help="continue the run recorded in --out (killed or complete) from its first missing batch; "
                    "the options must equal the recorded ones; missing products are rewritten")
    ex.add_argument("--overwrite", action="store_true",
                    help="delete the run files already in --out (results.h5, summary.json, products, figures) and "
                    "start again")
    r.add_argument("--trust-recorded", action="store_true",
                   help="with --resume: continue from the inputs recorded in results.h5 (data, noise, weights, "
                   "prior) even where the rebuilt ones differ by more than rounding (e.g. another sky model on "
                   "disk now); the draws are kept. Rounding differences never need it")


def _add_simulation_options(r, d) -> None:
    """The options of ``gcrsky run`` that mirror :class:`gcrsky.sim.Config` fields (defaults ``d``)."""
    r.add_argument("--data-seed", type=int_at_least(0, "data-seed", MAX_SEED), default=d.seed,
                   help="seed of the simulated noise and prior mean (Config.seed)")
    r.add_argument("--lmax", type=int_at_least(1, "lmax"), default=None,
                   help=f"maximum degree l (default: {d.lmax} for a simulation; with --data the reach of every used "
                   "baseline at the highest used frequency, capped by memory)")
    r.add_argument("--nside", type=nside_arg, default=d.nside, help="HEALPix nside of the response quadrature and maps")
    r.add_argument("--lst-start", type=finite_float("lst-start"), default=d.lst_range_hours[0],
                   help="first LST (sidereal hours)")
    r.add_argument("--lst-stop", type=finite_float("lst-stop"), default=d.lst_range_hours[1],
                   help="last LST (sidereal hours, >= --lst-start; to wrap through 0 h use e.g. 22 to 26)")
    r.add_argument("--n-lst", type=int_at_least(1, "n-lst"), default=d.n_lst,
                   help="number of LSTs, evenly spaced from start to stop inclusive")
    r.add_argument("--dish-diameter", type=positive_float("dish-diameter"), default=None,
                   help=f"dish diameter in metres (Gaussian beam, Airy-matched FWHM; default {d.dish_diameter:g} "
                   "for simulations; with --data, the beam if no --beam)")
    r.add_argument("--noise-scale", type=positive_float("noise-scale"), default=d.noise_scale,
                   help="factor on the noise variance")
    r.add_argument("--prior-scale", type=positive_float("prior-scale"), default=d.prior_scale,
                   help="factor on the prior variance")
    r.add_argument("--flat-prior", action="store_true", default=d.flat_prior,
                   help="no prior (S^-1 = 0; the posterior may be improper)")
    r.add_argument("--zero-prior-mean", action="store_true", default=d.zero_prior_mean,
                   help="prior mean a0 = 0 instead of a draw around the truth")
    r.add_argument("--date", default=d.obs_date, metavar="YYYY-MM-DD",
                   help="observe on this UTC date at the real times whose local Earth rotation angle is each "
                   "LST (sky in ICRS, exact ICRS -> CIRS-of-date frame map); default: the paper's idealised LSTs")


def _add_inspect_parser(sub) -> None:
    """``gcrsky inspect FILE``: what a run on the file would use, without solving."""
    from .cmd_inspect import inspect_command

    d = _defaults()
    ins = _command(
        sub, "inspect", inspect_command,
        help="print what 'gcrsky run --data FILE' would use (antennas, baselines, LSTs, products, units, flags, "
        "noise, memory) without solving",
        description="Read a visibility file's selection and report what the ingest would use, without building "
        "the response or solving.",
    )
    ins.add_argument("file", nargs="+", help="visibility file(s) (UVH5, or UVFITS / MS where pyuvdata's readers are "
                     "installed): one, several, a quoted glob or a directory, read as one observation")
    ins.add_argument("--lmax", type=int_at_least(1, "lmax"), default=None,
                     help="maximum degree l for the sizes (default: with a beam, the lmax a run would choose, the reach "
                     f"of every used baseline; without, {d.lmax})")
    ins.add_argument("--nside", type=nside_arg, default=d.nside, help="HEALPix nside (for the sizes)")
    ins.add_argument("--json", action="store_true", help="print the report as JSON")
    ins.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")
    add_data_options(ins, with_data=False)


def _add_scenarios_parser(sub) -> None:
    """``gcrsky scenarios [NAME ...]``: the paper's suite (Table 1)."""
    from .cmd_scenarios import scenarios_command

    sc = _command(
        sub, "scenarios", scenarios_command,
        help="run the paper's scenario suite (Table 1) and write the results table and figures",
        description="Run the named scenarios (default: all 16 of the paper's Table 1) into --out/NAME/, "
        "reusing the response wherever the instrument is shared, then write results.md, results.csv, "
        "claims.md and the cross-run figures (Figs. 6-8) to --out.",
    )
    sc.add_argument("names", nargs="*", metavar="NAME", help="scenarios to run (default: all)")
    sc.add_argument("--list", action="store_true", help="list the scenarios and exit")
    sc.add_argument("--out", default=DEFAULT_SUITE_OUT, help="output directory")
    sc.add_argument("--nsamples", type=int_at_least(1, "nsamples"), default=None,
                    help="draws per scenario (default: 200, 5000 for A1)")
    sc.add_argument("--nside", type=nside_arg, default=_defaults().nside, help="HEALPix nside (quick runs: 32)")
    sc.add_argument("--seed", type=int_at_least(0, "seed", MAX_SEED), default=0, help="seed of the posterior draws")
    sc.add_argument("--batch", type=int_at_least(1, "batch"), default=DEFAULT_BATCH, help="draws per batch")
    add_run_flags(sc, plots_help="skip all PNG figures")
    sc.add_argument("--overwrite", action="store_true",
                    help="replace the run files already in the scenarios' directories (else they are refused)")
    add_compile_cache_options(sc)
