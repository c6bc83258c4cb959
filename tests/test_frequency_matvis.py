"""Inpainting flagged channels of a GSM sky simulated by matvis (issue 25, "what it must show").

The observation (:func:`gcrsky.checks.multifreq.simulate_gsm_observation`, defaults): pyradiosky's
GSM truncated to lmax 8 (n = 81; the data hold no sky beyond it, so this is about the frequency
model, not truncation), 32 channels 100-131 MHz, the 10-antenna hexagon of 14 m Gaussian dishes
at HERA (45 baselines), 16 real times over a day, matvis with per-channel maps, thermal noise at
snr 50 (sigma ~ nu^-2.55), channels 8-11 and 20-23 flagged (25 %).  matvis and gcrsky's model
of the same truth differ by 0.034 sigma (rms, worst channel: the two quadratures), so the
model error is negligible.

The model: the joint dense posterior (:func:`gcrsky.solvers.joint.prepare_joint_dense`, the
operator has a frame map) under the log-frequency kernel prior with ``C_l(nu0)`` the GSM's
shipped table (:func:`gcrsky.model.skyprior.gsm_cl`, nu0 = 115 MHz) and fixed hyperparameters
(``HYPER``) near the maximum of the joint evidence (``joint_log_evidence_dense`` with BFGS in
log A, beta, log xi, log nugget: see ``HYPER``'s comment; too slow to refit here).

What it shows, at the flagged channels only (prior-whitened: ``lambda_i`` and ``v_i`` the
generalised eigenpairs of (posterior covariance, prior covariance) restricted to the 8 flagged
channels, 648 dimensions; ``z_i = v_i^T (a_true - a_wf) / sqrt(lambda_i)``):

* coupled: along the directions the data and the coupled prior constrain (``lambda_i < 0.1``,
  the posterior variance below a tenth of the prior's; 57 of 648 directions) ``sum z^2`` is
  chi^2 with that many degrees of freedom: two-sided test at false-alarm rate 1e-3 (measured
  sum z^2 / K = 0.97, chi^2 upper-tail p = 0.54);
* independent (``R`` the kernel's diagonal): the flagged channels are prior-only (the posterior
  mean is the prior mean and the covariance the prior's, to rounding), and their error is far
  larger than the coupled model's;
* negative control (must fail): the coupled prior with spectral index 0 instead of ~-2.4 gives
  ``sum z^2 / K`` = 151 (measured), chi^2 upper-tail p < 1e-6 asserted;
* the evidence prefers the coupled model over both.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import pytest
import scipy.linalg as sl
from scipy import stats

pytest.importorskip("matvis")
pytest.importorskip("pyradiosky")
from astropy.utils import iers

from gcrsky.checks.multifreq import (
    flag_blocks_mask,
    gsm_truth,
    joint_system,
    simulate_gsm_observation,
)
from gcrsky.model.gsmsky import gsm_maps
from gcrsky.model.operator import apply
from gcrsky.model.skyprior import gsm_cl
from gcrsky.model.spectral import frequency_prior, log_frequency_kernel
from gcrsky.solvers.joint import joint_log_evidence_dense, prepare_joint_dense

NU0 = 115e6
#: Kernel hyperparameters (A, beta, xi, nugget) at the joint evidence's maximum for this observation
#: (optimistix BFGS on log A, beta, log xi, log nugget from (1, -2.5, 0.3, 1e-4): 69 steps, converged;
#: log evidence 86567.7 at the start, 86936.3 at the maximum).  xi ~ 25 >> the band's log range
#: 0.27 and a nugget of 7e-8: over 100-131 MHz every GSM mode is one power law of index -2.40, to the
#: data's precision.
HYPER = dict(amplitude=1.42, beta=-2.40, xi=24.7, nugget=7.44e-8)
WRONG_BETA = 0.0
#: A direction is "constrained" where its posterior variance is below this fraction of the prior's.
CONSTRAINED = 0.1
FALSE_ALARM = 1e-3


@pytest.fixture(scope="module")
def obs():
    with iers.conf.set_temp("auto_download", False), iers.conf.set_temp("auto_max_age", None):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # astropy / pyuvdata chatter (IERS ranges, beam keywords)
            return simulate_gsm_observation()


def _cl(lmax):
    return np.asarray(gsm_cl([NU0], lmax))[0]


class Fit(NamedTuple):
    state: object
    evidence: float
    post: np.ndarray  # (|fl| n, |fl| n) posterior covariance at the flagged channels
    prior: np.ndarray  # (|fl| n, |fl| n) prior covariance at the flagged channels
    err: np.ndarray  # (|fl|, n) a_true - a_wf at the flagged channels


def _fit(obs, R) -> Fit:
    prior = frequency_prior(_cl(obs.lmax), R)
    st = prepare_joint_dense(joint_system(obs, prior))
    fl = np.flatnonzero(obs.flags)
    LR, sc = np.asarray(st.chol_r), np.asarray(st.sqrt_c)
    nf, n = LR.shape[0], sc.size
    # G^T restricted to the flagged channels' columns: G = L_R (x) diag(sqrt c), so the posterior
    # covariance there is B^T M^-1 B with B = G^T E_fl (the whitened form of joint.py)
    B = np.einsum("fh,k,kj->hkfj", LR[fl], sc, np.eye(n)).reshape(nf * n, fl.size * n)
    post = B.T @ np.asarray(jsl.cho_solve((st.chol, True), jnp.asarray(B)))
    prior_cov = np.kron(np.asarray(R)[np.ix_(fl, fl)], np.diag(sc**2))
    err = (obs.truth - np.asarray(st.a_wf))[fl]
    return Fit(st, float(joint_log_evidence_dense(st)), 0.5 * (post + post.T), prior_cov, err)


def _kernel(obs, **kw):
    return log_frequency_kernel(obs.freqs_hz, NU0, **{**HYPER, **kw})


@pytest.fixture(scope="module")
def coupled(obs):
    return _fit(obs, _kernel(obs))


@pytest.fixture(scope="module")
def independent(obs):
    return _fit(obs, jnp.diag(jnp.diag(_kernel(obs))))


@pytest.fixture(scope="module")
def wrong_beta(obs):
    return _fit(obs, _kernel(obs, beta=WRONG_BETA))


def _z2(fit: Fit):
    """(sum z^2, K, lambdas) over the constrained prior-whitened directions (module docstring)."""
    lam, V = sl.eigh(fit.post, fit.prior)
    z = (V.T @ fit.err.reshape(-1)) / np.sqrt(lam)
    sel = lam < CONSTRAINED
    return float(np.sum(z[sel] ** 2)), int(sel.sum()), lam


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


# ---------------------------------------------------------------- the simulation


def test_observation_is_what_it_claims(obs):
    nf, n = obs.truth.shape
    assert nf >= 32 and n == (obs.lmax + 1) ** 2
    assert obs.flags.sum() == nf // 4  # 25 %, two contiguous blocks of 4
    assert np.array_equal(np.flatnonzero(obs.flags), np.r_[8:12, 20:24])
    assert np.all(obs.inv_noise[obs.flags] == 0) and np.all(obs.data[obs.flags] == 0)
    assert np.all(obs.inv_noise[~obs.flags] > 0)
    # thermal noise follows the sky-dominated T_sys ~ nu^-2.55
    np.testing.assert_allclose(obs.sigma / obs.sigma[0], (obs.freqs_hz / obs.freqs_hz[0]) ** -2.55, rtol=1e-12)
    # matvis vs gcrsky's model of the same truth: far below the noise (measured 0.034 sigma at worst)
    assert np.max(obs.model_error / obs.sigma) < 0.1
    # the whitened residual of the unflagged data at the truth is the noise: chi^2 per real dof ~ 1
    # (measured 0.9965; 2 * 45 * 16 * 24 = 34560 dof: +-0.03 is 3.9 sigma of chi^2 per dof, false alarm 1e-4)
    r = obs.data - np.asarray(apply(obs.op, jnp.asarray(obs.truth)))
    keep = ~obs.flags
    chi2 = np.sum(obs.inv_noise[keep] * np.abs(r[keep]) ** 2) / (2 * obs.inv_noise[keep].size)
    print(f"\nunflagged data at the truth: chi^2 per real dof {chi2:.4f}")
    assert abs(chi2 - 1.0) < 0.03, chi2
    # the truth's monopole is the GSM map's mean (a_00 = sqrt(4 pi) <T>), independently of map2alm; to
    # 1e-3: measured 4.7e-4 (map2alm's iterations fit l <= 8 by least squares on the nside-8 pixels, and
    # the map's power above l = 8 leaks into it); a wrong unit or channel would be off by > 1 %
    maps, _ = gsm_maps(obs.freqs_hz)
    np.testing.assert_allclose(obs.truth[:, 0], np.sqrt(4 * np.pi) * maps.mean(axis=1), rtol=1e-3)


def test_bad_flags_and_lmax_raise():
    with pytest.raises(ValueError, match="overlaps"):
        flag_blocks_mask(32, ((8, 4), (10, 4)))
    with pytest.raises(ValueError, match="not inside"):
        flag_blocks_mask(32, ((30, 4),))
    with pytest.raises(ValueError, match="every channel"):
        flag_blocks_mask(4, ((0, 4),))
    with pytest.raises(ValueError, match="lmax"):
        gsm_truth([100e6], 17)


# ---------------------------------------------------------------- inpainting


def test_coupled_posterior_contains_truth_at_flagged_channels(coupled, independent):
    s, K, lam = _z2(coupled)
    # the data and the coupled prior constrain a real subspace at the unobserved channels (57 measured)
    assert K >= 20, K
    lo, hi = stats.chi2.ppf([FALSE_ALARM / 2, 1 - FALSE_ALARM / 2], K)
    print(f"\ncoupled: sum z^2 = {s:.1f} over K = {K} constrained directions (chi^2 {lo:.1f}..{hi:.1f})")
    assert lo < s < hi, f"sum z^2 = {s:.1f}, K = {K}: outside the chi^2 band [{lo:.1f}, {hi:.1f}]"


def test_independent_flagged_channels_are_prior_only(obs, coupled, independent):
    fl = np.flatnonzero(obs.flags)
    # posterior mean = prior mean (0) and covariance = prior covariance, to rounding
    a_wf = np.asarray(independent.state.a_wf)[fl]
    assert np.max(np.abs(a_wf)) < 1e-9 * np.max(np.abs(obs.truth)), np.max(np.abs(a_wf))
    np.testing.assert_allclose(independent.post, independent.prior, rtol=0, atol=1e-10 * np.max(independent.prior))
    # the errors: the independent model's is the truth itself (prior mean 0)
    e_ind, e_cpl = _rms(independent.err), _rms(coupled.err)
    e_ind1, e_cpl1 = _rms(independent.err[:, 1:]), _rms(coupled.err[:, 1:])
    # in the directions the coupled model constrains, in units of the prior sigma
    lam, V = sl.eigh(coupled.post, coupled.prior)
    sel = lam < CONSTRAINED
    p_ind = _rms(V[:, sel].T @ independent.err.reshape(-1))
    p_cpl = _rms(V[:, sel].T @ coupled.err.reshape(-1))
    unfl = ~obs.flags
    e_obs = _rms((obs.truth - np.asarray(coupled.state.a_wf))[unfl])
    print(f"\nrms error at the flagged channels, K: independent {e_ind:.3g}, coupled {e_cpl:.3g} "
          f"(l > 0: {e_ind1:.3g}, {e_cpl1:.3g}); coupled at the unflagged channels {e_obs:.3g}; "
          f"rms truth there {_rms(obs.truth[fl]):.3g}; constrained directions (prior sigma): "
          f"independent {p_ind:.3g}, coupled {p_cpl:.3g}; log evidence coupled - independent "
          f"{coupled.evidence - independent.evidence:.1f}")
    assert e_ind > 3 * e_cpl  # measured 375 K vs 56.4 K (6.6x); the coupled error matches the observed channels'
    # in the constrained directions the independent error is the truth, ~1 prior sigma (measured 1.04), the
    # coupled one ~ its posterior sigma (measured 0.109, 9.6x smaller)
    assert p_ind > 5 * p_cpl
    assert coupled.evidence > independent.evidence + 100  # measured +4053


def test_wrong_spectral_index_fails(coupled, wrong_beta):
    s, K, _ = _z2(wrong_beta)
    p = stats.chi2.sf(s, K)
    print(f"\nwrong beta {WRONG_BETA}: sum z^2 / K = {s / K:.1f} (K = {K}), p = {p:.2g}")
    assert p < 1e-6, (s, K, p)  # measured sum z^2 / K = 151, p = 0 (underflow)
    assert coupled.evidence > wrong_beta.evidence + 100  # measured +62386
