"""``gcrsky inspect FILE``: what a run on the file would use (:func:`gcrsky.ingest.inspect_uvdata`), without solving."""

from __future__ import annotations

from .errors import report_user_error
from .options import ingest_spec

__all__ = ["inspect_command"]


def _flag_line(info: dict) -> str:
    """The file's flags, zero nsample and gcrsky's own flags, each as a share of the samples."""
    f = info.get("flags")
    if not f:
        return f"  flagged       {100 * info['flagged_fraction']:.2f}% of the samples"
    return (f"  flagged       {100 * f['unusable']:.2f}% of the samples unusable: the file's (and its "
            f"calibration's) flags {100 * f['file']:.2f}%, zero nsample {100 * f['zero_nsample']:.2f}%, gcrsky's "
            f"checks {100 * f['gcrsky']:.2f}%")


def _noise_line(info: dict) -> str:
    """The radiometer noise from the autos, or why there is none (never a NaN)."""
    if not info["has_autos"]:
        return "no autocorrelations: use --noise diff"
    sigma = info.get("noise_sigma_median_k_sr")
    if sigma is None or not sigma == sigma:
        return "no unflagged autocorrelation with a positive nsample: no radiometer noise estimate"
    return f"radiometer (autos): median sigma {sigma:.4g} {info['noise_units']} per component"

def inspect_command(args, parser) -> int:
    """Print the report (or ``--json``); a file that cannot be used: a message, exit 2."""
    from .cmd_data import expand_inputs

    try:
        expand_inputs(args, "file")
        return _inspect(args)
    except (ValueError, FileNotFoundError) as e:  # a message, not a traceback (-v adds it)
        return report_user_error(e, "inspect", getattr(args, "verbose", 0))


def _inspect(args) -> int:
    import json

    from ..base.memory import format_bytes
    from ..ingest.inspect import inspect_uvdata
    from .inspect_checks import check_lines

    info = inspect_uvdata(args.file, ingest_spec(args, run=False), redundancy_tol_m=args.redundancy_tol)
    if args.json:
        print(json.dumps(info, indent=1))
        return 0
    c = info["conventions"]
    lines = [
        f"gcrsky inspect {info['source']}",
        f"  antennas      {info['n_antennas']}: {', '.join(str(a) for a in info['antennas'][:20])}"
        + (" ..." if info["n_antennas"] > 20 else ""),
        f"  baselines     {info['n_baselines']} ({info['n_unique_baselines']} unique by separation)",
        f"  times         {info['n_times']}, LST {info['lst_range_hours'][0]:.3f} - {info['lst_range_hours'][1]:.3f} h",
        f"  channels      {info['n_channels']}, {info['freq_range_hz'][0] / 1e6:.4f} - "
        f"{info['freq_range_hz'][1] / 1e6:.4f} MHz, width {info['channel_width_hz'] / 1e3:.3g} kHz",
        f"  products      file {', '.join(info['file_polarizations'])}; modelled {', '.join(info['modelled_products'])}",
        f"  conventions   {c['vis_units']}, pol_convention {c['pol_convention']}, {c['phase']}, "
        f"feed x points {c.get('x_orientation') or 'nowhere stated (x_orientation absent)'}",
        _flag_line(info),
        "  noise         " + _noise_line(info),
        f"  memory        read {format_bytes(info['read_bytes'])}; dense P at lmax {info['lmax_for_sizes']}: "
        f"{format_bytes(info['dense_precision_bytes'])}; response {format_bytes(info.get('response_bytes', 0))}",
        f"  site          lat {info['site_lat_lon_deg'][0]:.4f} deg, lon {info['site_lat_lon_deg'][1]:.4f} deg",
    ]
    band = info.get("band_limit")
    if band:
        lines.append(f"  band limit    the baselines reach l = {band['reach']} at the highest frequency (dish "
                     f"{band['dish_m'][0]:g} m); a run without --lmax models lmax {band['lmax']} ({band['chosen']})")
    lines += [f"  note          {n}" for n in info["notes"]]
    lines += check_lines(info)
    print("\n".join(lines))
    return 0
