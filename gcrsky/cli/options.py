"""Argument types and the option groups several commands share (compile cache, channels, a visibility file)."""

from __future__ import annotations

import argparse
import math
import os

from ..parallel.rendezvous import DEFAULT_DIST_TIMEOUT

__all__ = [
    "DEFAULT_BATCH",
    "DEFAULT_NSAMPLES",
    "DEFAULT_OUT",
    "DEFAULT_SUITE_OUT",
    "EXIT_DIST",
    "add_channel_options",
    "add_compile_cache_options",
    "add_data_options",
    "add_frequency_options",
    "add_gain_options",
    "check_frequency_options",
    "frequency_model",
    "gain_sampling",
    "add_beam_options",
    "add_beam_prior_options",
    "beam_sampling",
    "add_run_flags",
    "channel_mode",
    "check_channel_options",
    "CLI_SELECTION",
    "ingest_spec",
    "finite_float",
    "int_at_least",
    "nside_arg",
    "positive_float",
]

DEFAULT_OUT = os.path.join("runs", "standard")
DEFAULT_SUITE_OUT = os.path.join("runs", "paper")
DEFAULT_NSAMPLES = 200
DEFAULT_BATCH = 50

#: Exit status when the ``jax.distributed`` processes could not start together (see :mod:`gcrsky.cli`).
EXIT_DIST = 4


# ---------------------------------------------------------------- argument types


def _number(s: str, what: str, kind, noun: str):
    try:
        return kind(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must be {noun}, got {s!r}") from None


#: Largest seed (a signed 64-bit integer: what results.h5 records and JAX's PRNGKey takes).
MAX_SEED = 2**63 - 1


def int_at_least(lo: int, what: str, hi: int | None = None):
    """An integer option ``>= lo`` (and ``<= hi`` if given; ``what``: its name in the message)."""

    def conv(s: str) -> int:
        v = _number(s, what, int, "an integer")
        if v < lo or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"{what} must be >= {lo}" + ("" if hi is None else f" and <= {hi}")
                                             + f", got {v}")
        return v

    return conv


def _float_where(what: str, ok, requirement: str):
    def conv(s: str) -> float:
        v = _number(s, what, float, "a number")
        if not ok(v):
            raise argparse.ArgumentTypeError(f"{what} must be {requirement}, got {s!r}")
        return v

    return conv


def positive_float(what: str):
    """A positive finite number option."""
    return _float_where(what, lambda v: v > 0 and math.isfinite(v), "a positive finite number")


def finite_float(what: str):
    """A finite number option."""
    return _float_where(what, math.isfinite, "finite")


def nside_arg(s: str) -> int:
    """A HEALPix nside: a power of 2."""
    v = int_at_least(1, "nside")(s)
    if v & (v - 1):
        raise argparse.ArgumentTypeError(f"nside must be a power of 2, got {v}")
    return v


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


# ---------------------------------------------------------------- shared option groups


def add_run_flags(p, *, plots_help: str) -> None:
    """``--no-plots``, ``--no-progress`` and ``-v`` of the commands that run."""
    p.add_argument("--no-plots", action="store_true", help=plots_help)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-v info, -vv debug)")


