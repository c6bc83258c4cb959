"""The terminal is the CLI's: progress bars, the report of a run, the messages of a refused one."""

from __future__ import annotations

import math
from pathlib import Path

__all__ = [
    "StageBar",
    "batch_bar",
    "channel_bar",
    "compile_line",
    "compile_of",
    "print_summary",
    "refusal_message",
    "stage_names",
]


class StageBar:
    """A tqdm bar over the named stages of a run (``on_stage`` of :class:`gcrsky.run.Watch`)."""

    def __init__(self, names, disable):
        from tqdm.auto import tqdm

        self.bar = tqdm(total=len(names), desc="gcrsky", unit="stage", disable=disable, leave=False, position=0,
                        bar_format="{desc}: {n_fmt}/{total_fmt} stages |{bar}| {elapsed}")

    def __call__(self, name: str, event: str) -> None:
        if event == "start":
            self.bar.set_description(f"gcrsky: {name}")
        else:
            self.bar.update(1)

    def close(self):
        self.bar.close()


def stage_names(plots: bool) -> list[str]:
    """The stages a run goes through (:mod:`gcrsky.run.stages`), ``plots`` only when it draws figures."""
    return ["wiener", "draws", "maps"] + (["plots"] if plots else []) + ["write"]


def batch_bar(disable):
    """A tqdm wrapper of the draw batches (``progress`` of :class:`gcrsky.run.Watch`)."""
    from tqdm.auto import tqdm

    return lambda it: tqdm(it, desc="draw batches", unit="batch", disable=disable, leave=False, position=1)


def channel_bar(disable):
    """``total -> update`` of a tqdm bar over channels (``channel_progress`` of :class:`gcrsky.run.Watch`)."""
    from tqdm.auto import tqdm

    return lambda total: tqdm(total=total, desc="channels", unit="channel", disable=disable, leave=False,
                              position=1).update


def compile_of(since) -> dict:
    """The compilation since a snapshot, with the cache directory (as ``summary.json``'s ``compile``)."""
    from ..parallel.runtime import compile_cache_dir, compile_stats

    d = compile_stats().since(since)._asdict()
    where = compile_cache_dir()
    d["cache_dir"] = None if where is None else str(where)
    return d


def compile_line(c: dict, label: str = "compile") -> str:
    """``compile 8.0 s (39 programs; cache DIR: 0 hits, 39 misses)``, from a ``compile`` block."""
    if c.get("cache_dir"):
        cache = f"cache {c['cache_dir']}: {c['cache_hits']} hits, {c['cache_misses']} misses"
    else:
        cache = "compilation cache off"
    return f"  {label} {c['compile_s']:.1f} s ({c['programs']} programs; {cache})"


def _pct(x) -> str:
    return "nan" if x is None or not math.isfinite(x) else f"{100 * x:.2f}%"


def _metric_lines(s: dict) -> list[str]:
    """The first channel's truth metrics and z-scores, where the summary has them."""
    m = s["metrics"]
    lines = []
    if m.get("frac_diff_centre_median") is not None or "frac_diff_centre_p90" in m:
        lines += [
            f"  at {m['freq_hz'] / 1e6:g} MHz (FWHM {m['fwhm_deg']:.2f} deg, centre dec "
            f"{s['region']['centre_dec_deg']:.3f}):",
            f"    median |mean-truth|/truth  centre ring {_pct(m['frac_diff_centre_median'])}  "
            f"(90th pct {_pct(m['frac_diff_centre_p90'])}, within 5%: {_pct(m['frac_diff_centre_within_5pct'])})",
            f"                               +-1 FWHM    {_pct(m['frac_diff_fwhm_median'])}  "
            f"(90th pct {_pct(m['frac_diff_fwhm_p90'])}, within 10%: {_pct(m['frac_diff_fwhm_within_10pct'])})",
        ]
    if "mode_z" in m:
        lines.append(f"    per-mode z: rms {m['mode_z']['rms']:.2f}, |z|<=2 for {_pct(m['mode_z']['within_2'])}")
    return lines


def band_limit_line(check: dict | None) -> str:
    """One line of a file's band limit (``DataConfig.checks["band_limit"]``)."""
    if not check:
        return "gcrsky: band limit: not checked"
    how = {"given": "given", "reach": "the reach of every baseline", "memory": "capped by memory"}[check["chosen"]]
    line = f"gcrsky: band limit: lmax {check['lmax']} ({how}; reach {check['reach']}), {check['mode']}"
    if check["mode"] == "cut":
        line += (f": {check['rows_cut']} rows and {check['samples_cut']} (channel, row) samples cut"
                 + (f", lengths {check['cut_lengths_m']} m" if check["cut_lengths_m"] else ""))
    elif check["mode"] == "marginalise" and "added_std_over_noise" in check:
        line += f": l up to {check['lmax_hi']}, added std / noise median {check['added_std_over_noise']['median']:.3g}"
    else:
        line += f": {check['rows_beyond_lmax']} rows reach beyond lmax (unmodelled)"
    return line


def fit_line(gof: dict) -> str:
    """One line of the run's goodness of fit (``summary.json``'s ``goodness_of_fit``)."""
    chi = ", ".join("-" if x is None else f"{x:.3g}" for x in gof["chi2_per_dof"][:8]) + (
        " ..." if len(gof["chi2_per_dof"]) > 8 else "")
    p = [min(u, lo) for u, lo in zip(gof["p_value"], gof["p_value_low"]) if u is not None]
    verdict = (f"REJECTED in {len(gof['rejected_channels'])} channels" if gof["rejected"]
               else f"not rejected at p < {gof['threshold_p']:.2g} in either tail")
    return (f"  fit: chi2/dof {chi} (min tail p {min(p) if p else float('nan'):.2g}: {verdict}); outliers: "
            f"{gof['rows']['n_outliers']} rows, {gof['times']['n_outliers']} times")


