"""``gcrsky run --data FILE``: the posterior of a visibility file's sky (no truth: no truth metrics).

The problem is read by :func:`gcrsky.ingest.ingest` (the :class:`~gcrsky.ingest.IngestSpec` of the options) and run by :func:`gcrsky.run.execute`
with the paper's beam-region metrics and posterior figures
(:class:`gcrsky.paper.report.PaperReport`; the beam FWHM is the file's configuration's).
Nothing here imports :mod:`gcrsky.sim`.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from ..io.files import check_input_file
from ..io.manyfiles import source_name
from ..run.sampling import AMPLITUDE_MODEL_SD
from ..solvers.options import DEFAULT_TOL
from .errors import report_user_error
from .options import CLI_SELECTION, DEFAULT_NSAMPLES, amplitude_sampling, beam_sampling, gain_sampling, ingest_spec
from .runs import EXIT_REFUSED, execute_with_bars, report_run, run_spec
from .terminal import band_limit_line, refusal_message

__all__ = ["data_command"]

#: ``gcrsky run`` options of a simulation that a run on a file does not use (dest, option).
SIM_ONLY = (("scenario", "--scenario"), ("lst_start", "--lst-start"), ("lst_stop", "--lst-stop"),
            ("n_lst", "--n-lst"), ("noise_scale", "--noise-scale"), ("flat_prior", "--flat-prior"),
            ("zero_prior_mean", "--zero-prior-mean"), ("date", "--date"), ("data_seed", "--data-seed"))


def data_command(args, parser) -> int:
    """``gcrsky run --data FILE``: check the options, then run (a bad file or option: a message, exit 2)."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    _check_data_options(parser, args)
    with logging_redirect_tqdm():
        try:
            return _run_data(args)
        except (ValueError, FileNotFoundError) as e:  # the file or the options: a message, not a traceback
            return report_user_error(e, "run --data", args.verbose)


def _check_data_options(parser, args) -> None:
    """A run on a file takes its beam from --beam or --dish-diameter and refuses the simulation's options."""
    defaults = parser.parse_args(["run"])
    used = [opt for dest, opt in SIM_ONLY if getattr(args, dest) != getattr(defaults, dest)]
    if used:
        parser.error(f"{', '.join(used)} describe a simulation; with --data the file says what was observed")
    if (args.beam is None) == (args.dish_diameter is None):
        parser.error("with --data give the beam: --beam FILE (any file UVBeam reads) or --dish-diameter D (a "
                     "Gaussian beam of that dish), one of them")
    if args.prior not in ("gsm", "flat") and not Path(args.prior).exists():
        parser.error(f"--prior {args.prior!r}: neither 'gsm', 'flat' nor an existing file")
    _expand_data(parser, args)
    files = [("--cal", c, "calibration file", False) for c in ([args.cal] if isinstance(args.cal, str) else
                                                                 args.cal or [])]
    files.append(("--beam", args.beam, "beam file", False))
    if args.prior not in ("gsm", "flat"):
        files.append(("--prior", args.prior, "prior file", False))
    for option, path, what, ms in files:
        if path is not None:
            try:  # exists, a regular non-empty file (a Measurement Set may be a directory), readable
                check_input_file(path, what, measurement_set=ms)
            except (OSError, ValueError) as e:
                parser.error(f"{option}: {e}")
    check_gain_options(parser, args)
    check_beam_options(parser, args)


def expand_inputs(args, dest: str = "data") -> None:
    """``--data`` (or inspect's files) and ``--cal`` as given (paths, globs, directories) -> the file (a str) or
    the files (a list).

    Raises:
        FileNotFoundError, ValueError: a missing, empty or twice-given file, or a count of --cal files that is
            neither one nor the data files' (the message names it).
    """
    from ..io.files import expand_data_paths

    files = expand_data_paths(getattr(args, dest))
    setattr(args, dest, files[0] if len(files) == 1 else files)
    if args.cal is not None:
        cals = list(args.cal) if isinstance(args.cal, (list, tuple)) else [args.cal]
        if len(cals) not in (1, len(files)):
            raise ValueError(f"--cal: {len(cals)} calibration files for {len(files)} visibility files: give one for "
                             "all, or one per visibility file in their order")
        args.cal = cals[0] if len(cals) == 1 else cals


