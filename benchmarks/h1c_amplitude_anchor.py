"""What anchors the amplitude on the real H1C file: the exact marginal of u = q c over (u, p), S -> p S (issue 38).

For three channels of the H1C file (its omnical solutions applied, pseudo-Stokes I, lmax = the reach, 14 m
Gaussian dish), in the eigenbasis of the whitened data-space Gram matrix (gcrsky.run.amplitude's set-up, no
gains): ``y ~ N(u m, I + u^2 p Lambda)``.  Printed per channel: the best ``u`` with the prior's power as it is
(p = 1) and its range within 2 of the maximum log-likelihood, the same with ``p`` free (profile over p from 1e-4
to 1e8), for the GSM mean alone and with Pictor A (360 Jy at 150 MHz, spectral index -0.76) added to the mean,
and the norms of the whitened mean ``|m|`` and source ``|k|``.

    PYTHONPATH=. .venv/bin/python benchmarks/h1c_amplitude_anchor.py      (about 2 minutes)

Measured 2026-12-06 (this 2-core CPU):

    121.9 MHz GSM mean      : p=1: u 0.077 (0.0626-0.0948); p free: u 1e-05 (1e-05-0.177), |k|=752 |m|=6.62e+04
    146.9 MHz GSM mean      : p=1: u 0.1339 (0.109-0.169); p free: u 3.724e-05 (1.1e-05-0.378), |k|=48.7 |m|=7.46e+04
    171.9 MHz GSM mean      : p=1: u 0.1221 (0.102-0.15); p free: u 0.3144 (1.02e-05-0.973), |k|=2.4 |m|=1.16e+05
    (with Pictor A in the mean: the same, but for p free at 121.9 MHz up to 0.189; the autos' ratio is 0.0037,
    0.0036, 0.0026)
"""

from __future__ import annotations

from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
H1C = REAL / "zen.2458098.45361.HH_downselected.uvh5"
CAL = REAL / "zen.2458098.45361.HH.omni_downselected.calfits"
CHANS = [14, 30, 46]
# Pictor A (05h19m49.7s, -45d46m44s), ~360 Jy at 150 MHz, S ~ nu^-0.76
PICA_RA = np.deg2rad(15 * (5 + 19 / 60 + 49.7 / 3600))
PICA_DEC = np.deg2rad(-(45 + 46 / 60 + 44 / 3600))


def _profiles(lam, yt, mean):
    """(log-likelihood over u at p = 1, profile over p) on the module's grids."""
    lu = np.linspace(np.log(1e-5), np.log(10), 600)
    lp = np.linspace(np.log(1e-4), np.log(1e8), 300)
    u, p = np.exp(lu)[:, None, None], np.exp(lp)[None, :, None]
    den = 1 + u**2 * p * lam
    prof = (-0.5 * (np.sum((yt - u * mean) ** 2 / den, axis=-1) + np.sum(np.log(den), axis=-1))).max(axis=1)
    d1 = 1 + np.exp(2 * lu)[:, None] * lam
    l1 = -0.5 * (np.sum((yt - np.exp(lu)[:, None] * mean) ** 2 / d1, axis=-1) + np.sum(np.log(d1), axis=-1))
    return np.exp(lu), l1, prof


def _span(u, ll):
    ok = ll > ll.max() - 2
    return f"u {u[np.argmax(ll)]:.4g} ({u[ok].min():.3g}-{u[ok].max():.3g})"


def main() -> int:
    from astropy.coordinates import EarthLocation
    from astropy.time import Time

    from gcrsky.inference.amplitude import amplitude_eigen, amplitude_setup
    from gcrsky.ingest import from_uvdata
    from gcrsky.instrument import AntennaArray
    from gcrsky.instrument.beams import gaussian_beam
    from gcrsky.instrument.sources import problem_source_response
    from gcrsky.io import read_observation
    from gcrsky.solvers.dataspace import sqrt_weights, to_rows

    if not H1C.exists():
        print(f"skipped: {H1C} is not here")
        return 0
    prob = from_uvdata(str(H1C), cal=str(CAL), dish_diameter_m=14.0, nside=128, pol="pI", freq_chans=CHANS,
                       amplitude="infer", prior_mean="gsm", band_limit="cut", flux_scale="accept")
    obs = read_observation(str(H1C), pol="pI", freq_chans=CHANS)
    loc = EarthLocation.from_geocentric(*obs.site_ecef_m, unit="m")
    arr = AntennaArray(np.asarray(prob.antpos_enu_m), float(loc.lat.rad),
                       tuple([gaussian_beam(14.0)] * len(prob.antpos_enu_m)))
    K = np.asarray(problem_source_response(prob, arr, ra_rad=np.array([PICA_RA]), dec_rad=np.array([PICA_DEC]),
                                           times=Time(obs.times_jd, format="jd", scale="utc"), location=loc))
    freqs = np.asarray(prob.freqs_hz)
    flux = 360.0 * (freqs / 150e6) ** -0.76
    fixed = amplitude_setup(prob.system())
    eig = amplitude_eigen(fixed, None)
    sw = np.asarray(sqrt_weights(fixed.system))
    k = np.asarray(to_rows(jnp.asarray(sw * K[..., 0] * flux[:, None, None])))
    lam, yt, mt, vecs = (np.asarray(x) for x in (eig.lam, eig.yt, eig.mt, eig.vecs))
    kt = np.einsum("fij,fi->fj", vecs, k)
    for f in range(freqs.size):
        for name, mean in (("GSM mean", mt[f]), ("GSM + Pictor A", mt[f] + kt[f])):
            u, l1, prof = _profiles(lam[f], yt[f], mean)
            print(f"{freqs[f] / 1e6:.1f} MHz {name:15s}: p=1: {_span(u, l1)}; p free: {_span(u, prof)}, "
                  f"|k|={np.linalg.norm(k[f]):.3g} |m|={np.linalg.norm(mt[f]):.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
