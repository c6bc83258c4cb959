"""What ``gcrsky run`` and ``gcrsky run --data`` share: the :class:`~gcrsky.run.RunSpec` of the options,
the run with the command's progress bars, and its report on the terminal."""

from __future__ import annotations

import sys

from .options import channel_mode, frequency_model
from .terminal import StageBar, batch_bar, channel_bar, print_summary, refusal_message, stage_names

__all__ = ["EXIT_AFTER_DRAWS", "EXIT_REFUSED", "EXIT_REJECTED", "execute_with_bars", "existing_mode", "report_run",
           "run_spec"]

#: Exit status when the output directory's results are not ours to touch (see :mod:`gcrsky.cli`).
EXIT_REFUSED = 3
#: Exit status when a run failed after its draws (kept in results.h5; ``--resume`` finishes it).
EXIT_AFTER_DRAWS = 5
#: Exit status under ``--strict`` of a run that completed (everything written) but whose fit is rejected.
EXIT_REJECTED = 6


def existing_mode(args) -> str:
    """``RunSpec.output.existing`` of ``--resume`` / ``--overwrite``."""
    return "resume" if args.resume else ("overwrite" if args.overwrite else "refuse")


def run_spec(args, *, nsamples: int, method: str, tol: float, scenario: str | None = None, extra=None, gains=None,
             amplitude=None, sampling=None):
    """The :class:`~gcrsky.run.RunSpec` of ``gcrsky run``'s options (draws, output, channels, argv, gains,
    frequency prior); ``sampling``: a draw stage given as it is (e.g. :class:`gcrsky.run.Beams`)."""
    from ..run import Draws, Output, RunSpec, Solver
    from ..run.spec import sampling_of

    return RunSpec(Draws(nsamples, args.seed, args.batch), Output(args.out, existing_mode(args), not args.no_plots,
                                                                   bool(getattr(args, "trust_recorded", False))),
                   Solver(method, tol), sampling if sampling is not None else
                   sampling_of(channel_mode(args), gains, frequency_model(args), amplitude),
                   scenario=scenario, argv=getattr(args, "_argv", None), extra=extra)


def execute_with_bars(args, prob, spec, hooks, *, build_s: float, compile_since):
    """:func:`gcrsky.run.execute` with the command's bars: ``(summary, products)``, or an exit status
    (a refused run; a ``jax.distributed`` process other than 0, which writes nothing)."""
    from ..run import PostDrawError, ResumeError, RunExistsError, Watch, execute

    disable = True if args.no_progress else None  # tqdm's None: bars only on a terminal
    bar = StageBar(stage_names(spec.output.plots), disable)
    watch = Watch(on_stage=bar, progress=batch_bar(disable), channel_progress=channel_bar(disable))
    try:
        done = execute(prob, spec, hooks=hooks, watch=watch, build_s=build_s, compile_since=compile_since)
    except (RunExistsError, ResumeError) as e:  # e.g. the inputs differ from the recorded ones
        print(refusal_message(e, resume=args.resume), file=sys.stderr)
        return EXIT_REFUSED
    except PostDrawError as e:  # the draws are kept: a message with what to do, not a traceback
        print(f"gcrsky: {e}", file=sys.stderr)
        return EXIT_AFTER_DRAWS
    finally:
        bar.close()
    if done is None:
        print(f"gcrsky: process {args.process_id} of {args.num_processes}: computed its channels; process 0 "
              f"writes the results to {args.out}")
        return 0
    return done


def report_run(summary, products, out, *, strict: bool = False) -> int:
    """Print what the run did, its warnings (stderr), and return the exit status: 1 for non-finite draws;
    with ``strict`` (``--strict``), :data:`EXIT_REJECTED` when the goodness of fit rejects some channel; else 0."""
    if products.already_complete:
        missing = products.written
        print(f"gcrsky: the run in {out} was already complete; "
              + (f"rewrote the missing {', '.join(missing)}" if missing else "no file was missing"))
    print_summary(summary, out, products.written)
    for w in summary.warnings:
        print(w, file=sys.stderr)
    if not summary.draws_finite:
        print("gcrsky: the draws contain NaN/inf; exiting with status 1 (results written for diagnosis).",
              file=sys.stderr)
        return 1
    gof = summary.goodness_of_fit or {}
    if strict and gof.get("rejected"):
        print(f"gcrsky: --strict: the fit is rejected in {len(gof['rejected_channels'])} of {len(gof['chi2'])} "
              f"channels; exiting with status {EXIT_REJECTED} (everything is written)", file=sys.stderr)
        return EXIT_REJECTED
    return 0
