"""What a run reports: :class:`RunSummary` (``summary.json``) and :class:`RunProducts` (in memory).

``summary.json`` is written from a :class:`RunSummary` (:meth:`RunSummary.to_json`: its
fields in order, as the file's keys) and read back by :meth:`RunSummary.from_json`.
:func:`solver_summary` is its ``solver`` block (iterations, errors, convergence, the
eigen path's rank) with the warnings it implies; :func:`versions` its ``versions``.
"""

from __future__ import annotations

import dataclasses
import json
import platform
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

__all__ = ["RunProducts", "RunSummary", "first_data_channel", "fixed_flux_scale", "info_stats", "map_units", "read_summary",
           "shown_channel", "solver_summary", "versions"]

METRICS_NOTE = (
    "metrics at the shown channel (shown_channel: the first with data); |mean - truth|/|truth| of the "
    "posterior-mean map (sample mean of the draws) over the beam-centre ring (the HEALPix ring nearest dec = site latitude) and the +-1 FWHM band, "
    "both within RA = 15 x LST range; FWHM measured from the simulated beam's power pattern; "
    "per_frequency has every channel; the two top-level frac_diff_* keys repeat the shown channel's"
)
TIMINGS_NOTE = (
    "wall-clock seconds; 'wiener' and the first draw batch include JIT compilation; "
    "compile_s: XLA compilation in all stages (build included when the caller counted from before it), a "
    "program loaded from JAX's persistent compilation cache counting its loading time; cache_hits / "
    "cache_misses: programs loaded from / compiled despite that cache (both 0 when it is off; see 'compile'); "
    "the set-up (P, its Cholesky factor or CG preconditioner, the Wiener filter) is done once, in 'wiener'; "
    "a resumed run times only its own stages (draw_batches_s covers every batch)"
)
COMPILE_NOTE = (
    "this run's JAX compilation (gcrsky.parallel.compile_stats): compile_s backend compilation or loading from "
    "the persistent cache (cache_dir; null: off), trace_s tracing, lower_s lowering to MLIR (seconds, inside the "
    "stages' wall-clock times); programs compiled or loaded, cache_hits loaded from the cache, cache_misses "
    "compiled with the cache on, cache_writes entries written"
)
PRODUCTS_NOTE = (
    "posterior_mean.* are the Wiener filter (the exact posterior mean), not the draws' mean; posterior_std.fits "
    "(and the skyh5's stokes_error) is the per-pixel std over the draws (ddof 1); HEALPix RING, K, frame: "
    "'icrs' for real observing times, 'idealised' for the co-rotating frame of idealised LSTs (COORDSYS 'C')"
)