def _expand_data(parser, args) -> None:
    """:func:`expand_inputs` for ``run --data``: a bad input is a usage error (exit 2)."""
    try:
        expand_inputs(args)
    except (OSError, ValueError) as e:
        parser.error(str(e) if str(e).startswith("--cal") else f"--data: {e}")


#: The gain block's options (dest, option) that mean something only with ``--gains sample``.
GAIN_ONLY = (("gain_modes", "--gain-modes"), ("gain_basis", "--gain-basis"), ("gain_sigma", "--gain-sigma"),
             ("gain_burn", "--gain-burn"), ("gain_thin", "--gain-thin"), ("gauge_moves", "--gauge-moves"))


def check_gain_options(parser, args) -> None:
    """The gain block's options need ``--gains sample``; ``--gains sample`` needs ``--data`` and a joint run."""
    defaults = parser.parse_args(["run"])
    if args.gains == "off" or (args.gains == "auto" and args.data is None):
        used = [opt for dest, opt in GAIN_ONLY if getattr(args, dest) != getattr(defaults, dest)]
        if used:
            parser.error(f"{', '.join(used)} set the gain block: add --gains sample")
        return
    if args.gains == "auto":
        return
    if args.data is None:
        parser.error("--gains sample samples the gains of a file's data: give --data FILE")


#: The beam block's options (dest, option) that mean something only with ``--beams sample``.
BEAM_ONLY = (("beam_modes", "--beam-modes"), ("beam_sigma", "--beam-sigma"), ("beam_freq_modes", "--beam-freq-modes"),
             ("beam_burn", "--beam-burn"))


def check_beam_options(parser, args) -> None:
    """The beam block's options need ``--beams sample``; ``--beams sample`` needs ``--data`` and a joint run (one
    chain over the channels); the gains may be sampled with it (``--gains sample``), the amplitude inferred."""
    if args.beams != "sample":
        used = [opt for dest, opt in BEAM_ONLY if getattr(args, dest) is not None]
        if used:
            parser.error(f"{', '.join(used)} set the beam block: add --beams sample")
        return
    if args.data is None:
        parser.error("--beams sample samples the beams of a file's antennas: give --data FILE")
    from .options import channel_mode

    if channel_mode(args) is not None or getattr(args, "freq_prior", "independent") != "independent":
        parser.error("--beams sample samples one chain over all channels: drop --by-channel, --devices, "
                     "--num-processes and --freq-prior")


def _beam_inputs(args) -> None:
    """``--beams sample`` keeps every baseline (two baselines of one separation no longer share a response once
    their antennas' beams differ) and holds the gains at the file's unless ``--gains sample`` asks for them
    (``--gains auto`` resolves to off: the gains' burn-in costs ``--gain-burn`` steps of the beam chain; the
    amplitude's ``auto`` is resolved as in any run, from the headers)."""
    if args.beams != "sample":
        return
    if args.gains == "auto":
        args.gains = "off"
        print("gcrsky: --beams sample: the gains are the file's (or --cal's); --gains sample samples them with the beams")
    if not args.no_compress:
        print("gcrsky: --beams sample: every baseline kept (beams are per antenna; redundant compression would "
              "average baselines whose beams differ)")
        args.no_compress = True


def _amplitude_inputs(args) -> bool:
    """Resolve ``--amplitude auto`` (from the file's and the calibration's headers) and ``--gains auto``; True when
    the amplitude is inferred (then ``--gains auto`` samples the gains too)."""
    from ..ingest.datachecks import amplitude_needed

    why = amplitude_needed(args.data, args.cal) if args.amplitude == "auto" else None
    infer = args.amplitude == "infer" or why is not None
    if args.amplitude == "auto":
        args.amplitude = "infer" if infer else "fixed"
    if args.gains == "auto":
        args.gains = "sample" if infer else "off"
    if infer:
        print(f"gcrsky: the overall amplitude per channel is inferred with the sky ({why or 'asked'}); the sky's scale "
              f"is anchored by the sky model (--prior-mean {args.prior_mean or 'gsm'}, its scale known to "
              f"{100 * (args.model_sd or AMPLITUDE_MODEL_SD):g} %)"
              + ("; per-antenna gains sampled too (--gains off to keep the file's)" if args.gains == "sample" else ""))
    return infer


