"""Beams as they come and the prior over the band: the numbers behind docs/ingest.md's two sections.

Tables:

1. A small matvis file (4 antennas at HERA, 3 integrations, 100 and 101 MHz, white sky at
   lmax 4) simulated with matvis' (peak-normalised) HERA dipole beam, read with that beam
   scaled to physical units (x sqrt(8243)): the least-squares amplitude of the model on the
   data (1 = right) peak-normalised (default) and kept physical (the error class fixed).
2. The lowest power of a 4-channel Gaussian power beam clipped below 0.1, between its
   channels: pyuvdata's cubic interpolation vs gcrsky's prepared beam.
3. HERABEAM.FITS converted (SIN image -> az/za), FWHM with --beam-freq-scaling lambda.
4. The GSM C_l table: interpolation at held-out frequencies, extension on held-out end channels.

Run: ``PYTHONPATH=. .venv/bin/python benchmarks/beams_prior.py``.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

PEAK = 8243.0
REAL = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real"


def _hera():
    from pyuvdata import UVBeam

    from gcrsky.checks.matvis import matvis_hera_beam_path

    return UVBeam.from_file(str(matvis_hera_beam_path()))


def normalisation_table() -> None:
    from gcrsky.checks.matvis import HERA_SITE, observing_times, random_sky, site
    from gcrsky.checks.uvsim import simulate_uvdata
    from gcrsky.ingest.uvdata import from_uvdata

    lmax, nside, freqs = 4, 16, np.array([100e6, 101e6])
    pos = np.array([[0.0, 0, 0], [14.6, 0, 0], [7.3, 12.64, 0], [21.9, 12.64, 0]])
    a = random_sky(lmax, 3)
    sim = simulate_uvdata(pos, site(*HERA_SITE), observing_times("2025-03-21T18:00:00", 1.0, 3), freqs, _hera(), a,
                          lmax, nside_matvis=nside, noise_seed=0)
    uvd = sim.uvdata.copy()
    uvd.data_array = sim.model
    phys = _hera()
    phys.data_array = phys.data_array * np.sqrt(PEAK)
    phys.data_normalization = "physical"
    print("| beam used | --beam-normalization | model amplitude on the data (1 = right) | peak power found |")
    print("|---|---|---|---|")
    for name, beam, norm in (("the file's (peak)", _hera(), "peak"), ("physical x8243", phys, "peak"),
                             ("physical x8243", phys, "physical")):
        p = from_uvdata(uvd, lmax=lmax, nside=nside, beam=beam, pol="xx", compress=False, beam_normalization=norm)
        v = np.asarray(p.visibilities(np.broadcast_to(a, (2, a.size))))
        amp = float(np.real(np.vdot(v, np.asarray(p.data))) / np.real(np.vdot(v, v)))
        pk = np.atleast_1d(p.config.checks["beam"]["peak_power_found"])
        print(f"| {name} | {norm} | {amp:.6g} | {pk[0]:.6g} |")


def interpolation_table() -> None:
    from pyuvdata import BeamInterface
    from pyuvdata.analytic_beam import GaussianBeam

    from gcrsky.instrument.beamprep import resample_beam
    from gcrsky.instrument.beams import beam_amplitude

    ch = np.array([100e6, 130e6, 160e6, 190e6])
    g = GaussianBeam(sigma=np.deg2rad(8.0), spectral_index=-2.0, reference_frequency=100e6)
    uvb = g.to_uvbeam(freq_array=ch, beam_type="power", axis1_array=np.deg2rad(np.arange(0, 360, 5.0)),
                      axis2_array=np.deg2rad(np.linspace(0, 90, 181)))
    uvb.data_array = np.where(uvb.data_array.real < 0.1, 0.0, uvb.data_array).astype(uvb.data_array.dtype)
    uvb.data_normalization = "peak"
    za = np.deg2rad(np.linspace(0, 30, 601))
    az = np.zeros_like(za)
    print("\n| frequency (MHz) | pyuvdata cubic: min power | gcrsky prepared: min power |")
    print("|---|---|---|")
    for f in (103e6, 112e6, 121e6):
        raw = np.real(BeamInterface(uvb).compute_response(az_array=az, za_array=za, freq_array=np.array([f]),
                                                          freq_interp_kind="cubic",
                                                          interpolation_function="az_za_map_coordinates"))
        prep, _ = resample_beam(uvb, np.array([f]))
        got = beam_amplitude(prep, az, za, np.array([f])) ** 2
        print(f"| {f / 1e6:g} | {raw.min():.3g} | {got.min():.3g} |")


def herabeam_table() -> None:
    from gcrsky.instrument.beamprep import prepare_beam
    from gcrsky.instrument.beams import beam_fwhm_rad

    path = REAL / "HERABEAM.FITS"
    if not path.exists():
        print("\n(HERABEAM.FITS not found)")
        return
    f = np.array([100e6, 149.951177498e6, 200e6])
    b, rec = prepare_beam(str(path), f, freq_scaling="lambda", x_orientation="east")
    print(f"\nHERABEAM.FITS: {rec['kind']}")
    print("| frequency (MHz) | FWHM (deg), --beam-freq-scaling lambda |")
    print("|---|---|")
    for x in f:
        print(f"| {x / 1e6:.6g} | {np.rad2deg(beam_fwhm_rad(b, x)):.4g} |")


def prior_table() -> None:
    import healpy as hp

    from gcrsky.model.gsmsky import gsm_source_maps, powerlaw_extrapolate
    from gcrsky.model.skyprior import _table, gsm_cl
    from gcrsky.sim.sky import _map_to_alm, gsm_cl_table

    f = np.asarray(_table()[0])
    mids = np.sqrt(f[1:] * f[:-1])
    _, ref = gsm_cl_table(16, mids)
    err = np.abs(gsm_cl(mids, 16) / ref - 1).max(axis=1)
    print("\n| held-out frequency (MHz) | max_l |C_l table / C_l map - 1| |")
    print("|---|---|")
    for m, e in zip(mids, err):
        print(f"| {m / 1e6:.2f} | {e:.2g} |")
    sf, maps, _, _ = gsm_source_maps()
    print("\n| end channels held out | channel (MHz) | max_l |C_l extension / C_l map - 1| |")
    print("|---|---|---|")
    for hold in ([9], [0], [8, 9], [0, 1]):
        keep = [i for i in range(sf.size) if i not in hold]
        pred = powerlaw_extrapolate(sf[keep], maps[keep], sf[hold])
        for k, h in enumerate(hold):
            cp, ct = hp.alm2cl(_map_to_alm(pred[k], 16)), hp.alm2cl(_map_to_alm(maps[h], 16))
            print(f"| {hold} | {sf[h] / 1e6:.1f} | {np.abs(cp / ct - 1).max():.3f} |")


if __name__ == "__main__":
    warnings.filterwarnings("ignore")
    normalisation_table()
    interpolation_table()
    herabeam_table()
    prior_table()
