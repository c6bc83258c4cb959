"""The data checks' lines of ``gcrsky inspect`` (calibration, noise excess, flags, flux scale, PROBLEMs)."""

from __future__ import annotations

__all__ = ["check_lines"]


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.3g}"


def _calibration(cal: dict) -> list[str]:
    app = cal["applied"]
    if app is None:
        return [f"  calibration   none applied (vis_units {cal['vis_units']})"]
    lines = [(f"  calibration   {app['file']}: cal_style {app['cal_style']}, {app['cal_type']}, gain_convention "
              f"{app['gain_convention']}, gain_scale {app['gain_scale']}; units {app['units_before']} -> "
              f"{app['units_after']}")]
    if app["renamed_antennas"]:
        lines.append(f"                antennas matched by number ({len(app['renamed_antennas'])} names differ, e.g. "
                     + ", ".join(f"{a} {b}->{c}" for a, (b, c) in list(app["renamed_antennas"].items())[:3]) + ")")
    if app["flagged_antennas_in_solutions"]:
        lines.append(f"                flagged in the solutions: antennas {app['flagged_antennas_in_solutions']}")
    return lines


def _flags(rec: dict) -> list[str]:
    ne = rec.get("noise_excess", {})
    if "skipped" in ne:
        return [f"  noise excess  skipped: {ne['skipped']}"]
    med = [x for x in ne["per_channel_median"] if x is not None]
    out = rec["outliers"]
    flagged = set(out["channels"]) | set(out["dead_channels"])
    clean = [x for i, x in enumerate(ne["per_channel_median"]) if x is not None and i not in flagged]
    if not med:
        return ["  noise excess  no usable adjacent pair of samples (nothing unflagged with a positive nsample)",
                f"  antennas      fully flagged: {rec['fully_flagged_antennas'] or 'none'}"]
    lines = [(f"  noise excess  time-difference / radiometer variance, median over baselines per channel: clean "
              f"channels {_fmt(min(clean) if clean else None)} - {_fmt(max(clean) if clean else None)}, all "
              f"{_fmt(min(med))} - {_fmt(max(med))}")]
    verb = "flagged" if rec["outlier_flagging"] else "outliers (not flagged: --no-flag-outliers)"
    th = out["thresholds"]
    lines.append(f"  outliers      {verb}: channels " + (", ".join(
        f"{c} ({f:.2f} MHz, excess {e:.4g})" for c, f, e in zip(out["channels"], out["channels_mhz"],
                                                                 out["channel_excess"])) or "none")
        + f"; dead channels {out['dead_channels'] or 'none'}; baselines {out['baselines'] or 'none'}; times "
        f"{out['times'] or 'none'}; (channel, baseline) cells "
        + (", ".join(f"{c} {a}-{b} ({e:.4g})" for (c, (a, b)), e in zip(out.get("cells", []),
                                                                      out.get("cell_excess", []))) or "none")
        + f" (threshold: channel excess > {_fmt(th['channel'])}, k {th['k']:g})"
        + (f"; {out['not_judged_baselines']} baselines not judged one by one (the sky drifts > "
           f"{th['max_drift_rad']:g} rad per step)" if out.get("not_judged_baselines") else ""))
    lines += _per_file("noise excess", ne.get("per_file"), "median_excess")
    lines.append(f"  antennas      fully flagged: {rec['fully_flagged_antennas'] or 'none'}")
    return lines


def _per_file(what: str, rows, key: str) -> list[str]:
    """One line per file of a many-file observation (``rows``: ``[{"file", key}]``), the extremes first named."""
    if not rows:
        return []
    import os

    vals = [r[key] for r in rows if r[key] is not None]
    head = (f"  per file      {what}: {len(rows)} files, {_fmt(min(vals)) if vals else 'n/a'} - "
            f"{_fmt(max(vals)) if vals else 'n/a'}")
    return [head] + [f"                {os.path.basename(r['file'])}: {_fmt(r[key])}" for r in rows]


def _flux(rec: dict) -> list[str]:
    if rec.get("mode") == "off":
        return ["  flux scale    off"]
    if "skipped" in rec:
        return [f"  flux scale    skipped: {rec['skipped']}"]
    return [(f"  flux scale    data / model autos (GSM through the beam) {_fmt(rec['ratio'])} ({rec['units']}; "
             f"bounds {rec['bounds'][0]:g}-{rec['bounds'][1]:g}: {'within' if rec['within'] else 'OUTSIDE'})"),
            *_per_file("flux scale", rec.get("per_file"), "ratio")]


def check_lines(info: dict) -> list[str]:
    """The report's data-check lines, then one PROBLEM line per thing a run would refuse."""
    checks = info["data_checks"]
    lines = [(f"  redundancy    {info['n_unique_baselines']} unique within {info['redundancy_tol_m']:g} m (largest "
              f"offset in a group {info['redundancy_max_offset_m']:.3g} m); the run merges only identical responses: "
              f"{info['n_rows_exact']} rows")]
    lines += _calibration(checks["calibration"]) + _flags(checks["flags"]) + _flux(checks["flux_scale"])
    lines += [f"PROBLEM: {p}" for p in info["problems"]]
    return lines
