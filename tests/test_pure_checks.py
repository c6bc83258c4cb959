"""The system tier checks what it can: bad inputs are refused on concrete arrays, reported under a trace.

References: :func:`gcrsky.model.check_system` names each bad input on concrete arrays; under
``jax.jit`` a channel with a bad input must report ``Result.BAD_INPUT`` (never converged) on
every exact path, in the Wiener filter, the draws and the evidence, while the other channel
(clean) still converges; ``throw=True`` raises naming the input.  Before the fix a NaN datum
gave "converged" draws on CG and NaN draws marked converged on Cholesky, and a negative
``inv_noise`` finite "converged" draws.  One small full-day system (lmax 6, 15 times,
12 baselines, 2 channels) so that the m-mode path applies; the bad entry is always in
channel 0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import isotropic_problem

import gcrsky
from gcrsky.inference import condition, draw, log_evidence_system, prepare_system, sample_system, wiener_filter_system
from gcrsky.solvers import CGOptions, CholeskyOptions, DataSpaceOptions, EighOptions, MModeOptions
from gcrsky.solvers.info import Result, result_names

NBL = 12  # baselines kept (of 45): the data-space D stays small

OPTIONS = {
    # sketch 8 < n = 49: a sketch of every direction makes the SLQ evidence NaN here (Lanczos on ~I), a
    # separate limitation of the CG evidence
    "cg": CGOptions(tol=1e-8, sketch_size=8),
    "cholesky": CholeskyOptions(),
    "eigh": EighOptions(),
    "mmode": MModeOptions(),
    "dataspace": DataSpaceOptions(),
}


def _with_throw(name):
    import dataclasses

    return dataclasses.replace(OPTIONS[name], throw=True)


@pytest.fixture(scope="module")
def clean(small_array, small_response):
    """Uniform full-day coverage (m-mode applies), 12 baselines, 2 channels: a clean LinearSystem."""
    nt = 2 * small_response.lmax + 3
    system = isotropic_problem(small_array, small_response, 2 * np.pi * np.arange(nt) / nt, 7).system()
    op = system.op._replace(response=system.op.response[:, :NBL])
    return system._replace(op=op, data=system.data[:, :, :NBL], inv_noise=system.inv_noise[:, :, :NBL])


def _set(x, idx, value):
    return jnp.asarray(x).at[idx].set(value)


def _nan_datum(s):
    return s._replace(data=_set(s.data, (0, 1, 2), jnp.nan))


def _negative_noise(s):
    return s._replace(inv_noise=_set(s.inv_noise, (0, 1, 2), -1.0))


def _nan_mean(s):
    return s._replace(prior=s.prior._replace(mean=_set(s.prior.mean, (0, 3), jnp.nan)))


def _negative_inv_var(s):
    return s._replace(prior=s.prior._replace(inv_var=_set(s.prior.inv_var, (0, 3), -1.0)))


def _nan_flagged_datum(s):
    s = s._replace(inv_noise=_set(s.inv_noise, (0, 1, 2), 0.0))
    return s._replace(data=_set(s.data, (0, 1, 2), jnp.nan))


#: case -> (make the bad system, what check_system says, what throw=True says)
def _nan_response(s):
    return s._replace(op=s.op._replace(response=_set(s.op.response, (0, 3, 5), jnp.inf)))


CASES = {
    "nan-datum": (_nan_datum, r"data has 1 non-finite samples, first an unflagged one", "bad input: data"),
    "negative-noise": (_negative_noise, r"inv_noise must be finite and >= 0", "bad input: inv_noise"),
    "nan-prior-mean": (_nan_mean, r"prior.mean must be finite", "bad input: prior.mean"),
    "negative-prior-inv-var": (_negative_inv_var, r"prior.inv_var must be finite and >= 0",
                               "bad input: prior.inv_var"),
    "nan-flagged-datum": (_nan_flagged_datum, r"data has 1 non-finite samples, first a flagged one",
                          "bad input: data"),
    "inf-response": (_nan_response, r"op.response has non-finite entries in channel\(s\) \[0\]",
                     "bad input: op.response"),
}


def _mistyped(clean, case):
    """A system with one input of the wrong type or shape, and the message that must name it."""
    if case == "complex-inv-noise":
        return clean._replace(inv_noise=clean.inv_noise.astype(jnp.complex128)), "inv_noise is complex128"
    if case == "real-data":
        return clean._replace(data=clean.data.real), "data is float64; it must be complex"
    if case == "complex-prior-inv-var":
        prior = clean.prior._replace(inv_var=clean.prior.inv_var.astype(jnp.complex128))
        return clean._replace(prior=prior), "prior.inv_var is complex128"
    if case == "short-inv-noise":
        return clean._replace(inv_noise=clean.inv_noise[:, :-1]), r"inv_noise has shape .*expected \(Nf, Nt, Nbl\)"
    if case == "short-data":
        return clean._replace(data=clean.data[:, :, :-1]), r"data has shape .*expected \(Nf, Nt, Nbl\)"
    prior = clean.prior._replace(mean=clean.prior.mean[:, :-2])
    return clean._replace(prior=prior), r"prior.mean has shape .*expected \(Nf, n\)"


@pytest.mark.parametrize("traced", [False, True], ids=["eager", "jit"])
@pytest.mark.parametrize("case", ["complex-inv-noise", "real-data", "complex-prior-inv-var", "short-inv-noise",
                                  "short-data", "short-prior-mean"])
def test_a_mistyped_or_misshapen_input_is_refused_naming_it(clean, case, traced, getkey):
    """A complex ``inv_noise`` was accepted (draws 2.8 K off, a complex evidence), real ``data`` read as complex
    with SUCCESS, a complex ``inv_var`` a ``while_loop`` carry-type error on CG, and under ``jit`` a shape
    mismatch ``mul got incompatible shapes`` (issue 40): types and shapes are static, so they are refused naming
    the input under a trace too, on the Wiener filter, the draws (CG) and the evidence; the control: the clean
    system passes."""
    bad, match = _mistyped(clean, case)
    key = getkey()
    calls = (lambda s: wiener_filter_system(s, options=OPTIONS["cholesky"])[0],
             lambda s: sample_system(key, s, 2, options=OPTIONS["cg"])[0],
             lambda s: log_evidence_system(s, options=OPTIONS["cholesky"])[0])
    for call in calls:
        with pytest.raises(ValueError, match=match):
            jax.block_until_ready(jax.jit(call)(bad) if traced else call(bad))
        assert np.all(np.isfinite(np.asarray(jax.jit(call)(clean) if traced else call(clean))))
    gcrsky.model.check_system(clean)


# ---------------------------------------------------------------- concrete: refused, naming the input


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("path", list(OPTIONS))
def test_concrete_bad_input_is_a_value_error_naming_it(clean, path, case, getkey):
    make, message, _ = CASES[case]
    bad, opts = make(clean), OPTIONS[path]
    with pytest.raises(ValueError, match=message):
        prepare_system(bad, options=opts)
    with pytest.raises(ValueError, match=message):
        sample_system(getkey(), bad, 2, options=opts)
    with pytest.raises(ValueError, match=message):
        wiener_filter_system(bad, options=opts)
    with pytest.raises(ValueError, match=message):
        log_evidence_system(bad, options=opts)


def test_concrete_new_data_are_checked_by_condition_and_draw(clean, getkey):
    prepared = prepare_system(clean, options=OPTIONS["cholesky"])
    bad = _nan_datum(clean).data
    with pytest.raises(ValueError, match="first an unflagged one"):
        condition(prepared, bad)
    with pytest.raises(ValueError, match="first an unflagged one"):
        draw(getkey(), prepared, 2, data=bad)


def test_check_false_skips_the_host_check_but_still_reports(clean):
    """``check=False`` on concrete arrays: no ValueError, and the fold still marks the bad channel."""
    _, info = wiener_filter_system(_negative_noise(clean), options=OPTIONS["cholesky"], check=False)
    assert np.asarray(info.result).tolist() == [Result.BAD_INPUT, Result.SUCCESS]
    assert result_names(info) == {"success": 1, "bad_input": 1}


# ---------------------------------------------------------------- under jit: BAD_INPUT, never converged


_sample = jax.jit(sample_system, static_argnums=2, static_argnames=("options",))
_wiener = jax.jit(wiener_filter_system, static_argnames=("options",))
_evidence = jax.jit(log_evidence_system, static_argnames=("options",))


def _assert_channel0_bad(result, converged):
    result, converged = np.asarray(result), np.asarray(converged)
    assert np.all(result[0] == Result.BAD_INPUT), result
    assert not np.any(converged[0])
    assert np.all(result[1] == Result.SUCCESS) and np.all(converged[1]), result  # the clean channel


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("path", list(OPTIONS))
def test_traced_bad_input_is_reported_bad_input_on_every_path(clean, path, case):
    """Under jit nothing can raise: the channel with the bad input reports BAD_INPUT in the Wiener
    filter, the draws and the evidence (NaN there), whatever its solve measured; the clean channel
    converges.  A NaN at a *flagged* sample is bad input too (as on concrete arrays: 0 * NaN is NaN in
    the Wiener right-hand side)."""
    bad, opts = CASES[case][0](clean), OPTIONS[path]
    _, info = _sample(jax.random.PRNGKey(0), bad, 3, options=opts)
    _assert_channel0_bad(info.wiener.result, info.wiener.converged)
    _assert_channel0_bad(info.draws.result, info.draws.converged)
    assert np.asarray(info.draws.result).shape == (2, 3)
    _, winfo = _wiener(bad, options=opts)
    _assert_channel0_bad(winfo.result, winfo.converged)
    value, einfo = _evidence(bad, options=opts)
    _assert_channel0_bad(einfo.solve.result, einfo.solve.converged)
    value = np.asarray(value)
    assert np.isnan(value[0]) and np.isfinite(value[1])


@pytest.mark.parametrize("path", list(OPTIONS))
def test_clean_system_converges_on_every_path_under_jit(clean, path):
    """The negative control of the test above: nothing is flagged on clean inputs."""
    opts = OPTIONS[path]
    _, info = _sample(jax.random.PRNGKey(0), clean, 3, options=opts)
    for i in (info.wiener, info.draws):
        assert np.all(np.asarray(i.result) == Result.SUCCESS) and np.all(np.asarray(i.converged))
    value, einfo = _evidence(clean, options=opts)
    assert np.all(np.isfinite(np.asarray(value))) and np.all(np.asarray(einfo.solve.converged))


def test_prepared_state_draws_and_conditioned_data_under_jit(clean):
    """``draw`` folds from the state's system; traced new data (vmap over data sets) are judged too."""
    prepared = prepare_system(clean, options=OPTIONS["cholesky"])
    datas = jnp.stack([clean.data, _nan_datum(clean).data])
    wiener = jax.vmap(lambda d: condition(prepared, d).wiener.result)(datas)
    assert np.asarray(wiener).tolist() == [[Result.SUCCESS] * 2, [Result.BAD_INPUT, Result.SUCCESS]]
    _, info = jax.jit(lambda d: draw(jax.random.PRNGKey(1), prepared, 2, data=d))(datas[1])
    _assert_channel0_bad(info.draws.result, info.draws.converged)
    st = jax.jit(lambda s: gcrsky.solvers.PATHS["cholesky"].prepare(s, OPTIONS["cholesky"]))(_negative_noise(clean))
    _, info = gcrsky.inference.draw_exactly(jax.random.PRNGKey(2), st, 2)  # a state made by the path itself
    _assert_channel0_bad(info.draws.result, info.draws.converged)


