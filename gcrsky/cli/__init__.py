"""The ``gcrsky`` command line (also ``python -m gcrsky``).

``gcrsky run`` reproduces the paper's standard case (or a scenario of its Table 1,
``--scenario NAME``, or a variant through options mirroring :class:`gcrsky.Config`):
simulate, Wiener-filter, draw GCR samples, and write ``results.h5`` (draws
appended batch by batch), the standard products ``posterior_mean.fits`` /
``posterior_std.fits`` (HEALPix maps), ``posterior_mean_alm.fits`` (healpy alm) and
``posterior_mean.skyh5`` (pyradiosky), ``summary.json`` and the paper's per-run
figures (Figs. 3-7: mode z-scores, sky maps, beam region, beam-centre slice,
correlation matrix and corner plot); see :mod:`gcrsky.run` (the run) and
:mod:`gcrsky.paper.report` (the paper's metrics and figures).

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
values (results are still written for diagnosis); 2 for bad arguments (argparse) and every
other user error -- a file that is missing, empty, corrupt or of another kind, an option out of
range, an output path that is a file or cannot be written, a full disk, too little memory for
the problem -- with one message naming the cause and what to do (``-v`` adds the traceback;
:mod:`gcrsky.cli.errors`);
3 when the output directory holds results that the command refuses to touch
(neither ``--resume`` nor ``--overwrite``) or ``--resume`` cannot continue
(different settings or inputs, unreadable ``results.h5``); 4 when the ``jax.distributed``
processes (``--coordinator``/``--num-processes``/``--process-id``) could not start
together: the coordinator could not be reached, or a process did not join, within
``--dist-timeout`` seconds (default 120), or process 0 cannot listen on the coordinator's
port or refuses a process (another ``--num-processes``, a process id taken); each waiting
process prints one line naming the address, its process id, the number of processes and
the timeout, with no traceback (:func:`gcrsky.parallel.init_distributed`); 5 when the run failed after its draws (the maps, products, figures or summary): the draws are kept in
``results.h5`` and ``--resume`` redoes the rest from them; 6 with ``--strict`` when the run completed
(everything written) but the goodness of fit (``summary.json``'s ``goodness_of_fit``,
:mod:`gcrsky.run.fit`) rejects the model in some channel.  Without ``--strict`` a rejected fit exits 0
and the terminal says in one WARNING line which channels were rejected, their chi^2/dof and tail; 130
after Ctrl-C (one line: the completed batches' draws are kept in ``results.h5``, ``--resume`` continues).
"""

from __future__ import annotations

import sys

from .errors import EXIT_USAGE, USER_ERRORS, out_of_memory, report_user_error
from .options import EXIT_DIST
from .parser import build_parser
from .runs import EXIT_REFUSED, EXIT_REJECTED

__all__ = ["EXIT_DIST", "EXIT_INTERRUPTED", "EXIT_REFUSED", "EXIT_TERMINATED", "EXIT_REJECTED", "EXIT_USAGE", "build_parser", "main"]

#: Exit status after Ctrl-C (128 + SIGINT, the shell's): a line says what was kept, no traceback.
EXIT_INTERRUPTED = 130
#: Exit status after SIGTERM (128 + 15; e.g. a batch system's time limit): the same line.
EXIT_TERMINATED = 143


class Terminated(BaseException):
    """SIGTERM arrived (raised by the handler :func:`main` installs, so that it ends as Ctrl-C does)."""


def _on_sigterm(signum, frame):
    raise Terminated


def _catch_sigterm():
    """Install :func:`_on_sigterm` for SIGTERM (main thread only); returns the previous handler, or None."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _on_sigterm)

#  One module per command, the parser and what they share:
#  - ``parser``: :func:`build_parser`, one builder per command (``set_defaults(func=...)``);
#  - ``options``: argument types and the shared option groups;
#  - ``setup``: process settings before JAX's first computation, logging;
#  - ``runs``: the RunSpec of the options, the run with progress bars, its report;
#  - ``cmd_run``, ``cmd_data``, ``cmd_inspect``, ``cmd_scenarios``: the commands;
#  - ``terminal``: bars, the run's report, refusal messages.


def main(argv=None) -> int:
    """Entry point of the ``gcrsky`` command; returns the exit status."""
    from ..base.extras import require
    from .setup import setup_logging

    require("tqdm", "cli", "the gcrsky command line")
    parser = build_parser()
    args = parser.parse_args(argv)
    args._argv = list(sys.argv[1:] if argv is None else argv)
    setup_logging(args.verbose)
    from ..parallel.rendezvous import DistributedInitError

    previous = _catch_sigterm()
    try:
        return args.func(args, parser)
    except (KeyboardInterrupt, Terminated) as e:  # Ctrl-C, SIGTERM: what was kept and how to go on, no traceback
        out = getattr(args, "out", None)
        kept = (f"the draws of every completed batch are in {out}/results.h5; the same command with --resume "
                "continues it" if out else "nothing was written")
        why = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted (Ctrl-C)"
        print(f"\ngcrsky: {why}: {kept}", file=sys.stderr)
        return EXIT_TERMINATED if isinstance(e, Terminated) else EXIT_INTERRUPTED
    except DistributedInitError as e:  # the processes did not start together: a message, not a traceback
        hint = "; --dist-timeout SECONDS sets how long to wait" if isinstance(e, TimeoutError) else ""
        print(f"gcrsky: jax.distributed: {e}{hint}", file=sys.stderr)
        return EXIT_DIST
    except USER_ERRORS as e:  # a bad file, option or path, a full disk, too little memory: a message, exit 2
        return report_user_error(e, getattr(args, "command", None) or "", getattr(args, "verbose", 0))
    except Exception as e:  # XLA's out-of-memory (an allocation no estimate foresaw): a message too, not a traceback
        oom = out_of_memory(e)
        if oom is None:
            raise
        return report_user_error(oom, getattr(args, "command", None) or "", getattr(args, "verbose", 0))
    finally:
        if previous is not None:
            import signal

            signal.signal(signal.SIGTERM, previous)
