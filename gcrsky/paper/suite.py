"""The paper's whole scenario suite (Table 1): every run, the results table, the claims, the overlaid slices.

:func:`run_suite` is what ``gcrsky scenarios`` does: each scenario is built
(sharing the response wherever the instrument is shared) and run by
:func:`gcrsky.run.execute` with the paper's hooks (:func:`gcrsky.paper.pipeline.paper_hooks`)
into ``out/NAME/``; then ``results.md``,
``results.csv``, ``claims.md``, ``suite.json`` and the slice figures of Figs. 6 and 8
are written to ``out``.  Nothing here prints; :class:`SuiteResult` carries the text.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, NamedTuple

import numpy as np

from ..io.results import write_json
from ..run import Draws, Output, RunSpec, Solver, execute, versions
from ..sim.standard import problem_from_config
from . import metrics as M
from .pipeline import paper_hooks
from .scenarios import (
    SCENARIOS,
    claims_markdown,
    evaluate_claims,
    result_row,
    results_csv,
    results_markdown,
    scenario_config,
)
from .scenarios import scenario as get_scenario

__all__ = ["SLICE_GROUPS", "SuiteResult", "run_suite", "slice_figures", "suite_names"]

#: Groups of runs overlaid in the slice figures (the paper's Figs. 6 and 8).
SLICE_GROUPS = (
    ("A", "fig6_slices_A1.png", ("standard", "A1")),
    ("B", "fig6_slices_B.png", ("standard", "B1", "B2", "B3", "B4", "B5", "B6", "B7", "B8")),
    ("C", "fig8_slices_C.png", ("standard", "C1", "C2", "C3", "C4", "C5")),
    ("D", "fig8_slices_D1.png", ("standard", "D1")),
)


class SuiteResult(NamedTuple):
    """What :func:`run_suite` wrote: the table rows, the claims, the Markdown text and figure names."""

    rows: list
    claims: list
    markdown: str
    claims_markdown: str
    figures: list
    wall_s: float


def suite_names(names) -> list[str]:
    """The scenarios to run, canonical names (all when ``names`` is empty); ValueError for
    unknown or repeated ones."""
    names = [get_scenario(n).name for n in names] or list(SCENARIOS)
    if len(set(names)) != len(names):
        raise ValueError(f"scenario names repeat: {names}")
    return names


def slice_figures(prods: dict, out: Path) -> list[str]:
    """The slice figures of every group with at least two runs present; returns the file names.

    ``prods``: ``{scenario name: gcrsky.run.RunProducts}``."""
    from . import figures as P

    written = []
    for _, fname, members in SLICE_GROUPS:
        have = [n for n in members if n in prods]
        if len(have) < 2 and not (len(have) == 1 and len(members) == 1):
            continue
        ref = prods["standard"] if "standard" in prods else prods[have[0]]
        curves = []
        for n in have:
            p = prods[n]
            nside = int(np.sqrt(p.mean_map.size / 12))
            absfrac = np.abs(M.frac_diff_map(p.mean_map, p.truth_map))
            ra, vals = M.ring_slice(absfrac, nside, p.centre_dec_deg)
            same = tuple(p.ra_range_deg) == tuple(ref.ra_range_deg)
            curves.append((n, ra, vals) if same else (n, ra, vals, p.ra_range_deg))
        P.plot_frac_slices(curves, Path(out) / fname, fwhm_deg=ref.fwhm_deg, ra_range_deg=ref.ra_range_deg,
                           dec_deg=ref.centre_dec_deg,
                           title="|posterior mean - truth| / truth along the beam-centre declination")
        written.append(fname)
    return written


def run_suite(
    names,
    out,
    *,
    nside: int,
    nsamples: int | None = None,
    seed: int = 0,
    batch: int = 50,
    plots: bool = True,
    argv=None,
    progress: Callable | None = None,
    on_result: Callable[[str, dict, dict], None] | None = None,
) -> SuiteResult:
    """Run the named scenarios into ``out/NAME/`` and write the suite's tables and figures.

    Args:
        names: scenario names (canonical, e.g. from :func:`suite_names`).
        out: output directory (created if needed).
        nside: HEALPix nside of every run.
        nsamples: draws per scenario (default: each scenario's own).
        seed, batch: the draws' seed and batch size (as ``gcrsky run``).
        plots: write the figures.
        argv: the command line (recorded).
        progress: wrapper of the scenario-name iterable (e.g. a tqdm bar).
        on_result: called as ``on_result(name, row, summary)`` after each scenario
            (``summary``: its :class:`gcrsky.run.RunSummary`).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cache: dict = {}
    rows, prods = {}, {}
    t_suite = time.perf_counter()
    for name in progress(names) if progress else names:
        sc = get_scenario(name)
        t0 = time.perf_counter()
        prob = problem_from_config(scenario_config(name, nside=nside), response_cache=cache)
        build_s = time.perf_counter() - t0
        (out / name).mkdir(parents=True, exist_ok=True)
        spec = RunSpec(Draws(nsamples or sc.nsamples, seed, batch), Output(out / name, plots=plots),
                       Solver(sc.method, sc.tol), scenario=name, argv=argv)
        summary, prod = execute(prob, spec, hooks=paper_hooks(prob), build_s=build_s)
        row = result_row(name, summary.to_json(), prod.z)
        reg = M.summary_metrics(prod.mean_map, prod.truth_map, prod.centre_dec_deg, prod.fwhm_deg, (0.0, 120.0))
        row["fwhm_median_0_8h"] = reg["frac_diff_fwhm_median"]
        rows[name] = row
        prods[name] = prod._replace(draws=None)  # keep the suite's memory small
        if on_result:
            on_result(name, row, summary)
    total = time.perf_counter() - t_suite
    table = [rows[n] for n in names]
    claims = evaluate_claims(rows)
    head = (
        f"# gcrsky scenario suite\n\n{len(names)} scenarios, nside {nside}, seed {seed}; "
        f"wall time {total:.0f} s in all (one process, JIT compilation included).  Metrics at the first "
        "frequency (100 MHz): |posterior mean - truth| / |truth| of the maps along the beam-centre ring and "
        "in the +-1 FWHM band over the observed RA range, the fraction of the whole sky within 10%, and "
        "per-mode z = (mean - truth) / std of the draws.  CG iterations are per draw (0: dense sampler).\n\n"
    )
    md = head + results_markdown(table)
    cmd = claims_markdown(claims)
    (out / "results.md").write_text(md)
    (out / "results.csv").write_text(results_csv(table))
    (out / "claims.md").write_text("# The paper's claims, checked by this suite\n\n" + cmd)
    figures = slice_figures(prods, out) if plots else []
    write_json(out / "suite.json", {"scenarios": list(names), "rows": table, "claims": [c._asdict() for c in claims],
                                    "wall_s": total, "nside": nside, "seed": seed, "figures": figures,
                                    "versions": versions()})
    return SuiteResult(table, claims, md, cmd, figures, total)
