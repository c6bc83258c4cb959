"""``gcrsky scenarios [NAME ...]``: the paper's scenario suite (:func:`gcrsky.paper.suite.run_suite`)."""

from __future__ import annotations

import sys
from pathlib import Path

from .runs import EXIT_REFUSED

__all__ = ["scenarios_command"]


def scenarios_command(args, parser) -> int:
    """``--list``, or run the named scenarios (unknown names: a usage error)."""
    from tqdm.contrib.logging import logging_redirect_tqdm

    from ..paper.suite import suite_names

    try:
        suite_names(args.names)
    except ValueError as e:
        parser.error(str(e))
    with logging_redirect_tqdm():
        return _scenarios(args)


def _list() -> int:
    from ..paper.scenarios import SCENARIOS

    for sc in SCENARIOS.values():
        extra = ", ".join(f"{k}={v}" for k, v in sc.overrides) or "-"
        print(f"{sc.name:9s} {sc.varies:28s} draws {sc.nsamples:5d}  method {sc.method:5s}  Config: {extra}")
    return 0


def _refused(args, names) -> bool:
    """Scenario directories that hold a run's files: refused (message, True) unless ``--overwrite`` (cleared)."""
    from ..paper.report import FIGURE_FILES
    from ..run import existing_run_files, remove_run_files

    figures = tuple(FIGURE_FILES.values())

    taken = {n: existing_run_files(Path(args.out) / n, figures) for n in names}
    taken = {n: f for n, f in taken.items() if f}
    if taken and not args.overwrite:
        what = "; ".join(f"{Path(args.out) / n}: {', '.join(f)}" for n, f in taken.items())
        print(f"gcrsky: scenario directories already hold results ({what}); pass --overwrite to replace them "
              f"(or choose another --out; to continue one killed scenario: gcrsky run --scenario NAME --resume "
              f"--out {Path(args.out) / 'NAME'} with the suite's --nside, --nsamples, --seed and --batch).",
              file=sys.stderr)
        return True
    for n in taken:
        remove_run_files(Path(args.out) / n, figures)
    return False


def _on_result(name, row, summary) -> None:
    from tqdm.auto import tqdm

    tqdm.write(
        f"{name:9s} centre {100 * row['centre_median']:7.2f}%  +-1 FWHM {100 * row['fwhm_median']:7.2f}%  "
        f"sky<10% {100 * row['sky_within_10pct']:5.1f}%  |z|>15: {row['z_beyond_15']:3d}  "
        f"{row['wall_s']:6.1f} s" + ("" if summary.solver["all_converged"] else "  (NOT CONVERGED)")
    )


def _scenarios(args) -> int:
    if args.list:
        return _list()
    from ..paper.suite import run_suite, suite_names
    from .setup import setup_jax
    from .terminal import compile_line, compile_of

    names = suite_names(args.names)
    compile0 = setup_jax(args)
    if _refused(args, names):
        return EXIT_REFUSED
    from tqdm.auto import tqdm

    bars = []

    def progress(it):
        bars.append(tqdm(it, desc="scenarios", unit="run", disable=True if args.no_progress else None, leave=False))
        return bars[-1]

    res = run_suite(names, args.out, nside=args.nside, nsamples=args.nsamples, seed=args.seed, batch=args.batch,
                    plots=not args.no_plots, argv=getattr(args, "_argv", None), progress=progress,
                    on_result=_on_result)
    for bar in bars:
        bar.close()
    print(res.markdown)
    print(res.claims_markdown)
    print(f"wrote {args.out}/results.md, results.csv, claims.md, suite.json"
          + (", " + ", ".join(res.figures) if res.figures else ""))
    print(compile_line(compile_of(compile0), "compile (all scenarios)"))
    return 0