def add_compile_cache_options(p) -> None:
    """``--compile-cache DIR`` / ``--no-compile-cache`` (JAX's persistent compilation cache)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--compile-cache", default=None, metavar="DIR",
                   help="directory of JAX's persistent compilation cache, so that later runs load the compiled "
                   "programs instead of compiling them (default: $GCRSKY_COMPILE_CACHE, else "
                   "$JAX_COMPILATION_CACHE_DIR, else $XDG_CACHE_HOME/gcrsky/jax or ~/.cache/gcrsky/jax; "
                   "GCRSKY_COMPILE_CACHE=off turns it off)")
    g.add_argument("--no-compile-cache", action="store_true",
                   help="compile every program afresh and write no compilation cache")


def add_channel_options(p) -> None:
    """``--by-channel``, ``--devices K`` and the ``jax.distributed`` options (:mod:`gcrsky.parallel.channels`)."""
    g = p.add_argument_group(
        "channels", "solve the frequency channels independently (their own key scheme: other, equally exact draws "
        "than a joint run), with a progress bar over channels: one at a time (--by-channel), split over devices "
        "(--devices K) or over processes (--coordinator/--num-processes/--process-id: start the same command once "
        "per process, e.g. once per host; process 0 writes the outputs)")
    g.add_argument("--by-channel", action="store_true",
                   help="one channel at a time (memory of one channel's solver)")
    g.add_argument("--devices", type=int_at_least(1, "devices"), default=None, metavar="K",
                   help="split the channels over K devices (on a CPU: K forced host devices, set before JAX starts)")
    g.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="jax.distributed coordinator address (process 0 listens there)")
    g.add_argument("--num-processes", type=int_at_least(1, "num-processes"), default=None, metavar="N")
    g.add_argument("--process-id", type=int_at_least(0, "process-id"), default=None, metavar="I")
    g.add_argument("--dist-timeout", type=positive_float("dist-timeout"), default=None, metavar="SECONDS",
                   help="with --coordinator: how long the processes wait for each other at start-up (default "
                   f"{DEFAULT_DIST_TIMEOUT:g}); a coordinator that cannot be reached, or a process that does not "
                   f"join, in that time ends every waiting process with a message and exit status {EXIT_DIST}")


def channel_mode(args) -> str | None:
    """``RunSpec.channels`` for the options: "processes", "devices", "loop" or None (joint)."""
    if getattr(args, "coordinator", None):
        return "processes"
    if (getattr(args, "devices", None) or 1) > 1:
        return "devices"
    return "loop" if getattr(args, "by_channel", False) else None


def check_channel_options(parser, args) -> None:
    """The ``jax.distributed`` options go together, and the process id is below their number."""
    dist = [args.coordinator, args.num_processes, args.process_id]
    if any(v is not None for v in dist) and any(v is None for v in dist):
        parser.error("--coordinator, --num-processes and --process-id go together")
    if args.process_id is not None and args.process_id >= args.num_processes:
        parser.error(f"--process-id {args.process_id} must be below --num-processes {args.num_processes}")
    if getattr(args, "dist_timeout", None) is not None and args.coordinator is None:
        parser.error("--dist-timeout goes with --coordinator")


def add_data_options(g, *, with_data: bool) -> None:
    """The options of a run on a visibility file (``run --data``) and of ``inspect``."""
    if with_data:
        g.add_argument("--data", default=None, nargs="+", metavar="FILE",
                       help="visibility file(s) (UVH5; UVFITS, MS where pyuvdata's readers are installed): one, "
                       "several, a quoted glob ('night/zen.*.uvh5') or a directory; several files of one array and "
                       "band are one observation (a night, several nights)")
        g.add_argument("--beam", default=None, metavar="FILE",
                       help="beam file UVBeam reads (beamfits, CST, MWA; E-field or power), the same for every antenna")
        g.add_argument("--prior", default="gsm", metavar="gsm|flat|FILE",
                       help="prior: gsm (isotropic, zero mean, the GSM's C_l at the data's frequencies, times "
                       "--prior-scale), flat, a C_l file (.npy, or text: l then C_l per frequency) or a HEALPix map "
                       "/ alm FITS file (the prior mean; variance the GSM's C_l)")
        g.add_argument("--noise", choices=("autos", "diff"), default="autos",
                       help="noise: radiometer equation on the file's autos, or time-adjacent differences")
        g.add_argument("--no-compress", action="store_true", help="keep every baseline (no redundant compression)")
        g.add_argument("--band-limit", choices=("cut", "marginalise", "truncate"), default="cut",
                       help="rows whose reach 2 pi (|b| + D) nu / c exceeds --lmax: cut them (default; the summary "
                       "says which lengths), marginalise the sky above lmax (its variance from the prior's C_l added "
                       "to the noise), or truncate (keep them: a control)")
        add_beam_prior_options(g)
    g.add_argument("--pol", default=None, metavar="pI|xx|yy|xx,yy",
                   help="modelled product: pseudo-Stokes I (xx + yy), one feed product, or xx and yy jointly; "
                   "ee / nn (ee,nn) name feed products through the file's x_orientation (east: ee = xx). "
                   "Default pI; with --gains sample the file's two feed products jointly (each feed has its own "
                   "gain: pI would mix them)")
    g.add_argument("--freq-range", nargs=2, type=positive_float("freq-range"), default=None, metavar=("LO", "HI"),
                   help="keep channels in [LO, HI] MHz")
    g.add_argument("--chans", type=_csv("chans", int), default=None, metavar="I,J,...", help="channel indices to keep")
    g.add_argument("--lst-range", nargs=2, type=finite_float("lst-range"), default=None, metavar=("START", "STOP"),
                   help="keep integrations with LST in [START, STOP] hours (START > STOP wraps through 0 h)")
    g.add_argument("--antennas", type=_csv("antennas", _antenna), default=None, metavar="A,B,...",
                   help="antenna numbers or names to keep")
    add_check_options(g, with_data=with_data)


def add_check_options(g, *, with_data: bool) -> None:
    """The data checks' options (docs/ingest.md: data checks, calibration, flux scale)."""
    g.add_argument("--cal", default=None, nargs="+", metavar="FILE",
                   help="gain solutions (calfits, calh5: any file UVCal reads) applied to the data first; antennas "
                   "matched by number; one file for all the data files, or one per data file in their order; "
                   "solutions at other times are interpolated linearly in time (pyuvdata)")
    g.add_argument("--flag-outliers", action=argparse.BooleanOptionalAction, default=True,
                   help="flag channels, baselines and times whose noise excess (time-difference scatter over the "
                   "autos' radiometer noise) is a robust outlier; inspect reports them either way")
    g.add_argument("--flux-scale", choices=("check", "accept", "off"), default="check",
                   help="the data's autos against the GSM's through the beam: check (refuse a ratio outside "
                   "0.5-2 where the amplitude is fixed; a check beside the inferred amplitude), accept (record it), "
                   "off")
    if not with_data:
        g.add_argument("--beam", default=None, metavar="FILE", help="beam file for the flux-scale check")
        g.add_argument("--dish-diameter", type=positive_float("dish-diameter"), default=None, metavar="D",
                       help="Gaussian beam of a D m dish for the flux-scale check")
        g.add_argument("--redundancy-tol", type=positive_float("redundancy-tol"), default=0.5, metavar="M",
                       help="tolerance (metres) on baseline vectors when counting unique baselines: above real "
                       "arrays' position scatter (0.16 m in HERA H1C), below their spacing (14.6 m)")


