"""The paper's application: its scenarios, map metrics, figures and the run pipeline.

- ``scenarios``: the 16 runs of Table 1 as named configurations, the results table and
  the check of the paper's claims;
- ``metrics``: map-space accuracy in the beam region, ring slices, per-mode z-scores;
- ``figures``: the paper's Figs. 3-8 (matplotlib, the ``[plots]`` extra);
- ``pipeline``: one run (sample, summarise, plot, write): :func:`run_problem`;
- ``suite``: every scenario, the tables, claims and overlaid slices: :func:`run_suite`.

Submodules are imported on use (``from gcrsky.paper import pipeline``).
"""

__all__ = ["figures", "metrics", "pipeline", "scenarios", "suite"]
