"""Band limit: a sky to 3 x lmax seen by a tiny array, modelled at lmax cut, marginalised and truncated.

The data are simulated with gcrsky's own response at the sky's degree ``lmax_sky``
(the independent reference here is the *higher-degree model*: the truth has every
coefficient to ``lmax_sky``, the fits see only ``l <= lmax``), plus white noise.  Per
case, per channel:

* ``z2``: the whitened error of the truth's band-limited part,
  ``(a_wf - a_lo)^T Cov^-1 (a_wf - a_lo) / n`` with ``Cov`` the case's posterior
  covariance: chi-square / n under a right model (its 99.9 % range is printed);
* ``chi2/dof``: the exact goodness of fit (:func:`gcrsky.run.fit.goodness_of_fit`);
* for ``marginalise``: the Wiener filter's rms difference from the exact one (the dense
  posterior at ``lmax_sky``, restricted to ``l <= lmax``) in exact standard deviations,
  and the ratio of the posterior standard deviations to the exact ones.

Run: ``PYTHONPATH=. .venv/bin/python benchmarks/band_limit.py [--seeds 5]``.
"""

from __future__ import annotations

import argparse

from gcrsky.parallel import use_safe_cpu_threading

use_safe_cpu_threading()  # before JAX's first computation
import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

from gcrsky.instrument.antennas import make_array  # noqa: E402
from gcrsky.instrument.beams import gaussian_beam  # noqa: E402
from gcrsky.instrument.response import response_matrix  # noqa: E402
from gcrsky.model import adjoint, build_problem, isotropic_prior  # noqa: E402
from gcrsky.model.bandlimit import beam_dish_m, cut_rows, marginalise_rows  # noqa: E402
from gcrsky.sphere.modes import mode_table  # noqa: E402

#: The tiny array: 4 antennas of 6 m Gaussian dishes (pyuvdata's needs D > 0.7 lambda); baselines 4 m (E, N),
#: 5.7 m, 8-13 m.
ANTPOS_M = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0], [12.0, 5.0, 0.0]])
DISH_M = 6.0
FREQS_HZ = np.array([40e6, 45e6])
LMAX, LMAX_SKY, NSIDE = 12, 36, 16
LSTS = np.linspace(0.0, 2 * np.pi, 12, endpoint=False)
LATITUDE_DEG = -30.7


def sky_cl(lmax: int) -> np.ndarray:
    """(Nf, lmax+1) C_l of the simulated sky: ``100 / (1 + l)^2`` K^2 at every channel."""
    return np.tile(100.0 / (1.0 + np.arange(lmax + 1)) ** 2, (FREQS_HZ.size, 1))


def low_index(lmax: int, lmax_hi: int) -> np.ndarray:
    """Indices into the realified vector at ``lmax_hi`` of the entries at ``lmax`` (same order)."""
    hi = mode_table(lmax_hi)
    pos = {(int(a), int(b), bool(c)): k for k, (a, b, c) in enumerate(zip(hi.ell, hi.m, hi.is_imag))}
    lo = mode_table(lmax)
    return np.array([pos[(int(a), int(b), bool(c))] for a, b, c in zip(lo.ell, lo.m, lo.is_imag)])


def simulate(seed: int, sigma: float = 0.02, lmax: int = LMAX, lmax_sky: int = LMAX_SKY):
    """``(array, problem at lmax_sky with its truth, response at lmax_sky)``: a sky drawn from
    :func:`sky_cl` to ``lmax_sky`` and noise ``sigma`` per component."""
    array = make_array(ANTPOS_M, LATITUDE_DEG, gaussian_beam(DISH_M))
    prior = isotropic_prior(sky_cl(lmax_sky), (lmax_sky + 1) ** 2)
    truth = np.asarray(prior.inv_var) ** -0.5 * np.random.default_rng(seed).standard_normal(prior.inv_var.shape)
    full = build_problem(array, FREQS_HZ, LSTS, lmax_sky, NSIDE, a_true=truth, sigma=sigma, prior=prior,
                         key=jax.random.PRNGKey(seed))
    return array, full


