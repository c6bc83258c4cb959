"""The paper's report of a run: beam-region and truth metrics, and its figures, as a run-layer hook.

:class:`PaperReport` is a :class:`gcrsky.run.ReportHook`: after the draws it adds, per
frequency (:mod:`gcrsky.paper.metrics`):

- with a configuration (the observed strip, :func:`gcrsky.run.maps.observed_region`): the
  beam FWHM ``fwhm_deg`` and the posterior std by region (``std_*``, no truth needed);
  none of the region metrics where the FWHM is undefined (a beam whose power does not
  fall to half above the horizon: ``fwhm_deg`` None and a ``fwhm_note``);
- with a truth too: ``|mean - truth| / truth`` on the beam-centre ring and in the +-1 FWHM
  band, for the draws' mean and the Wiener filter (``frac_diff_*``, ``wiener_frac_diff_*``);
- with a truth: the per-mode z-scores' statistics (``mode_z``);

and its figures: the paper's Figs. 3-7 for a run with a truth (:func:`run_figures`), or the
posterior mean and std maps and the correlation (:func:`data_figures`) for one without.

The FWHM is the one a file's configuration records (:class:`gcrsky.ingest.DataConfig`), or the
one given to :class:`PaperReport` (a simulated configuration's beam:
:func:`gcrsky.paper.pipeline.paper_hooks`).  Nothing here imports :mod:`gcrsky.sim`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable

import numpy as np

from ..io.atomic import atomic_path
from ..run.report import FigureReport, ReportHook, RunView
from . import metrics as M

__all__ = ["FIGURE_FILES", "PaperReport", "data_figures", "run_figures"]

#: The per-run figures of the paper's report: ``{key: file name}`` (Figs. 3-7); :meth:`PaperReport.files`
#: declares them to the run, so they are refused, overwritten and resumed with its other files.
FIGURE_FILES = {
    "fig3": "fig3_alm_residuals.png",
    "fig4": "fig4_sky_maps.png",
    "fig5": "fig5_beam_region.png",
    "fig6": "fig6_slice.png",
    "fig7_correlation": "fig7_correlation.png",
    "fig7_corner": "fig7_corner.png",
}


@dataclasses.dataclass(frozen=True)
class PaperReport(ReportHook):
    """The paper's metrics and figures of a run (module doc).

    Attributes:
        fwhm_deg: ``(Nf,)`` beam FWHM per channel, degrees, for a configuration that does
            not record one (a simulated :class:`~gcrsky.sim.Config`); None: the
            configuration's ``fwhm_deg``.
    """

    fwhm_deg: tuple | None = None

    def _fwhm(self, cfg, f: int) -> float:
        recorded = getattr(cfg, "fwhm_deg", None)
        if recorded is not None:
            return float(recorded[f])
        if self.fwhm_deg is None:
            raise ValueError("PaperReport needs the beam FWHM of a configuration that records none (a simulation): "
                             "pass fwhm_deg, as gcrsky.paper.pipeline.paper_hooks does")
        return float(self.fwhm_deg[f])

    def files(self) -> dict:
        """The figures this hook may write: :data:`FIGURE_FILES`."""
        return dict(FIGURE_FILES)

    def metrics(self, view: RunView) -> list[dict]:
        """Per frequency: ``fwhm_deg``, ``std_*``, the truth metrics and ``mode_z`` where they apply."""
        return [self._channel(view, f) for f in range(len(view.per_freq))]

    def _channel(self, view: RunView, f: int) -> dict:
        cfg, maps = view.problem.config, view.maps
        centre_dec, ra_range = maps.centre_dec_deg, maps.ra_range_deg
        m = {}
        if cfg is not None:
            fwhm = self._fwhm(cfg, f)
            if not (np.isfinite(fwhm) and fwhm > 0):  # a beam that never falls to half above the horizon:
                m["fwhm_deg"] = None  # no +-1 FWHM band, so no region metrics (the run's products are not lost)
                m["fwhm_note"] = (f"no beam-region metrics: the beam's FWHM is {fwhm} (its power does not fall "
                                  "to half above the horizon)")
                cfg = None
            else:
                m["fwhm_deg"] = fwhm
        if cfg is not None:
            if bool(np.isfinite(maps.std_maps[f]).all()):  # metrics that need no truth: where the data constrain
                m.update(M.std_metrics(maps.std_maps[f], centre_dec, fwhm, ra_range))
            if maps.truth_maps is not None:
                truth = maps.truth_maps[f]
                m.update(M.summary_metrics(maps.mean_maps[f], truth, centre_dec, fwhm, ra_range,
                                           std_map=maps.std_maps[f]))
                wfm = M.summary_metrics(maps.wiener_maps[f], truth, centre_dec, fwhm, ra_range)
                m["wiener_frac_diff_centre_median"] = wfm["frac_diff_centre_median"]
                m["wiener_frac_diff_fwhm_median"] = wfm["frac_diff_fwhm_median"]
        if maps.mode_z is not None:
            m["mode_z"] = M.z_score_stats(maps.mode_z[f])
        return m

    def figures(self, view: RunView, out: Path, *, only_missing: bool) -> FigureReport:
        """Figs. 3-7 with a truth, the posterior maps without one; a note when neither applies."""
        maps = view.maps
        if (view.finite and maps.truth_maps is not None and maps.centre_dec_deg is not None
                and view.per_freq[view.shown].get("fwhm_deg") is not None):
            return FigureReport(run_figures(out, view, only_missing=only_missing), [])
        if view.finite and maps.truth_maps is None and maps.centre_dec_deg is not None:
            return FigureReport(data_figures(out, view, only_missing=only_missing), [])
        if maps.truth_maps is None:
            return FigureReport({}, ["NOTE: no figures: this problem has neither a truth nor a region (configuration)."])
        return FigureReport({}, [])


def _atomic_figure(out: Path, key: str, plot: Callable[[Path], object], only_missing: bool) -> str:
    """Write figure ``FIGURE_FILES[key]`` through ``plot(path)`` atomically (unless present and ``only_missing``)."""
    name = FIGURE_FILES[key]
    target = out / name
    if not (only_missing and target.exists()):
        with atomic_path(target) as tmp:
            plot(tmp)
    return name


def run_figures(out: Path, view: RunView, *, only_missing: bool = False) -> dict:
    """The paper's per-run figures (first frequency): Figs. 3-7 as PNG files in ``out`` (each written atomically).

    Needs a truth and a configuration (``view.maps.truth_maps``, ``centre_dec_deg``) and the
    first channel's metrics (``fwhm_deg``, ``frac_diff_*``: :class:`PaperReport`).

    Args:
        only_missing: keep figures already in ``out`` (a resumed run).

    Returns:
        ``{figure key: file name}`` (:data:`FIGURE_FILES`).
    """
    from . import figures as P

    ms = view.maps
    if ms.truth_maps is None or ms.centre_dec_deg is None:
        raise ValueError("the per-run figures compare with a truth and need the configuration's region")
    i = view.shown
    out, prob, draws, f0 = Path(out), view.problem, view.draws, view.per_freq[i]
    modes, truth, nsamples = prob.modes, np.asarray(prob.a_true), draws.shape[1]
    truth_map, mean_map, std_map = ms.truth_maps[i], ms.mean_maps[i], ms.std_maps[i]
    centre_dec, ra_range = ms.centre_dec_deg, ms.ra_range_deg
    scenario = view.scenario
    lab = (f"{scenario}: " if scenario else "") + f"{np.asarray(prob.freqs_hz)[i] / 1e6:g} MHz, {nsamples} draws"
    fig = lambda key, plot: _atomic_figure(out, key, plot, only_missing)  # noqa: E731
    names = {}
    names["fig3"] = fig("fig3", lambda p: P.plot_alm_residuals(
        ms.mode_z[i], modes.ell, modes.m, modes.is_imag, p,
        title=f"(posterior mean $-$ truth) / posterior std per mode, {lab}",
    ))
    names["fig4"] = fig("fig4", lambda p: P.plot_sky_maps(
        truth_map, mean_map, std_map, p, region=(centre_dec, f0["fwhm_deg"], ra_range),
        title=f"{lab}; green: $\\pm$1 FWHM band over the observed LSTs",
    ))
    names["fig5"] = fig("fig5", lambda p: P.plot_beam_region(
        M.frac_diff_map(mean_map, truth_map), p,
        centre_dec_deg=centre_dec, fwhm_deg=f0["fwhm_deg"], ra_range_deg=ra_range,
        title=f"(posterior mean $-$ truth) / truth near the beam, {lab}\nmedian |frac|: "
        f"{f0['frac_diff_centre_median']:.2%} on the centre ring, {f0['frac_diff_fwhm_median']:.2%} within "
        f"$\\pm$1 FWHM (observed RA range)",
    ))
    ra_ring, vals = M.ring_slice(np.abs(M.frac_diff_map(mean_map, truth_map)), prob.nside, centre_dec)
    names["fig6"] = fig("fig6", lambda p: P.plot_frac_slices(
        [(scenario or "this run", ra_ring, vals)], p, fwhm_deg=f0["fwhm_deg"],
        ra_range_deg=ra_range, dec_deg=centre_dec, title=f"|mean $-$ truth| / truth along the beam centre, {lab}",
    ))
    if nsamples >= 2:
        names["fig7_correlation"] = fig("fig7_correlation", lambda p: P.plot_correlation_matrix(
            draws[i], modes.ell, modes.m, modes.is_imag, p, title=f"posterior correlation (real parts), {lab}"))
        names["fig7_corner"] = fig("fig7_corner", lambda p: P.plot_corner(
            draws[i], truth[i], modes.ell, modes.m, modes.is_imag, p, m_value=2,
            title=f"marginal posteriors / truth at m = 2, {lab}",
        ))
    return names


def data_figures(out: Path, view: RunView, *, only_missing: bool = False) -> dict:
    """The figures of a run without a truth (real data), on its shown channel (:attr:`RunView.shown`: the first
    with data): the posterior mean and std maps with the observed strip outlined (``fig4``) and the posterior
    correlation (``fig7_correlation``), labelled with the channel and the maps' unit."""
    from . import figures as P

    i = view.shown
    out, prob, draws, ms, f0 = Path(out), view.problem, view.draws, view.maps, view.per_freq[i]
    unit = (view.units or {}).get("maps", "K")
    first = " (first channel with data)" if i else ""
    lab = f"{np.asarray(prob.freqs_hz)[i] / 1e6:g} MHz{first}, {draws.shape[1]} draws"
    region = None if f0.get("fwhm_deg") is None else (ms.centre_dec_deg, f0["fwhm_deg"], ms.ra_range_deg)
    fig = lambda key, plot: _atomic_figure(out, key, plot, only_missing)  # noqa: E731
    names = {"fig4": fig("fig4", lambda p: P.plot_posterior_maps(
        ms.wiener_maps[i], ms.std_maps[i], p, region=region, unit=unit,
        title=f"{lab}; green: $\\pm$1 FWHM band over the observed LSTs",
    ))}
    if draws.shape[1] >= 2:
        modes = prob.modes
        names["fig7_correlation"] = fig("fig7_correlation", lambda p: P.plot_correlation_matrix(
            draws[i], modes.ell, modes.m, modes.is_imag, p, title=f"posterior correlation (real parts), {lab}"))
    return names