def gains_line(g: dict) -> str:
    """One line on a gain run: the crosses' flux scale (first channel) against the autos', the phase gradients; for
    gains sampled with the beams (no flux scale of their own: the amplitude's) the fit with the file's gains."""
    text = f"  gains: {g['units']} units"
    if "flux_scale" in g:
        f = g["flux_scale"][0]
        lo, hi = f["ci95"]
        text += f"; flux scale {f['mean']:.4g} +- {f['sd']:.2g} (95 %: {lo:.4g}-{hi:.4g})"
    if g.get("fit_file_gains"):
        chi = ", ".join(f"{c:.3g}" for c in g["fit_file_gains"]["chi2_per_dof"])
        text += f"; with the file's gains chi2/dof {chi}" + (" (rejected)" if g["fit_file_gains"]["rejected"] else "")
    if g.get("autos_flux_ratio") is not None:
        text += f" against the autos' {g['autos_flux_ratio']:.4g}"
    if g.get("flux_scale_ess") is not None:
        text += f", ESS {g['flux_scale_ess']:.0f} of {g['ndraws']}"
    chain = g.get("chain") or {}
    if chain.get("ok") is not None:
        least = "never moved" if chain["ess_min"] is None else f"{chain['ess_min']:.0f}"
        text += (f"; chain: least ESS {least} ({chain['worst']}), "
                 + (f"{chain['n_below_floor']} of {chain['n_scalars']} scalars below {chain['floor']:.0f}"
                    if chain["n_below_floor"] else f"every scalar at or above {chain['floor']:.0f}"))
    for p in g.get("phase_gradients") or ():
        text += f"; {p['direction']} phase gradient sd {p['ratio']:.2f} x prior"
    return text


def print_summary(summary, out: Path, written=None) -> None:
    """Print what a run did (a :class:`gcrsky.run.RunSummary`, or its ``summary.json`` dict)."""
    s = summary.to_json() if hasattr(summary, "to_json") else summary
    t, sv = s["timings_s"], s["solver"]
    cfg = s.get("config") or {}
    lines = [f"gcrsky run -> {out}"]
    if s.get("sky_note"):
        lines.append(f"  sky: {s['sky_note'].split('. ')[0][:160]}")
    lines.append(
        f"  {s['run']['nsamples']} draws ({sv['method']})"
        + (f", lmax {cfg['lmax']}, nside {cfg['nside']}" if cfg else "") + f", {len(s['per_frequency'])} channels"
    )
    lines += _metric_lines(s)
    worst = [x for x in (sv["wiener"]["err_sigma_max"], sv["draws"]["err_sigma_max"]) if x is not None]
    lines += [
        f"  solver: Wiener {sv['wiener']['iterations_max']} it max; draws {sv['draws']['iterations_mean']:.0f} it mean / "
        f"{sv['draws']['iterations_max']} max; worst err {max(worst) if worst else float('nan'):.2g} "
        f"sigma; all converged: {sv['all_converged']}",
        f"  time: build {t['build']:.1f} s, wiener {t['wiener']:.1f} s, draws {t['draws']:.1f} s (compile included), "
        f"maps {t['maps']:.1f} s" + (f", plots {t['plots']:.1f} s" if "plots" in t else ""),
    ]
    if s.get("compile"):  # not in the summary of a run made before it was recorded
        lines.append(compile_line(s["compile"]))
    if s.get("goodness_of_fit"):
        lines.append(fit_line(s["goodness_of_fit"]))
    if s.get("gains"):
        lines.append(gains_line(s["gains"]))
    if written is None:
        written = ["results.h5", "summary.json", *s.get("figures", {}).values()]
    lines.append("  wrote " + (", ".join(written) if written else "nothing (every file was there)"))
    print("\n".join(lines))


#: The command-line option behind each recorded run setting (for --resume's messages).
OPTION_OF = {
    "config.lmax": "--lmax", "config.nside": "--nside", "config.n_lst": "--n-lst",
    "config.lst_range_hours": "--lst-start/--lst-stop", "config.dish_diameter": "--dish-diameter",
    "config.noise_scale": "--noise-scale", "config.prior_scale": "--prior-scale", "config.flat_prior": "--flat-prior",
    "config.zero_prior_mean": "--zero-prior-mean", "config.seed": "--data-seed", "config.obs_date": "--date",
    "nsamples": "--nsamples", "seed": "--seed", "batch": "--batch", "method": "--method", "tol": "--tol",
    "scenario": "--scenario",
}


def refusal_message(e, *, resume: bool) -> str:
    """The message of a refused run (:class:`~gcrsky.run.RunExistsError` / :class:`~gcrsky.run.ResumeError`)."""
    from ..run import ResumeError, RunLockedError

    if isinstance(e, RunLockedError):
        return f"gcrsky: {e}."
    if isinstance(e, ResumeError) and e.differences:
        what = ", ".join(f"{OPTION_OF.get(k, k)} (recorded {a!r}, now {b!r})" for k, a, b in e.differences)
        return (f"gcrsky: --resume: the run in {e.out} was made with other settings: {what}. Give the recorded "
                f"options to resume it, or --overwrite to start again (or choose another --out).")
    if isinstance(e, ResumeError):
        return f"gcrsky: --resume: {e}. --overwrite starts again (or choose another --out)."
    if resume:
        return f"gcrsky: --resume: {e} (--overwrite)."
    return (f"gcrsky: {e.out} already holds results of a run ({', '.join(e.files)}); pass --resume to continue "
            f"that run or --overwrite to replace it (or choose another --out).")