def _gain_inputs(args) -> None:
    """``--gains sample`` reads every baseline (gains are per antenna; a redundant group averages baselines with
    different gains) and samples the overall amplitude (the flux-scale check's ratio starts it, not refuses it)."""
    if args.gains != "sample":
        return
    if args.pol is None:
        args.pol = _feed_products(args.data)
        if args.pol != "pI":
            print(f"gcrsky: --gains sample: the feed products modelled separately (--pol {args.pol}): each feed has its "
                  "own gain, and pseudo-Stokes I would mix the two feeds' (--pol pI to model it anyway)")
    if not args.no_compress:
        print("gcrsky: --gains sample: every baseline kept (gains are per antenna; redundant compression would "
              "average baselines with different gains)")
        args.no_compress = True
    if args.flux_scale == "check" and args.amplitude == "fixed":
        print("gcrsky: --gains sample: the overall amplitude is sampled; the flux-scale check's ratio is recorded "
              "and starts it (--flux-scale accept)")
        args.flux_scale = "accept"


def _feed_products(data) -> str:
    """The file's two feed products as ``--pol`` names them (``"xx,yy"``, or ``"ee,nn"`` where the file names them
    so), its one feed product, or ``"pI"`` where it has neither (or its header cannot be read here: the reader
    says why later)."""
    from pyuvdata import UVData

    from ..io.manyfiles import first_file

    try:
        pols = set(UVData.from_file(str(first_file(data)), read_data=False).get_pols())
    except Exception:  # noqa: BLE001 - any unreadable header: ingest reports it with the file's name
        return "pI"
    for pair in (("xx", "yy"), ("ee", "nn")):
        have = [p for p in pair if p in pols]
        if have:
            return ",".join(have)
    return "pI"


def _applied_amplitude(prob) -> float:
    """The gains' starting amplitude: the square root of the flux-scale check's ratio (data autos / GSM autos),
    1 where the check did not run."""
    import math

    ratio = (prob.config.checks.get("flux_scale") or {}).get("ratio")
    return math.sqrt(ratio) if ratio is not None and math.isfinite(ratio) and ratio > 0 else 1.0


def _file_digest(path):
    """SHA-256 of a file (what a resumed run on a file must find unchanged); of several files, the list."""
    import hashlib

    if isinstance(path, (list, tuple)):
        return [_file_digest(p) for p in path]
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _data_settings(args, spec) -> dict:
    """The settings that identify a run on a file (``RunSpec.extra``): the file, its digest and the
    :class:`~gcrsky.ingest.IngestSpec`'s settings (beam, prior, noise, band limit, checks, selection)."""
    kw = spec.keywords()
    data = [str(Path(p).resolve()) for p in args.data] if isinstance(args.data, list) else str(Path(args.data).resolve())
    return {"data_file": data, "data_sha256": _file_digest(args.data),
            "beam": kw["beam"], "dish_diameter": kw["dish_diameter_m"], "prior": kw["prior"],
            "prior_scale": kw["prior_scale"], "noise": kw["noise"], "compress": kw["compress"],
            "lmax": kw["lmax"], "nside": kw["nside"], "band_limit": kw["band_limit"],
            **{k: kw[k] for k in ("beam_normalization", "beam_freq_scaling", "accept_x_orientation_mismatch",
                                  "prior_mean", "cal", "flag_outliers", "flux_scale", "amplitude")},
            "cal_sha256": _file_digest(args.cal) if args.cal else None,
            "selection": {k: (list(kw[k]) if isinstance(kw[k], tuple) else kw[k]) for k in CLI_SELECTION}}


def _read_problem(args, spec):
    """``(problem, beams)``: the :class:`~gcrsky.model.Problem` of the file and its nominal beams, one per antenna
    (:func:`gcrsky.ingest.ingest_with_beams`; the beam a path: its file is recorded)."""
    from ..ingest.uvdata import ingest_with_beams

    return ingest_with_beams(args.data, spec)