def model_problem(array, full, lmax: int = LMAX):
    """The data of ``full`` modelled at ``lmax`` (the prior's C_l cut there; truth: the band-limited part)."""
    idx = low_index(lmax, full.lmax)
    prior = isotropic_prior(sky_cl(lmax), (lmax + 1) ** 2)
    prob = build_problem(array, FREQS_HZ, LSTS, lmax, NSIDE, data=full.data, sigma=full.sigma, prior=prior)
    import dataclasses

    return dataclasses.replace(prob, a_true=np.asarray(full.a_true)[:, idx])


def dense_posterior(prob):
    """``(a_wf (Nf, n), cov (Nf, n, n))`` of a problem by dense linear algebra (numpy)."""
    sys = prob.system()
    p = np.asarray(prob.precision_matrix())
    b = np.asarray(adjoint(sys.op, sys.inv_noise * sys.data)) + np.asarray(sys.prior.inv_var * sys.prior.mean)
    cov = np.linalg.inv(p)
    return np.einsum("fij,fj->fi", cov, b), cov


def whitened_z2(a_wf, cov, truth) -> np.ndarray:
    """(Nf,) ``(a_wf - truth)^T cov^-1 (a_wf - truth) / n`` per channel."""
    e = a_wf - truth
    return np.einsum("fi,fi->f", e, np.linalg.solve(cov, e[..., None])[..., 0]) / e.shape[1]


def cases(seed: int, sigma: float = 0.02) -> dict:
    """``{case: (problem, a_wf, cov)}`` for "exact", "cut", "marginalise", "truncate" (and the full problem)."""
    array, full = simulate(seed, sigma)
    base = model_problem(array, full)
    dish = beam_dish_m(array.beams, FREQS_HZ)
    cut, report = cut_rows(base, LMAX, dish)
    resp_hi = response_matrix(array, np.asarray(base.antpairs), FREQS_HZ, LMAX_SKY, NSIDE)
    marg, _ = marginalise_rows(base, resp_hi, sky_cl(LMAX_SKY))
    out = {"truncate": base, "cut": cut, "marginalise": marg}
    res = {k: (p, *dense_posterior(p)) for k, p in out.items()}
    a_full, cov_full = dense_posterior(full)
    idx = low_index(LMAX, LMAX_SKY)
    res["exact"] = (base, a_full[:, idx], cov_full[:, idx][:, :, idx])
    res["_full"] = (full, a_full)
    res["_report"] = report
    return res


def main() -> None:
    from gcrsky.run.fit import goodness_of_fit

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--sigma", type=float, default=0.02, help="noise std per component, K sr")
    args = ap.parse_args()
    n = (LMAX + 1) ** 2
    lo, hi = stats.chi2.ppf([5e-4, 1 - 5e-4], n) / n
    print(f"array {ANTPOS_M.shape[0]} antennas, D = {DISH_M} m, {FREQS_HZ / 1e6} MHz, lmax {LMAX}, sky to "
          f"{LMAX_SKY}, {LSTS.size} times; z2 99.9 % range for n = {n}: [{lo:.3f}, {hi:.3f}]")
    print(f"{'seed':>4} {'case':>12} {'rows':>4} {'z2 (per channel)':>22} {'chi2/dof (per channel)':>26} "
          f"{'p min':>9} {'wf err/std':>10} {'std ratio':>12}")
    for seed in range(args.seeds):
        res = cases(seed, args.sigma)
        a_ex, cov_ex = res["exact"][1], res["exact"][2]
        sd_ex = np.sqrt(np.diagonal(cov_ex, axis1=1, axis2=2))
        for name in ("exact", "cut", "marginalise", "truncate"):
            prob, a_wf, cov = res[name]
            z2 = whitened_z2(a_wf, cov, np.asarray(prob.a_true))
            gof = goodness_of_fit(*res["_full"]) if name == "exact" else goodness_of_fit(prob, a_wf)
            sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
            err = np.sqrt(np.mean(((a_wf - a_ex) / sd_ex) ** 2))
            ratio = sd / sd_ex
            print(f"{seed:>4} {name:>12} {prob.antpairs.shape[0]:>4} {np.array2string(z2, precision=3):>22} "
                  f"{np.array2string(np.asarray(gof['chi2_per_dof']), precision=3):>26} "
                  f"{min(gof['p_value']):>9.2e} {err:>10.3f} "
                  f"{ratio.min():>5.2f}-{ratio.max():<5.2f}")
        print(f"     cut: {res['_report']}")


if __name__ == "__main__":
    main()
