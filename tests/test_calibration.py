"""Simulation-based calibration (SBC, Talts et al. 2018) of both samplers, with flags.

Set-up: the 10-antenna hexagon at lmax 4 (n = 25), nside 16, one channel, 6 LSTs
over 0-6 h, heterogeneous per-component noise sigma in [1.5, 3] x 1e-4, an
isotropic prior C_l = 200 / (1 + l)^2, and flags: 20% of samples at random plus
the whole time index 2 and the whole baseline index 7 (33% flagged in all), with
NaN in the flagged data (cleaned by :func:`gcrsky.model.noise.clean_data` like real data).
Each SBC run: M = 1000 replicates, truth ~ prior, data ~ likelihood, L = 15
posterior draws per replicate, ranks of 9 functionals fixed in advance
(:func:`gcrsky.checks.sbc.default_functionals`): the 3 most data-dominated
directions in prior-whitened coordinates (whitened data-term eigenvalue lam ~
1e5-8e5, the data carry > 99.99% of the precision), the 1 most balanced (lam 0.68),
the 2 most prior-dominated (lam < 3e-4) and the coefficients a_00, Re a_11, Im a_31.

False-alarm rate.  ALPHA = 1e-3.  Per functional, three tests whose null
distributions are *exact*, not asymptotic (randomised PIT u = (rank + V) / (L + 1),
exactly U(0, 1); exact KS on u; sum Phi^-1(u)^2 ~ chi2(M); sum Phi^-1(u) / sqrt(M)
~ N(0, 1)), combined by Bonferroni (x 3) and across the 9 functionals by
Bonferroni (x 9), which holds whatever the dependence between functionals of one
replicate (ranks of *one* functional across replicates are independent, so each
test's null is exact).  Hence each SBC test below fails a correct sampler with
probability <= ALPHA = 1e-3 (for its fixed seed the outcome is deterministic).
:func:`test_rank_pvalues_have_exact_size` checks the exactness claim itself.

Power.  The same statistic must reject (family p < 1e-6) three wrong samplers built
here from gcrsky's public pieces (no bug switches in the library):
(i) the reference code's fluctuation bug (data-space fluctuation x 1/sqrt 2:
draws with half the variance along data-dominated directions), (ii) the posterior
built with noise variance 2 sigma^2 while the data have sigma^2 (over-dispersed)
and (iii) data with 2 sigma^2 while the posterior assumes sigma^2 (under-dispersed).

Measured (these seeds; family p-values): cg 0.21, cholesky 1.0; controls
(i) 5.8e-23, (ii) 2.0e-36, (iii) 3.9e-25.  The correct samplers' smallest
per-functional p-values are 2.3e-2 (cg, "balanced", bias) and 0.13 (cholesky);
Pearson's chi-square on 16-bin rank histograms (asymptotic, reported only) gives
1.9e-28 / 1.1e-24 / 2.2e-31 for the controls' top data-dominated direction
(0.046 and 0.040 at worst for cg and cholesky).  With M = 4000, L = 31 the
benchmark measures family p 0.11 (cg), 0.87 (cholesky), 3.9e-135, 5.1e-148, 2.7e-144.
``benchmarks/calibration.py`` prints the whole table.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy import stats

from gcrsky.checks.sbc import (
    GCRSampler,
    default_functionals,
    flagged_example_problem,
    rank_pvalues,
    reference_bug_sampler,
    run_sbc,
)
from gcrsky.solvers import CGOptions

jax.config.update("jax_enable_x64", True)

ALPHA = 1e-3  # false-alarm rate of every calibration test in this module
POWER_P = 1e-6  # the negative controls must be rejected at this level
M, L = 1000, 15  # replicates, posterior draws per replicate


@pytest.fixture(scope="module")
def setup():
    prob, flags = flagged_example_problem()
    system = prob.system()
    G, names, lam = default_functionals(system, coefficients=(0, 5, 17))
    return dict(prob=prob, flags=flags, system=system, G=G, names=names, lam=lam)


def _sbc(setup, sampler, seed, system=None, posterior=None, batch_size=50):
    return run_sbc(
        jax.random.PRNGKey(seed),
        setup["system"] if system is None else system,
        sampler,
        n_replicates=M,
        n_draws=L,
        functionals=setup["G"],
        names=setup["names"],
        posterior=posterior,
        batch_size=batch_size,
    )


def _report(res):
    return {n: (round(float(z), 3), float(p)) for n, z, p in zip(res.names, res.mean_z2, res.p_functional)}


def test_setup_is_realistic_and_functionals_probe_both_regimes(setup):
    flags = setup["flags"]
    assert flags.mean() > 0.3 and flags[:, 2, :].all() and flags[:, :, 7].all()
    w = np.asarray(setup["prob"].weights)
    np.testing.assert_array_equal(w == 0, flags)
    assert np.all(np.asarray(setup["prob"].data)[flags] == 0)  # NaN under flags cleaned to 0
    lam = setup["lam"]
    names = setup["names"]
    data = [k for k, s in enumerate(names) if s.startswith("data")]
    prior = [k for k, s in enumerate(names) if s.startswith("prior")]
    bal = [k for k, s in enumerate(names) if s.startswith("balanced")]
    assert len(data) == 3 and np.all(lam[data] > 1e4)  # data carry > 99.99% of the precision
    assert len(prior) == 2 and np.all(lam[prior] < 1e-3)  # prior carries > 99.9%
    assert len(bal) == 1 and 0.1 < lam[bal[0]] < 10
    assert sum(s.startswith(("a_", "Re", "Im")) for s in names) == 3


@pytest.mark.slow
@pytest.mark.parametrize(
    "sampler,seed,batch_size",
    [
        # CG with a deliberately weak (rank 8 of 25) Nystrom preconditioner, so it really
        # iterates (up to ~25 iterations); dense P (gcrsky.sample's default; the
        # matrix-free P is checked against it in test_flags.py).  Replicates one at a
        # time: the vmapped CG compiles slower than it runs here.
        (GCRSampler("cg", CGOptions(dense=True, preconditioner="nystrom", sketch_size=8)), 100, None),
        (GCRSampler("cholesky"), 101, 50),
    ],
    ids=["cg", "cholesky"],
)
def test_sbc_calibrated_with_flags(setup, sampler, seed, batch_size):
    res = _sbc(setup, sampler, seed, batch_size=batch_size)
    assert res.converged.all()
    assert res.ranks.shape == (M, len(setup["names"])) and res.ranks.max() <= L
    assert res.p_family > ALPHA, _report(res)


@pytest.mark.slow
def test_sbc_detects_reference_fluctuation_bug(setup):
    res = _sbc(setup, reference_bug_sampler, 102)
    assert res.p_family < POWER_P, _report(res)
    # it is the data-dominated directions that expose it (under-dispersed: z^2 > 1)
    k = int(np.argmin(res.p_functional))
    assert res.names[k].startswith("data") and res.mean_z2[k] > 1.3


@pytest.mark.parametrize("case", ["posterior_assumes_2sigma2", "data_have_2sigma2"])
def test_sbc_detects_noise_variance_off_by_two(setup, case):
    system = setup["system"]
    doubled = system._replace(inv_noise=system.inv_noise / 2.0)  # noise variance 2 sigma^2
    if case == "posterior_assumes_2sigma2":
        res = _sbc(setup, GCRSampler("cholesky"), 103, system=system, posterior=doubled)
        over = True  # draws too wide: z^2 < 1
    else:
        res = _sbc(setup, GCRSampler("cholesky"), 104, system=doubled, posterior=system)
        over = False
    assert res.p_family < POWER_P, _report(res)
    k = int(np.argmin(res.p_functional))
    assert res.names[k].startswith("data")
    assert (res.mean_z2[k] < 0.7) if over else (res.mean_z2[k] > 1.3)


def test_rank_pvalues_have_exact_size():
    """Under the null (iid uniform ranks) every p-value of ``rank_pvalues`` is uniform and
    the family rejects at level a with probability <= a.

    500 null data sets of M = 200, F = 2, L = 15 (numpy, fixed seed).  The KS tests of
    uniformity of the 500 p-values (3 kinds x 2 functionals, Bonferroni) and a binomial
    bound on the family's rejection rate at a = 0.05 each have false-alarm <= ALPHA.
    """
    rng = np.random.default_rng(7)
    R, m, F, Ld = 500, 200, 2, 15
    out = [rank_pvalues(rng.integers(0, Ld + 1, size=(m, F)), Ld, seed=i) for i in range(R)]
    for kind in ("p_ks", "p_dispersion", "p_bias"):
        p = np.stack([o[kind] for o in out])  # (R, F)
        for f in range(F):
            assert stats.kstest(p[:, f], "uniform").pvalue > ALPHA / (3 * F + 1), (kind, f)
    fam = np.array([o["p_family"] for o in out])
    # P(reject at 0.05) <= 0.05: the count is stochastically <= Binomial(R, 0.05)
    assert np.sum(fam <= 0.05) <= stats.binom.isf(ALPHA / (3 * F + 1), R, 0.05)
