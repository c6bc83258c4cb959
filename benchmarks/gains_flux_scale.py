"""``--gains sample`` on data calibrated in Jy with gainsim's default gains: the sky's scale kept (issue 38).

The file: a matvis simulation (7 antennas of 14 m in a hexagon, HERA's site, 6 integrations over 3 h, two
channels, a white random sky band-limited at ``--lmax``, radiometer noise) corrupted by
``gcrsky.checks.gainsim.corrupt_with_gains`` with its defaults (5 % / 5 deg per antenna and feed, linear in
frequency and time), written in Jy.  Two runs of ``gcrsky run --data FILE --dish-diameter 14`` at the file's
band limit: without gains, and with ``--gains sample`` and its default options (the amplitude held at 1
on Jy data, the modes following the selection, both feed products).  Printed per run and channel: the
fit's chi2/dof, the flux scale (mean and 95 %, held at 1 on Jy data), the sky's scale on the beam-centre
ring (least-squares ratio of the posterior mean to the truth over the observed stretch of the HEALPix
ring nearest the site's latitude, and the 95 % interval of the same ratio over the draws), the median
fractional error of the posterior mean there, and the slowest ESS of the gain chain.

Before issue 38 the same kind of file (5 % / 3 deg gains, 60/61 MHz) gave an accepted fit with
``--gains sample`` and a map 108 % off on that ring: the flux scale had drifted along the gains' degeneracy.

Run: ``PYTHONPATH=. .venv/bin/python benchmarks/gains_flux_scale.py`` (about 3 minutes on 2 cores;
``--freqs 60,61`` for the issue's channels).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import h5py  # noqa: E402
import healpy as hp  # noqa: E402
import numpy as np  # noqa: E402

from gcrsky import cli  # noqa: E402
from gcrsky.checks.gainsim import corrupt_with_gains  # noqa: E402
from gcrsky.checks.matvis import HERA_SITE, observing_times, random_sky, site  # noqa: E402
from gcrsky.checks.uvsim import simulate_uvdata  # noqa: E402
from gcrsky.instrument import gaussian_beam, hex_array  # noqa: E402
from gcrsky.sphere.maps import alm_to_map  # noqa: E402


def _ring(nside: int, ra_range_deg) -> np.ndarray:
    """Pixels of the ring nearest the site's latitude inside the observed RA stretch."""
    ra, dec = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)), lonlat=True)
    near = np.abs(dec - HERA_SITE[0]) < 0.5 * np.rad2deg(hp.nside2resol(nside))
    ring, ra = np.flatnonzero(near), ra[near]
    lo, hi = ra_range_deg
    inside = (ra - lo) % 360.0 <= (hi - lo) % 360.0
    return ring[inside]


def _run(path: Path, out: Path, lmax: int, extra: list[str]) -> dict:
    t0 = time.perf_counter()
    argv = ["run", "--data", str(path), "--out", str(out), "--dish-diameter", "14", "--lmax", str(lmax),
            "--nside", "32", "--band-limit", "truncate", "--nsamples", "200", "--batch", "100", "--no-plots",
            "--no-progress", "--flux-scale", "accept", *extra]  # a white random sky, not the GSM
    assert cli.main(argv) == 0, argv
    s = json.loads((out / "summary.json").read_text())
    s["_seconds"] = time.perf_counter() - t0
    return s


def _sky_scale(out: Path, truth: np.ndarray, lmax: int, ring: np.ndarray) -> list[tuple]:
    """Per channel: (ratio of the posterior mean, 2.5 and 97.5 % of the draws' ratios, median |frac. error|)."""
    with h5py.File(out / "results.h5", "r") as h:
        draws = h["draws"][()]  # (Nf, ndraws, n)
    t = alm_to_map(truth, lmax, 32)[ring]
    rows = []
    for f in range(draws.shape[0]):
        maps = np.stack([alm_to_map(a, lmax, 32)[ring] for a in draws[f]])
        ratios = maps @ t / (t @ t)
        mean = maps.mean(axis=0)
        rows.append((float(mean @ t / (t @ t)), *np.percentile(ratios, [2.5, 97.5]),
                     float(np.median(np.abs(mean - t) / np.abs(t)))))
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--lmax", type=int, default=6)
    p.add_argument("--freqs", default="100,101", help="the two channels, MHz")
    p.add_argument("--phase-deg", type=float, default=5.0, help="gainsim's rms phase (its default 5)")
    a = p.parse_args(argv)
    freqs = np.array([float(x) * 1e6 for x in a.freqs.split(",")])
    truth = random_sky(a.lmax, 3)
    sim = simulate_uvdata(hex_array((2, 3, 2)), site(*HERA_SITE), observing_times("2025-03-21T18:00:00", 3.0, 6),
                          freqs, gaussian_beam(14.0), truth, a.lmax, nside_matvis=32)
    cor, _ = corrupt_with_gains(sim.uvdata, phase_deg=a.phase_deg)
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        path = d / "gains.uvh5"
        cor.write_uvh5(str(path))
        print(f"gcrsky {cli.__name__}: {a.freqs} MHz, lmax {a.lmax}, gains 5 % / {a.phase_deg:g} deg (gainsim), Jy")
        print("| run | channel | chi2/dof | flux scale (95 %) | sky scale on the ring: mean (draws' 95 %) "
              "| median abs frac error | slowest gain ESS | seconds |")
        print("|---|---|---|---|---|---|---|---|")
        for name, extra in (("no gains", ["--gains", "off"]), ("--gains sample", ["--gains", "sample"])):
            out = d / name.replace(" ", "_").strip("-")
            s = _run(path, out, a.lmax, extra)
            ring = _ring(32, s["region"]["ra_range_deg"])
            g = s.get("gains") or {}
            fs = g.get("flux_scale") or [None] * len(freqs)
            ess = (g.get("chain") or {}).get("ess_min")
            for f, row in enumerate(_sky_scale(out, truth, a.lmax, ring)):
                flux = "fixed" if fs[f] is None else f"{fs[f]['mean']:.4g} ({fs[f]['ci95'][0]:.4g}-{fs[f]['ci95'][1]:.4g})"
                print(f"| {name} | {freqs[f] / 1e6:g} MHz | {s['goodness_of_fit']['chi2_per_dof'][f]:.3g} | {flux} | "
                      f"{row[0]:.3f} ({row[1]:.3f}-{row[2]:.3f}) | {100 * row[3]:.1f} % | "
                      f"{'' if ess is None else f'{ess:.3g}'} | {s['_seconds']:.0f} |")


if __name__ == "__main__":
    main()