@dataclasses.dataclass(frozen=True)
class RunSummary:
    """The summary of one run, field for field the keys of ``summary.json`` (in this order).

    Attributes:
        frac_diff_centre_median, frac_diff_fwhm_median: the first channel's truth metrics
            (None without a report hook that computes them).
        metrics: the first channel's metrics; per_frequency: every channel's
            (``freq_hz`` and what the report hooks added).
        region: the observed strip (``centre_dec_deg``, ``ra_range_deg``, ``fwhm_deg`` per
            channel), or None without a configuration.
        solver: :func:`solver_summary`'s block; draws_finite: every draw is finite.
        warnings: what the terminal should say (solver, non-finite draws, report hooks).
        timings_s: seconds per stage, the batches' seconds, compilation.
        compile: the run's JAX compilation and cache use.
        run: nsamples, seed, batch, the path that ran, scenario, argv, resumed_at_batch, frame.
        figures: ``{key: file name}`` the report hooks wrote.
        products: ``{key: file name}`` of the products and ``results.h5``.
        config: the problem's configuration (its ``to_dict()``), or None.
        sky_note: where the problem's sky came from; versions: :func:`versions`.
        exit_status: 0, or 1 when a draw is not finite.
        *_note: what the blocks mean, in words.
        data_checks: what the ingest checked and decided about a file's data (the
            configuration's ``checks``: beam, calibration, flux scale, flags, band limit, prior),
            or None for a simulated run.
        goodness_of_fit: the posterior predictive check of the data against the model, or
            None where it was not computed.
        gains: a run that samples the gains with the sky: their settings, the posterior flux
            scale, the phase gradients against their prior (:func:`gcrsky.run.gains.gain_summary`);
            None otherwise.
        channels: the channels and their model (:func:`gcrsky.run.frequency.channels_block`): the
            frequency model, which channels are fully or partly flagged, each channel's unflagged
            fraction, where a flagged channel's posterior comes from, and a frequency prior's settings.
        flux_scale: a run on a file: the amplitude ``q`` per channel (``data = q x`` the sky model's
            visibilities in K): its posterior median and 95 % interval where inferred
            (:func:`gcrsky.run.amplitude.amplitude_summary`), 1 where fixed; the autos' ratio beside it
            and ``source`` (``"inferred"``, ``"fixed"``); None for a simulated run.
        amplitude: a run that infers the amplitude: its settings and the ESS of every sampled scalar.
        beams: a run that samples every antenna's beam with the sky: the block's evidence against the nominal
            beams, the nominal beams' fit, each antenna's coefficients, the chain's diagnostics
            (:func:`gcrsky.run.beams.beam_summary`); None otherwise.
        shown_channel: the channel whose metrics are the top-level ones and whose maps the figures and
            :class:`RunProducts` show (:func:`shown_channel`: the first with unflagged data).
        units: what the maps are in (:func:`map_units`): ``maps`` (``"K"``, or ``"K x q"`` on the data's
            own scale), ``flux_scale`` (``"simulation"``, ``"inferred"``, ``"fixed"``, ``"accepted"``) and a note.
    """

    frac_diff_centre_median: float | None
    frac_diff_fwhm_median: float | None
    metrics: dict
    metrics_note: str
    per_frequency: list
    region: dict | None
    solver: dict
    draws_finite: bool
    warnings: list
    timings_s: dict
    compile: dict | None
    run: dict
    figures: dict
    products: dict
    products_note: str
    config: dict | None
    sky_note: str | None
    versions: dict
    exit_status: int
    data_checks: dict | None = None
    goodness_of_fit: dict | None = None
    gains: dict | None = None
    channels: dict | None = None
    flux_scale: dict | None = None
    amplitude: dict | None = None
    beams: dict | None = None
    shown_channel: dict | None = None
    units: dict | None = None

    def to_json(self) -> dict:
        """The ``summary.json`` object: ``{field: value}`` in field order."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    @classmethod
    def from_json(cls, d: dict) -> RunSummary:
        """The summary of a ``summary.json`` object (a key this gcrsky did not write yet is None).

        Raises:
            ValueError: ``d`` has keys that are not fields.
        """
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(d) - set(names))
        if unknown:
            raise ValueError(f"not keys of a run summary: {', '.join(unknown)}")
        return cls(**{k: d.get(k) for k in names})


def fixed_flux_scale(prob) -> dict | None:
    """The ``flux_scale`` block of a run on a file whose amplitude is fixed: ``q = 1`` per channel (the data taken
    as calibrated), the autos' ratio beside it; None for a problem without data checks (a simulation)."""
    checks = getattr(getattr(prob, "config", None), "checks", None)
    if not checks:
        return None
    flux = checks.get("flux_scale") or {}
    autos = flux.get("ratio_per_channel") or []
    amp = checks.get("amplitude") or {}
    return {"source": "fixed", "why": amp.get("why", "the data are taken as calibrated"),
            "per_channel": [{"freq_hz": float(f), "median": 1.0, "lo95": 1.0, "hi95": 1.0,
                             "autos_ratio": autos[i] if i < len(autos) else None}
                            for i, f in enumerate(np.asarray(prob.freqs_hz))],
            "autos_ratio": flux.get("ratio")}


def first_data_channel(prob) -> int:
    """Index of the first channel with an unflagged sample (0 where every channel is flagged)."""
    w = np.asarray(prob.system().inv_noise)
    has = np.any(w.reshape(w.shape[0], -1) > 0, axis=1)
    return int(np.argmax(has)) if has.any() else 0


def shown_channel(prob, index: int) -> dict:
    """``summary.json``'s ``shown_channel``: the index, frequency and why that channel is shown."""
    nf = int(np.asarray(prob.freqs_hz).size)
    why = "the first channel" if index == 0 else f"the first channel with data (channels 0-{index - 1} are flagged)"
    if index == 0 and nf and not np.any(np.asarray(prob.system().inv_noise)[0] > 0):
        why = "every channel is flagged: the prior's"
    return {"index": int(index), "freq_hz": float(np.asarray(prob.freqs_hz)[index]), "why": why}


def map_units(prob, flux_scale: dict | None = None) -> dict:
    """``summary.json``'s ``units``: what the maps (and FITS products) are in.

    A simulation, a run that infers the amplitude (the draws are the sky in K) and a run on data calibrated
    in Jy are in K; a run that accepted an uncalibrated flux scale (``--flux-scale accept``) is on the
    data's own scale, ``q`` x K (``q`` the autos' ratio, the data / model autocorrelations).
    """
    checks = getattr(getattr(prob, "config", None), "checks", None) or {}
    if not checks:
        return {"maps": "K", "flux_scale": "simulation", "note": "the simulation's sky, K (Rayleigh-Jeans)"}
    if (flux_scale or {}).get("source") == "inferred":
        return {"maps": "K", "flux_scale": "inferred",
                "note": "the sky a = c (a0 + delta) in K; the amplitude q (data = q x the model) is inferred"}
    flux = checks.get("flux_scale") or {}
    if flux.get("mode") == "accept" and flux.get("ratio") is not None and not flux.get("within", True):
        return {"maps": "K x q", "flux_scale": "accepted",
                "note": f"on the data's own scale: q x K with q ~ {flux['ratio']:.4g} (the autos' ratio), not K"}
    return {"maps": "K", "flux_scale": "fixed", "note": "the data taken as calibrated (Jy): the sky in K"}


