"""Flags and bad samples (DESIGN section 3): a flagged sample has no effect at all.

* :func:`gcrsky.model.noise.weights_from_flags` turns boolean flags into weights.
* Whatever a flagged sample holds (NaN, +Inf, -Inf, 1e300, finite garbage) the
  problem is *bitwise* the same: same cleaned data, precision matrix, Wiener
  filter and draws for the same key (``clean_data`` zeroes every flagged sample).
* Flagging equals removing: a problem with a whole time and a whole baseline
  flagged agrees with one built without them (operator shrunk), and a problem
  with scattered flags agrees with the dense posterior computed in numpy from the
  unflagged rows of X only.  Tolerance 1e-9 relative (and 1e-8 posterior sigma),
  why: the two routes sum the same terms in a different order (plus exact zeros),
  so P and the right-hand side differ by rounding only, measured <= 1e-16
  relative; a backward-stable solve amplifies that by at most cond(P) ~ 5.5e6,
  i.e. ~6e-10 in the worst case.  Measured 5e-11 to 2.2e-10 relative depending on
  the summation order inside the response (direct or ring quadrature, with or
  without the beam floor), so the bound is the worst case, not the typical value;
  any real leak of a flagged sample (a change of order 1 sigma, checked below) is
  1e8 times larger.
* Unflagged NaN / +-Inf is a ValueError naming (freq, time, baseline) and antennas.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import gcrsky
from gcrsky.inference import prepare_system, wiener_filter_system
from gcrsky.instrument import HERA_LATITUDE_DEG, gaussian_beam, hex_array, make_array
from gcrsky.model import LinearSystem, build_problem, dense_matrix, isotropic_prior
from gcrsky.model.noise import clean_data, weights_from_flags
from gcrsky.model.system import precision_matrix, wiener_rhs
from gcrsky.solvers import CGOptions
from gcrsky.sphere import hours_to_rad

jax.config.update("jax_enable_x64", True)

LMAX, NSIDE, NT, NBL = 4, 16, 6, 45
REL = 1e-9  # flagged vs removed: relative agreement (see module docstring)
SIG = 1e-8  # ... and in posterior-sigma units


@pytest.fixture(scope="module")
def base():
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    n = (LMAX + 1) ** 2
    prior = isotropic_prior((200.0 / (1.0 + np.arange(LMAX + 1)) ** 2)[None], n)
    rng = np.random.default_rng(0)
    sigma = rng.uniform(1.5e-4, 3e-4, (1, NT, NBL))
    lsts = hours_to_rad(np.linspace(0, 6, NT))
    truth = rng.normal(size=(1, n)) / np.sqrt(prior.inv_var)
    full = build_problem(
        arr, [100e6], lsts, LMAX, NSIDE, a_true=truth, sigma=sigma, prior=prior, key=jax.random.PRNGKey(3)
    )
    data = np.asarray(full.data)  # finite everywhere
    scattered = rng.random((1, NT, NBL)) < 0.2
    whole = np.zeros((1, NT, NBL), bool)
    whole[:, 2, :] = True  # one time
    whole[:, :, 7] = True  # one baseline

    def build(d, flags=None, lst_keep=slice(None)):
        w = None if flags is None else weights_from_flags(flags)[:, lst_keep]
        return build_problem(
            arr,
            [100e6],
            lsts[lst_keep],
            LMAX,
            NSIDE,
            data=d[:, lst_keep],
            sigma=sigma[:, lst_keep],
            weights=w,
            prior=prior,
        )

    return dict(full=full, data=data, sigma=sigma, prior=prior, scattered=scattered, whole=whole, build=build)


# ------------------------------------------------------------------ weights_from_flags


def test_weights_from_flags_semantics():
    flags = np.zeros((2, 3, 4), bool)
    flags[1, 2, 3] = flags[0, 0, 0] = True
    w = weights_from_flags(flags)
    assert w.dtype == np.float64 and w.shape == flags.shape
    np.testing.assert_array_equal(w, np.where(flags, 0.0, 1.0))
    # broadcastable flags: a whole time at every frequency and baseline
    t = np.zeros((1, 3, 1), bool)
    t[0, 1, 0] = True
    wt = weights_from_flags(t, shape=(2, 3, 4))
    assert wt.shape == (2, 3, 4) and np.all(wt[:, 1] == 0) and np.all(wt[:, [0, 2]] == 1)
    # fractional prior weights are kept where unflagged; anything (even NaN) under a flag is ignored
    nsamp = np.full((2, 3, 4), 0.5)
    nsamp[1, 2, 3] = np.nan
    wf = weights_from_flags(flags, nsamp)
    assert wf[1, 2, 3] == 0.0 and wf[0, 0, 0] == 0.0 and np.all(wf[~flags] == 0.5)


@pytest.mark.parametrize(
    "args,err,match",
    [
        ((np.zeros((1, 2, 3), int),), TypeError, "boolean"),
        ((np.zeros((1, 2, 3), float),), TypeError, "boolean"),
        ((np.zeros((2, 3), bool), None, (1, 2, 4)), ValueError, "do not broadcast"),
        ((np.zeros((1, 2, 3), bool), np.ones((1, 2, 4))), ValueError, "do not broadcast"),
        ((np.zeros((1, 2, 3), bool), np.full((1, 2, 3), 1.5)), ValueError, r"\[0, 1\]"),
        ((np.zeros((1, 2, 3), bool), np.full((1, 2, 3), np.nan)), ValueError, r"\[0, 1\]"),
    ],
)
def test_weights_from_flags_rejects_bad_input(args, err, match):
    with pytest.raises(err, match=match):
        weights_from_flags(*args)


# --------------------------------------------------- garbage under a flag changes nothing


def _garbage(flags, kinds):
    out = np.zeros(flags.shape, complex)
    idx = np.argwhere(flags)
    for j, i in enumerate(idx):
        out[tuple(i)] = kinds[j % len(kinds)]
    return out


def test_garbage_under_flags_gives_bitwise_identical_posterior(base):
    flags = base["scattered"] | base["whole"]
    bad = np.where(
        flags,
        _garbage(flags, [np.nan, np.inf, -np.inf, 1e300, complex(np.nan, np.inf), complex(1e300, -np.inf)]),
        base["data"],
    )
    rng = np.random.default_rng(1)
    junk = rng.normal(size=flags.shape) * 1e3 + 1j * rng.normal(size=flags.shape) * 1e3
    ref = np.where(flags, junk, base["data"])
    p_bad, p_ref = base["build"](bad, flags), base["build"](ref, flags)
    d_bad = np.asarray(p_bad.data)
    assert np.all(np.isfinite(d_bad)) and np.all(d_bad[flags] == 0)
    np.testing.assert_array_equal(d_bad, np.asarray(p_ref.data))
    np.testing.assert_array_equal(np.asarray(p_bad.precision_matrix()), np.asarray(p_ref.precision_matrix()))
    # Wiener filter and draws (same key) through the exact sampler; CG's inputs are the
    # same bitwise-identical arrays (and its fluctuation term never reads the data)
    prep_bad, prep_ref = gcrsky.prepare(p_bad, method="cholesky"), gcrsky.prepare(p_ref, method="cholesky")
    np.testing.assert_array_equal(np.asarray(prep_bad.a_wf), np.asarray(prep_ref.a_wf))
    key = jax.random.PRNGKey(17)
    d1, d2 = gcrsky.draw(key, prep_bad, 3)[0], gcrsky.draw(key, prep_ref, 3)[0]
    assert np.all(np.isfinite(np.asarray(d1)))
    np.testing.assert_array_equal(np.asarray(d1), np.asarray(d2))
    # and the linear algebra itself ignores finite garbage under a zero weight, even
    # uncleaned (0 * 1e300 == 0 exactly); only non-finite values need clean_data
    sys_ref = p_ref.system()
    raw = jnp.asarray(np.where(flags, 1e300 * (1 + 1j), base["data"]))
    np.testing.assert_array_equal(np.asarray(wiener_rhs(sys_ref._replace(data=raw))), np.asarray(wiener_rhs(sys_ref)))


# ---------------------------------------------------------- flagging equals removing


def _sigma_units(P):
    return np.sqrt(np.diag(np.linalg.inv(P)))


def _assert_close(a, b, sig, what):
    rel = np.abs(a - b).max() / np.abs(b).max()
    ins = (np.abs(a - b) / sig).max()
    assert rel < REL and ins < SIG, (what, rel, ins)


def test_flagged_time_and_baseline_equal_removing_them(base):
    whole = base["whole"]
    p_flag = base["build"](np.where(whole, np.nan, base["data"]), whole)
    # without them: build the problem on the other 5 LSTs, then drop baseline 7 from the operator
    kt, kb = np.arange(NT) != 2, np.arange(NBL) != 7
    st = base["build"](base["data"], None, kt).system()
    s_drop = LinearSystem(
        st.op._replace(response=st.op.response[:, kb]), st.data[..., kb], st.inv_noise[..., kb], st.prior
    )
    assert s_drop.data.shape == (1, NT - 1, NBL - 1)
    s_flag = p_flag.system()
    P1, P2 = np.asarray(precision_matrix(s_flag))[0], np.asarray(precision_matrix(s_drop))[0]
    assert np.abs(P1 - P2).max() < 1e-14 * np.abs(P2).max()
    sig = _sigma_units(P2)
    c1, c2 = prepare_system(s_flag, method="cholesky"), prepare_system(s_drop, method="cholesky")
    _assert_close(np.asarray(c1.a_wf)[0], np.asarray(c2.a_wf)[0], sig, "Wiener filter")
    key = jax.random.PRNGKey(5)  # Cholesky draws use z of shape (Nf, n): same key, same z
    d1, d2 = gcrsky.draw(key, c1, 4)[0], gcrsky.draw(key, c2, 4)[0]
    _assert_close(np.asarray(d1)[0], np.asarray(d2)[0], sig, "Cholesky draws")
    # non-vacuous: keeping those (finite, informative) samples moves the posterior by ~sigma
    c_all = prepare_system(base["build"](base["data"]).system(), method="cholesky")
    assert (np.abs(np.asarray(c_all.a_wf)[0] - np.asarray(c2.a_wf)[0]) / sig).max() > 0.1


def test_scattered_flags_equal_dense_posterior_of_unflagged_rows(base):
    flags = base["scattered"] | base["whole"]
    p = base["build"](np.where(flags, np.nan, base["data"]), flags)
    # numpy reference from the unflagged rows of the dense X only
    X = np.asarray(dense_matrix(p.operator()))[0]  # (Nt, Nbl, n)
    keep = ~flags[0]
    Xk, dk = X[keep], base["data"][0][keep]
    Wk = 1.0 / base["sigma"][0][keep] ** 2
    sinv, a0 = np.asarray(p.prior.inv_var)[0], np.asarray(p.prior.mean)[0]
    P = Xk.real.T @ (Wk[:, None] * Xk.real) + Xk.imag.T @ (Wk[:, None] * Xk.imag) + np.diag(sinv)
    b = Xk.real.T @ (Wk * dk.real) + Xk.imag.T @ (Wk * dk.imag) + sinv * a0
    a_ref = np.linalg.solve(P, b)
    sig = _sigma_units(P)
    Pg = np.asarray(p.precision_matrix())[0]
    assert np.abs(Pg - P).max() < 1e-14 * np.abs(P).max()
    np.testing.assert_allclose(np.asarray(wiener_rhs(p.system()))[0], b, rtol=0, atol=1e-14 * np.abs(b).max())
    prep = gcrsky.prepare(p, method="cholesky")
    _assert_close(np.asarray(prep.a_wf)[0], a_ref, sig, "Cholesky Wiener filter")
    # matrix-free CG (flags enter through W in every matvec): with the rank-128 >= n Nystrom
    # preconditioner err_sigma bounds the error's P-norm, which bounds every mode's error
    # in sigma units; 1e-9 is just above the rounding floor of the residual (~1.4e-10)
    a_cg, info = wiener_filter_system(p.system(), options=CGOptions(dense=False), tol=1e-9)
    assert bool(info.converged.all())
    assert (np.abs(np.asarray(a_cg)[0] - a_ref) / sig).max() < 1e-9
    # Cholesky draws: a_ref + L^-T z with z = normal(split(fold_in(key, 0), k)[i], (Nf, n)) (one bucket of 4)
    key, k = jax.random.PRNGKey(9), 4
    z = np.stack([np.asarray(jax.random.normal(kk, (1, P.shape[0])))[0]
                  for kk in jax.random.split(jax.random.fold_in(key, 0), k)])
    Lc = np.linalg.cholesky(P)
    ref_draws = a_ref[None] + np.linalg.solve(Lc.T, z.T).T
    draws, _ = gcrsky.sample(key, p, k, method="cholesky")
    _assert_close(np.asarray(draws)[0], ref_draws, sig, "Cholesky draws")
    # non-vacuous: with every row the posterior is materially different
    P_all = np.asarray(base["full"].precision_matrix())[0]
    assert np.abs(P_all - P).max() > 0.05 * np.abs(P).max()


# ------------------------------------------------------- unflagged bad data is an error


@pytest.mark.parametrize(
    "value,kind",
    [
        (np.nan, "NaN"),
        (np.inf, r"\+Inf"),
        (-np.inf, "-Inf"),
        (complex(0.5, np.inf), r"\+Inf"),
        (complex(np.nan, 1), "NaN"),
    ],
)
def test_unflagged_non_finite_is_an_error_naming_the_sample(base, value, kind):
    flags = base["whole"]
    d = np.where(flags, np.nan, base["data"])  # flagged NaN are fine ...
    d[0, 3, 11] = value  # ... this one is not
    with pytest.raises(ValueError, match=rf"1 non-finite unflagged.*{kind}.*\(freq, time, baseline\) = \(0, 3, 11\)"):
        base["build"](d, flags)
    # with the antenna pairs the message names the antennas too
    pairs = base["full"].antpairs
    iv = weights_from_flags(flags)
    with pytest.raises(ValueError, match=rf"\(0, 3, 11\) \(antennas {pairs[11][0]}-{pairs[11][1]}\)"):
        clean_data(d, iv, antpairs=pairs)
    # flagging it makes it harmless
    f2 = flags.copy()
    f2[0, 3, 11] = True
    assert np.all(np.isfinite(np.asarray(base["build"](d, f2).data)))


def test_build_problem_flags_argument(base):
    """``build_problem(flags=...)`` is ``weights=weights_from_flags(flags)``; flags combine with weights."""
    d = base["data"].copy()
    d[base["scattered"]] = np.nan
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))
    lsts = hours_to_rad(np.linspace(0, 6, NT))
    common = dict(data=d, sigma=base["sigma"], prior=base["prior"])
    by_flags = build_problem(arr, [100e6], lsts, LMAX, NSIDE, flags=base["scattered"], **common)
    by_weights = base["build"](d, base["scattered"])
    np.testing.assert_array_equal(np.asarray(by_flags.weights), np.asarray(by_weights.weights))
    np.testing.assert_array_equal(np.asarray(by_flags.data), np.asarray(by_weights.data))
    half = build_problem(arr, [100e6], lsts, LMAX, NSIDE, flags=base["scattered"], weights=0.5, **common)
    np.testing.assert_array_equal(np.asarray(half.weights), 0.5 * np.asarray(by_flags.weights))
    with pytest.raises(ValueError, match=r"antennas"):
        build_problem(arr, [100e6], lsts, LMAX, NSIDE, **common)  # NaN left unflagged