def add_beam_prior_options(g) -> None:
    """How a beam file is used and the prior's mean (:func:`gcrsky.instrument.beamprep.prepare_beam`)."""
    g.add_argument("--beam-normalization", choices=("peak", "physical"), default="peak",
                   help="peak (default): a beam the file calls 'physical' (directivity units) is divided by its peak "
                   "power, as calibrated visibilities assume; physical: use the file's numbers as they are")
    g.add_argument("--beam-freq-scaling", choices=("none", "lambda"), default=None,
                   help="a beam with one frequency used at others: none (the same pattern) or lambda (angular size "
                   "~ 1/frequency); required for such a beam")
    g.add_argument("--accept-x-orientation-mismatch", action="store_true",
                   help="run although the beam's feed x points elsewhere than the file's (a symmetric beam)")
    g.add_argument("--prior-mean", choices=("zero", "gsm"), default=None,
                   help="the prior's mean: zero or gsm (the GSM's coefficients at the data's frequencies, l <= 16), so "
                   "the sky the data do not see is the GSM rather than zero (default: gsm where the amplitude is "
                   "inferred, whose scale it anchors; zero otherwise)")
    g.add_argument("--amplitude", choices=("auto", "infer", "fixed"), default="auto",
                   help="the overall amplitude per channel (bandpass): auto (default: inferred with the sky where the "
                   "data are not absolutely calibrated: vis_units uncalib, or --cal solutions without a gain_scale; "
                   "fixed otherwise), infer, fixed (the data taken as calibrated)")
    g.add_argument("--model-sd", type=positive_float("model-sd"), default=None, metavar="S",
                   help="where the amplitude is inferred: the fractional uncertainty of the sky model's overall scale "
                   "(default 0.1, the GSM's stated accuracy; docs/amplitude.md)")