def read_summary(path) -> RunSummary:
    """The :class:`RunSummary` of a ``summary.json`` file."""
    return RunSummary.from_json(json.loads(Path(path).read_text()))


class RunProducts(NamedTuple):
    """In-memory products of one run (first frequency), e.g. for the scenario suite.

    Attributes:
        truth_map, mean_map, std_map: ``(Npix,)`` maps, K (truth None without a truth).
        z: ``(n,)`` per-mode z-scores, or None; draws: ``(ndraws, n)``; truth: ``(n,)`` or None.
        modes: the mode table; fwhm_deg: the beam FWHM a report hook recorded, or None.
        centre_dec_deg, ra_range_deg: the observed strip, or None.
        resumed_at_batch: the batch a resumed run started at (None for a new run).
        written: the files written by this call.
        already_complete: a resumed run that had nothing left to draw or finalise.
    """

    truth_map: np.ndarray | None
    mean_map: np.ndarray
    std_map: np.ndarray
    z: np.ndarray | None
    draws: np.ndarray | None
    truth: np.ndarray | None
    modes: Any
    fwhm_deg: float | None
    centre_dec_deg: float | None
    ra_range_deg: tuple | None
    resumed_at_batch: int | None
    written: list
    already_complete: bool


def info_stats(info) -> dict:
    """Summary numbers of a :class:`~gcrsky.solvers.SolveInfo` (iterations, worst error, convergence)."""
    it = np.asarray(info.iterations)
    err = np.asarray(info.err_sigma, np.float64)
    conv = np.asarray(info.converged, bool)
    return {
        "n_solves": int(conv.size),
        "iterations_mean": float(it.mean()) if it.size else 0.0,
        "iterations_median": float(np.median(it)) if it.size else 0.0,
        "iterations_max": int(it.max()) if it.size else 0,
        "err_sigma_max": float(np.nanmax(err)) if err.size and np.isfinite(err).any() else float("nan"),
        "n_not_converged": int((~conv).sum()),
        "all_converged": bool(conv.all()),
    }


def solver_summary(method: str, tol: float, winfo, dinfo, prepared=None, n: int = 0, *, rank=None
                   ) -> tuple[dict, list[str]]:
    """The ``solver`` block of ``summary.json`` and the run's solver warnings.

    Args:
        method: the path that ran; tol: the CG tolerance asked for.
        winfo, dinfo: SolveInfo of the Wiener solve and of the draws.
        prepared: the prepared path (the eigen path reports its rank), or None.
        n: number of parameters.
        rank: the eigen path's ``(Nf,)`` rank, when ``prepared`` is not at hand
            (e.g. read back from ``results.h5``).
    """
    warnings: list[str] = []
    solver = {"method": method, "tol_sigma": tol, "wiener": info_stats(winfo), "draws": info_stats(dinfo)}
    if rank is None:
        rank = getattr(prepared, "kept", None)
    if rank is not None:
        rank = [int(r) for r in np.asarray(rank)]
        solver["rank"] = rank
        if min(rank) < n:
            warnings.append(
                f"NOTE: P is singular (improper posterior, e.g. S^-1 = 0): {n - min(rank)} of {n} directions carry "
                f"no information and are pinned at 0; draws and the mean cover the {min(rank)} the data inform."
            )
    solver["all_converged"] = solver["wiener"]["all_converged"] and solver["draws"]["all_converged"]
    if not solver["all_converged"]:
        warnings.append(
            f"WARNING: {solver['wiener']['n_not_converged']} Wiener-filter and "
            f"{solver['draws']['n_not_converged']} draw solves did not converge "
            f"(worst error {max(solver['wiener']['err_sigma_max'], solver['draws']['err_sigma_max']):.3g} "
            "posterior sigma); results are written but may be inaccurate (exit status stays 0)."
        )
    return solver, warnings


def versions() -> dict:
    """Versions of gcrsky and the packages a run's numbers depend on."""
    import h5py
    import healpy

    from .. import __version__

    return {
        "gcrsky": __version__,
        "jax": jax.__version__,
        "jaxlib": getattr(getattr(jax, "lib", None), "__version__", None) or _pkg_version("jaxlib"),
        "numpy": np.__version__,
        "healpy": healpy.__version__,
        "h5py": h5py.__version__,
        "matplotlib": _pkg_version("matplotlib"),
        "pyradiosky": _pkg_version("pyradiosky"),
        "python": platform.python_version(),
        "jax_backend": jax.default_backend(),
    }


def _pkg_version(name: str):
    try:
        from importlib.metadata import version

        return version(name)
    except Exception:  # noqa: BLE001
        return None