# ---------------------------------------------------------------- throw=True: an error naming the input


@pytest.mark.parametrize("case", ["nan-datum", "negative-noise"])
@pytest.mark.parametrize("path", list(OPTIONS))
def test_throw_raises_naming_the_bad_input(clean, path, case):
    make, _, message = CASES[case]
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(_wiener(make(clean), options=_with_throw(path)))


@pytest.mark.parametrize("case", ["nan-prior-mean", "negative-prior-inv-var", "nan-flagged-datum"])
def test_throw_names_every_input(clean, case):
    make, _, message = CASES[case]
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(_sample(jax.random.PRNGKey(0), make(clean), 2, options=_with_throw("cholesky")))
    with pytest.raises(Exception, match=message):
        jax.block_until_ready(_evidence(make(clean), options=_with_throw("cholesky")))


def test_throw_on_traced_new_data(clean):
    prepared = prepare_system(clean, options=_with_throw("cholesky"))
    with pytest.raises(Exception, match="bad input: data"):
        jax.block_until_ready(jax.jit(lambda d: condition(prepared, d).a_wf)(_nan_datum(clean).data))


def test_throw_on_clean_inputs_does_not_raise(clean):
    _, info = _wiener(clean, options=_with_throw("cholesky"))
    assert np.all(np.asarray(info.converged))