def _gain_modes(s: str) -> tuple:
    parts = s.split(",")
    try:
        modes = tuple(int(p) for p in parts)
    except ValueError:
        modes = ()
    if len(modes) not in (1, 2) or min(modes) < 1:
        raise argparse.ArgumentTypeError(f"gain-modes must be K or KF,KT (integers >= 1), got {s!r}")
    return modes * 2 if len(modes) == 1 else modes


def add_gain_options(g) -> None:
    """``--gains sample`` and the gain block's settings (:class:`gcrsky.run.GainSampling`)."""
    g.add_argument("--gains", choices=("auto", "off", "sample"), default="auto",
                   help="per-antenna gains sampled with the sky: auto (default: sampled where the amplitude is "
                   "inferred, off otherwise), off (the data's gains taken as right), sample")
    g.add_argument("--gain-modes", type=_gain_modes, default=None, metavar="KF[,KT]",
                   help="smooth modes per gain in frequency (delay) and time (fringe rate); one number sets both "
                   "(default: from the selection, gcrsky.run.gains.default_gain_modes: 2,2 -- constant and slope in "
                   "each -- plus one in frequency for each full 20 %% of fractional bandwidth (at most 4), 3 in time "
                   "over 12 h or more, never more than the channels or times)")
    g.add_argument("--gain-basis", choices=("dpss", "fourier", "legendre"), default=None,
                   help="the modes' basis (default legendre: polynomials, which hold a linear drift exactly)")
    g.add_argument("--gain-sigma", type=positive_float("gain-sigma"), default=0.05, metavar="S",
                   help="prior sd of each mode's coefficient: the rms fractional gain error (default 0.05)")
    g.add_argument("--gain-burn", type=int_at_least(2, "gain-burn"), default=200, metavar="N",
                   help="burn-in sweeps before the first kept draw (default 200)")
    g.add_argument("--gain-thin", type=int_at_least(1, "gain-thin"), default=1, metavar="N",
                   help="sweeps per kept draw (default 1)")
    g.add_argument("--gauge-moves", type=int_at_least(0, "gauge-moves"), default=4, metavar="N",
                   help="moves along the amplitude-sky gauge per sweep (default 4; 0: plain Gibbs)")


def add_beam_options(g) -> None:
    """``--beams sample`` and the beam block's settings (:class:`gcrsky.run.BeamSampling`)."""
    g.add_argument("--beams", choices=("off", "sample"), default="off",
                   help="every antenna's beam perturbation sampled with the sky (Zernike modes over the main lobe; "
                   "docs/beams.md): off (default: the nominal beam for every antenna), sample (every baseline kept; "
                   "the gains the file's unless --gains sample, the amplitude inferred or fixed as --amplitude says; the sky or data space per channel "
                   "at most 2500)")
    g.add_argument("--beam-modes", type=int_at_least(1, "beam-modes", 4), default=None, metavar="NMAX",
                   help="the highest Zernike radial order of the perturbations (default 2: tilts, defocus, "
                   "astigmatisms; 1: tilts, i.e. pointing, only)")
    g.add_argument("--beam-sigma", type=positive_float("beam-sigma"), default=None, metavar="S",
                   help="prior sd of each perturbation coefficient (fractional voltage change at 1.5 FWHM; "
                   "default 0.2: a 5 mrad pointing offset of a 14 m dish at 100-200 MHz is a tilt of ~0.1-0.3)")
    g.add_argument("--beam-freq-modes", type=int_at_least(1, "beam-freq-modes", 8), default=None, metavar="Q",
                   help="Legendre modes per coefficient across the band (default 1: constant)")
    g.add_argument("--beam-burn", type=int_at_least(0, "beam-burn"), default=None, metavar="N",
                   help="warm-up steps of the beam chain (default 20)")