def _run_data(args) -> int:
    """Refuse a used --out before reading the file (--resume is checked once the problem is built: its
    recorded settings include what the file said), read it, run it."""
    from .setup import setup_jax

    compile0 = setup_jax(args)
    from ..paper.report import PaperReport
    from ..run import RunExistsError, check_out_dir, check_unlocked, existing_run_files

    _beam_inputs(args)
    infer = _amplitude_inputs(args)
    _gain_inputs(args)
    ingested = ingest_spec(args, run=True)
    spec = run_spec(args, nsamples=args.nsamples or DEFAULT_NSAMPLES, method=args.method or "auto",
                    tol=args.tol or DEFAULT_TOL, extra=_data_settings(args, ingested))
    out = spec.output.out
    if not args.process_id:
        check_out_dir(out)  # a writable directory (the message says what is wrong)
        try:
            check_unlocked(out)  # another run writes there (execute's lock is what excludes)
        except RunExistsError as e:
            print(refusal_message(e, resume=args.resume), file=sys.stderr)
            return EXIT_REFUSED
    if spec.output.existing == "refuse" and not args.process_id:
        taken = existing_run_files(out)
        if taken:
            print(refusal_message(RunExistsError(out, taken), resume=False), file=sys.stderr)
            return EXIT_REFUSED
    t0 = time.perf_counter()
    prob, nominal = _read_problem(args, ingested)
    build_s = time.perf_counter() - t0
    cfg = prob.config
    print(f"gcrsky: {source_name(args.data if isinstance(args.data, list) else [args.data])}: "
          f"{len(cfg.conventions['antenna_numbers'])} antennas, {prob.data.shape[2]} rows "
          f"({'compressed' if cfg.compressed else 'all baselines'}), {prob.data.shape[1]} times, "
          f"{prob.data.shape[0]} channels, {cfg.pol}; prior: {cfg.prior}")
    print(band_limit_line(cfg.checks.get("band_limit")))
    if args.beams == "sample":
        from ..run.sampling import Beams

        spec = run_spec(args, nsamples=spec.draws.nsamples, method=spec.solver.method, tol=spec.solver.tol,
                        extra=spec.extra,
                        sampling=Beams(beam_sampling(args, amplitude_sampling(args) if infer else None,
                                                     gain_sampling(args, prob=prob)), nominal=nominal))
        b = spec.sampling.beams
        g = b.gains
        print(f"gcrsky: beams sampled with the sky: Zernike orders 1-{b.nmax} ({b.freq_modes} frequency mode(s)) per "
              f"antenna, prior sd {b.sigma:g} (array mean {b.mean_sigma:g}), warm-up {b.burn} steps"
              + ("; the overall amplitude per channel with them" if infer else "")
              + ("" if g is None else f"; gains with them: {g.modes[0]} x {g.modes[1]} {g.basis} modes per gain, prior "
                                      f"sd {g.sigma:g}, fitted with the beams (no burn-in), thinned by {g.thin}")
              + "; the draws are a Markov chain's")
    elif infer:
        spec = run_spec(args, nsamples=spec.draws.nsamples, method=spec.solver.method, tol=spec.solver.tol,
                        extra=spec.extra, gains=gain_sampling(args, prob=prob), amplitude=amplitude_sampling(args))
        g = spec.sampling.amplitude.gains
        print("gcrsky: amplitude inferred per channel (exact marginal, then the sky given it)"
              + ("; the draws are independent" if g is None else
                 f"; gains sampled with the sky: {g.modes[0]} x {g.modes[1]} {g.basis} modes per gain, prior sd "
                 f"{g.sigma:g}, burn-in {g.burn} sweeps; the draws are a Markov chain's"))
    elif args.gains == "sample":
        spec = run_spec(args, nsamples=spec.draws.nsamples, method=spec.solver.method, tol=spec.solver.tol,
                        extra=spec.extra, gains=gain_sampling(args, _applied_amplitude(prob), prob))
        how = "" if args.gain_modes is not None else " (from the channels and time span)"
        print(f"gcrsky: gains sampled with the sky: {spec.gains.modes[0]} x {spec.gains.modes[1]} "
              f"{spec.gains.basis} modes per gain{how}, "
              f"prior sd {spec.gains.sigma:g}, starting amplitude {spec.gains.applied:.4g}, burn-in {spec.gains.burn}"
              f" sweeps; the draws are a Markov chain's")
    else:
        from ..run.memoryplan import fit_in_memory

        plan = fit_in_memory(prob, spec)  # one channel at a time where all at once does not fit a direct path
        if plan.note:
            print(f"gcrsky: {plan.note}")
        spec = plan.spec
    done = execute_with_bars(args, prob, spec, (PaperReport(),), build_s=build_s, compile_since=compile0)
    return done if isinstance(done, int) else report_run(*done, out, strict=args.strict)