# ---------------------------------------------------------------- pure: no callback, gradients intact


def test_the_traced_check_adds_no_host_callback(clean):
    for path in ("cg", "cholesky"):
        text = str(jax.make_jaxpr(lambda s, o=OPTIONS[path]: wiener_filter_system(s, options=o))(clean))
        assert "callback" not in text, path


def test_gradient_of_the_evidence_is_finite_through_the_check(clean):
    def f(scale):
        s = clean._replace(inv_noise=clean.inv_noise * scale)
        return log_evidence_system(s, options=OPTIONS["cholesky"])[0].sum()

    g = jax.grad(f)(1.0)
    assert np.isfinite(float(g)) and float(g) != 0.0


def test_a_prior_only_system_converges_on_every_path(clean):
    """Every sample flagged (inv_noise 0): the Wiener filter is the prior mean, reported SUCCESS (the Nystrom
    sketch of a zero data term made CG report NONFINITE for a valid system: issue 40)."""
    prior_only = clean._replace(inv_noise=jnp.zeros_like(clean.inv_noise))
    for name, opts in OPTIONS.items():
        a, info = wiener_filter_system(prior_only, options=opts)
        assert result_names(info) == {"success": 2}, name
        np.testing.assert_allclose(np.asarray(a), np.asarray(prior_only.prior.mean), rtol=0, atol=1e-10)