def beam_sampling(args, amplitude=None, gains=None):
    """The :class:`gcrsky.run.BeamSampling` of the options (its defaults where not given), with the amplitude
    inferred where ``amplitude`` (an :class:`gcrsky.run.AmplitudeSampling`) is given and the gains sampled where
    ``gains`` (a :class:`gcrsky.run.GainSampling`) is, or None without ``--beams sample``."""
    if args.beams != "sample":
        return None
    from ..run.spec import BeamSampling

    kw = {k: v for k, v in (("nmax", args.beam_modes), ("sigma", args.beam_sigma),
                            ("freq_modes", args.beam_freq_modes), ("burn", args.beam_burn)) if v is not None}
    return BeamSampling(**kw, amplitude=amplitude, gains=gains)


def add_frequency_options(g) -> None:
    """``--freq-prior`` and its settings (:class:`gcrsky.run.FrequencyModel`)."""
    g.add_argument("--freq-prior", choices=("independent", "template", "basis", "kernel"), default="independent",
                   help="independent (default): each channel its own prior, sampled separately; template: one "
                   "power law (nu/nu0)^beta shared by all channels; basis: --freq-nbasis log-polynomial spectral "
                   "functions; kernel: a smooth covariance in log frequency (--freq-xi); the coupled priors sample "
                   "all channels jointly and inpaint fully flagged channels through their neighbours")
    g.add_argument("--freq-beta", type=finite_float("freq-beta"), default=None, metavar="B",
                   help="spectral index of the prior's standard deviation (default: fitted to how the prior's own "
                   "variance changes across the channels, e.g. the GSM's)")
    g.add_argument("--freq-xi", type=positive_float("freq-xi"), default=0.1, metavar="XI",
                   help="kernel: correlation length in natural log frequency (default 0.1: ~10 %% in frequency)")
    g.add_argument("--freq-nbasis", type=int_at_least(1, "freq-nbasis", 8), default=3, metavar="K",
                   help="basis: number of log-polynomial functions (default 3: power law, running, curvature)")
    g.add_argument("--freq-basis-sigma", type=positive_float("freq-basis-sigma"), default=0.1, metavar="S",
                   help="basis: prior sd of the k-th function's coefficient relative to the power law's, S^k "
                   "(default 0.1)")
    g.add_argument("--freq-nugget", type=_float_where("freq-nugget", lambda v: v >= 0 and math.isfinite(v),
                                                      "a non-negative finite number"), default=None, metavar="E",
                   help="relative variance each channel may have beyond the model (default: template and kernel "
                   "1e-6, basis 1e-3)")
    g.add_argument("--freq-fit", action="store_true",
                   help="kernel: fit its amplitude, beta and xi by maximum joint evidence before sampling")


#: The frequency block's options (dest, option) that need a coupled ``--freq-prior``.
FREQ_ONLY = (("freq_beta", "--freq-beta"), ("freq_xi", "--freq-xi"), ("freq_nbasis", "--freq-nbasis"),
             ("freq_basis_sigma", "--freq-basis-sigma"), ("freq_nugget", "--freq-nugget"), ("freq_fit", "--freq-fit"))


def check_frequency_options(parser, args) -> None:
    """The frequency block's options need a coupled ``--freq-prior`` (and the right one); channels then run jointly."""
    defaults = parser.parse_args(["run"])
    used = [opt for dest, opt in FREQ_ONLY if getattr(args, dest) != getattr(defaults, dest)]
    if args.freq_prior == "independent":
        if used:
            parser.error(f"{', '.join(used)} set a frequency prior: add --freq-prior template, basis or kernel")
        return
    wrong = {"template": ("--freq-xi", "--freq-nbasis", "--freq-basis-sigma", "--freq-fit"),
             "basis": ("--freq-xi", "--freq-fit"), "kernel": ("--freq-nbasis", "--freq-basis-sigma")}
    bad = [opt for opt in used if opt in wrong[args.freq_prior]]
    if bad:
        parser.error(f"{', '.join(bad)} do not apply to --freq-prior {args.freq_prior}")
    if channel_mode(args) is not None:
        parser.error(f"--freq-prior {args.freq_prior} couples the channels, so they are sampled together: drop "
                     "--by-channel, --devices and --num-processes")
    if getattr(args, "gains", "off") == "sample":
        parser.error(f"--freq-prior {args.freq_prior} is not combined with --gains sample yet")


