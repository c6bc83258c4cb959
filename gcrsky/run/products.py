"""The standard products of a run: the posterior mean and std as HEALPix FITS, healpy alm and skyh5.

Each file is written atomically (temporary name, then rename; :mod:`gcrsky.io.atomic`).
The posterior mean in the products is the Wiener filter (the exact posterior mean, no
Monte Carlo noise); the std map is the per-pixel standard deviation over the draws.
"""

from __future__ import annotations

from pathlib import Path

from ..io.fits import write_alm_fits, write_healpix_fits
from ..io.skymodel import write_skyh5
from .output import PRODUCT_FILES

__all__ = ["write_products"]


def write_products(
    out,
    *,
    wiener_filter,
    wiener_maps,
    std_maps,
    freqs_hz,
    lmax: int,
    frame: str,
    ndraws: int,
    method: str,
    seed: int | None = None,
    only_missing: bool = False,
    units: dict | None = None,
) -> dict:
    """The standard products of a run (:data:`PRODUCT_FILES`), each written atomically into ``out``.

    - ``posterior_mean.fits``: the map of the Wiener filter (the exact posterior mean),
      HEALPix RING, one column per frequency (:func:`gcrsky.io.write_healpix_fits`);
    - ``posterior_std.fits``: the per-pixel standard deviation over the draws (ddof 1);
    - ``posterior_mean_alm.fits``: the Wiener filter as complex healpy-ordered alm, one
      HDU per frequency (:func:`gcrsky.io.write_alm_fits`);
    - ``posterior_mean.skyh5``: a pyradiosky ``SkyModel`` of the posterior-mean map,
      with the std map as ``stokes_error`` (:func:`gcrsky.io.write_skyh5`).

    All in kelvin, in the frame of the coefficients (``frame``: :func:`gcrsky.run.maps.parameter_frame`).

    Args:
        out: output directory.
        wiener_filter: ``(Nf, n)`` realified posterior mean; wiener_maps, std_maps: ``(Nf, Npix)``.
        freqs_hz: ``(Nf,)``; lmax: maximum degree; frame: ``"icrs"`` or ``"idealised"``.
        ndraws, method, seed: recorded in the headers / history.
        only_missing: keep products already in ``out``.
        units: :func:`gcrsky.run.summary.map_units`'s block: its ``maps`` and ``flux_scale`` go into the FITS
            headers (``MAPUNIT``, ``FLUXSCAL``) and the skyh5 history (default: K, unstated flux scale).

    Returns:
        ``{product key: file name}`` of the files written now.
    """
    out = Path(out)
    writers = _writers(wiener_filter, wiener_maps, std_maps, freqs_hz, lmax, frame, ndraws, method, seed, units)
    written = {}
    for key, write in writers.items():
        path = out / PRODUCT_FILES[key]
        if only_missing and path.exists():
            continue
        write(path)
        written[key] = PRODUCT_FILES[key]
    return written


def _writers(wiener_filter, wiener_maps, std_maps, freqs_hz, lmax, frame, ndraws, method, seed, units=None) -> dict:
    """``{product key: write(path)}`` of :func:`write_products`."""
    from .. import __version__

    common = [("NDRAWS", int(ndraws), "posterior draws of the run"), ("METHOD", str(method), "GCR solver path"),
              ("ORIGIN", f"gcrsky {__version__}", "software")]
    if seed is not None:
        common.append(("SEED", int(seed), "seed of the draws"))
    units = dict(units or {})
    common.append(("MAPUNIT", str(units.get("maps", "K")), "map unit (K x q: the data's scale)"))
    if units.get("flux_scale"):
        common.append(("FLUXSCAL", str(units["flux_scale"]), "flux scale source"))
    mean_what = "posterior mean: the Wiener filter (exact)"
    wiener_card = ("MEANTYPE", "WIENER", "exact posterior mean (not the draws' mean)")
    return {
        "posterior_mean_fits": lambda p: write_healpix_fits(
            p, wiener_maps, freqs_hz, frame=frame, lmax=lmax, content=mean_what, extra_header=common + [wiener_card]),
        "posterior_std_fits": lambda p: write_healpix_fits(
            p, std_maps, freqs_hz, frame=frame, lmax=lmax, content="posterior std: per pixel over the draws (ddof 1)",
            extra_header=common + [("DDOF", 1, "std over draws: divisor NDRAWS - 1")]),
        "posterior_mean_alm": lambda p: write_alm_fits(
            p, wiener_filter, lmax, freqs_hz, frame=frame, content=mean_what, extra_header=common + [wiener_card]),
        "posterior_mean_skyh5": lambda p: write_skyh5(
            p, wiener_maps, freqs_hz, frame=frame, std_maps=std_maps,
            history=f"gcrsky {__version__}: posterior mean (the Wiener filter, exact) of a GCR run ({method}, "
            f"{ndraws} draws, lmax {lmax}); stokes_error: per-pixel posterior std over the draws (ddof 1). "
            f"Units: {units.get('maps', 'K')}" + (f" ({units['note']})" if units.get("note") else "") + "."),
    }
