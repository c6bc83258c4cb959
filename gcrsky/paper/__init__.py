"""The paper's application: its scenarios, map metrics, figures and its report of a run.

- ``scenarios``: the 16 runs of Table 1 as named configurations, the results table and
  the check of the paper's claims;
- ``metrics``: map-space accuracy in the beam region, ring slices, per-mode z-scores;
- ``figures``: the paper's Figs. 3-8 (matplotlib, the ``[plots]`` extra);
- ``report``: :class:`~gcrsky.paper.report.PaperReport`, the report hook a run
  (:func:`gcrsky.run.execute`) takes: the paper's metrics and per-run figures;
- ``pipeline``: :func:`~gcrsky.paper.pipeline.paper_hooks` for a problem (simulated or
  read from a file) and the compatibility form :func:`~gcrsky.paper.pipeline.run_problem`;
- ``suite``: every scenario, the tables, claims and overlaid slices: :func:`run_suite`.

Submodules are imported on use (``from gcrsky.paper import report``).
"""

__all__ = ["figures", "metrics", "pipeline", "report", "scenarios", "suite"]