def frequency_model(args):
    """The :class:`gcrsky.run.FrequencyModel` of the options, or None with ``--freq-prior independent``."""
    if args.freq_prior == "independent":
        return None
    from ..run.spec import FrequencyModel

    return FrequencyModel(prior=args.freq_prior, beta=args.freq_beta, xi=args.freq_xi, nbasis=args.freq_nbasis,
                          basis_sigma=args.freq_basis_sigma, nugget=args.freq_nugget, fit=args.freq_fit)


def amplitude_sampling(args):
    """The :class:`gcrsky.run.AmplitudeSampling` of the options (``--model-sd``)."""
    from ..run.spec import AmplitudeSampling

    return AmplitudeSampling() if args.model_sd is None else AmplitudeSampling(model_sd=args.model_sd)


def gain_sampling(args, applied: float = 1.0, prob=None):
    """The :class:`gcrsky.run.GainSampling` of the options, or None without ``--gains sample``.

    Modes and basis the options leave out follow the selection of ``prob`` (its channels and
    times: :func:`gcrsky.run.gains.default_gain_modes`, :data:`gcrsky.run.gains.DEFAULT_GAIN_BASIS`);
    without ``prob``, ``GainSampling``'s own defaults."""
    if args.gains != "sample":
        return None
    from ..run.gains import DEFAULT_GAIN_BASIS, default_gain_modes
    from ..run.spec import GainSampling

    kw = {}
    if args.gain_modes is not None:
        kw["modes"] = args.gain_modes
    elif prob is not None:
        kw["modes"] = default_gain_modes(prob.freqs_hz, prob.lsts_rad)
    if args.gain_basis is not None:
        kw["basis"] = args.gain_basis
    elif prob is not None:
        kw["basis"] = DEFAULT_GAIN_BASIS
    if getattr(args, "amplitude", None) == "fixed":  # the data are calibrated: q held at 1 (issue 38)
        from ..run.sampling import FIXED_SCALE_SD

        kw["scale_sd"], applied = FIXED_SCALE_SD, 1.0
    return GainSampling(**kw, sigma=args.gain_sigma, burn=args.gain_burn, thin=args.gain_thin,
                        gauge_moves=args.gauge_moves, applied=applied)


def _pol_of(pol: str):
    return tuple(pol.split(",")) if "," in pol else pol


def _selection_keywords(args) -> dict:
    """The selection options as :class:`gcrsky.ingest.Selection`'s keywords (MHz -> Hz)."""
    return dict(
        freq_chans=args.chans,
        freq_range_hz=None if args.freq_range is None else tuple(1e6 * x for x in args.freq_range),
        lst_range_hours=None if args.lst_range is None else tuple(args.lst_range),
        antennas=args.antennas,
        pol=_pol_of(args.pol or "pI"),
    )


#: The selection settings the command line sets (recorded in a run's settings, ``selection``).
CLI_SELECTION = ("freq_chans", "freq_range_hz", "lst_range_hours", "antennas", "pol")


def ingest_spec(args, *, run: bool):
    """The :class:`gcrsky.ingest.IngestSpec` of the parsed options: the one builder of ``run --data`` (``run``)
    and ``inspect`` (which has no prior, noise, compression, band-limit or beam-preparation options: the
    spec's defaults; its ``--flux-scale`` defaults to check, as a run's)."""
    from ..ingest.spec import IngestSpec

    kw = dict(lmax=args.lmax, nside=args.nside, beam=args.beam, dish_diameter_m=args.dish_diameter, cal=args.cal,
              flag_outliers=args.flag_outliers, flux_scale=args.flux_scale, **_selection_keywords(args))
    if run and getattr(args, "amplitude", None) in ("infer", "fixed"):
        kw["amplitude"] = args.amplitude
    if run:
        kw.update(prior=args.prior, prior_scale=args.prior_scale, noise=args.noise, compress=not args.no_compress,
                  band_limit=args.band_limit, beam_normalization=args.beam_normalization,
                  beam_freq_scaling=args.beam_freq_scaling,
                  accept_x_orientation_mismatch=args.accept_x_orientation_mismatch, prior_mean=args.prior_mean)
    return IngestSpec.from_keywords(**kw)
