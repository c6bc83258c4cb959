"""The frequency-coupled prior's hyperparameters: maximum joint evidence, collapsed NUTS, an evidence table.

The model (DESIGN section 13, :mod:`gcrsky.model.spectral`): all channels' realified coefficients
``a (Nf, n)`` are jointly Gaussian, ``a ~ N(a0, R (x) diag(c))`` with ``c`` the per-entry variances
of ``C_l(nu0)`` (:func:`gcrsky.model.spectral.mode_variance`) and the log-frequency kernel

    R(nu, nu') = A (nu nu' / nu0^2)^beta exp(-(log nu - log nu')^2 / (2 xi^2)) (+ nugget on the diagonal)

(:func:`gcrsky.model.spectral.log_frequency_kernel`).  The hyperparameters are fitted and sampled in
an unconstrained parametrisation, a dict ``theta`` with the keys of :data:`HYPER_NAMES`:

* ``"log_amplitude"``: ``log A`` (natural log).  ``A`` scales ``C_l(nu0)``: ``R (x) diag(c)``
  depends on A and on the ``C_l`` amplitude only through their product, so ``A`` *is* the ``C_l``
  amplitude (fitting both would be exactly degenerate; the shape of ``C_l`` is fixed by
  :class:`SpectralModel`);
* ``"beta"``: the spectral index of the standard deviation (the variance goes as ``nu^(2 beta)``);
* ``"log_xi"``: ``log xi``, the correlation length in ``log nu`` (``xi -> 0``: independent channels,
  ``xi -> inf``: one power law for all channels).

Any of them can be held fixed (``fixed=``, a dict of values); the free ones are
``jax.flatten_util.ravel_pytree(theta0)``'s order (sorted keys: ``beta``, ``log_amplitude``,
``log_xi``), which is the order of a fit's Laplace covariance.

The prior mean is a power law of one (n,) map at nu0, ``a0(nu) = (nu/nu0)^beta m0``
(``SpectralModel.mean0``; default zero), so the three models of :func:`evidence_table` have the same
mean and their evidences are of the same data under comparable priors.

The joint log evidence ``log p(d | theta)`` of all channels together is exact and differentiable
(:func:`gcrsky.solvers.joint.joint_log_evidence_dense` / ``_mmode``); ``method`` picks the path, by its
name in :data:`gcrsky.solvers.registry.PATHS`:
``"cholesky"`` for small joint systems (``Nf n <= DENSE_SMALL``), else ``"mmode"`` where the coverage
is uniform over the full day with time-constant noise (:func:`gcrsky.solvers.mmode_check`: blocks of
``Nf s_m``), else ``"cholesky"`` (one ``(Nf n)^2`` Cholesky; refused beyond ``memory_budget``).  ``"dense"``, the
former name of ``"cholesky"``, is still accepted (deprecated: a ``DeprecationWarning``).  ``"auto"`` decides on concrete
arrays; under a trace give it explicitly.

* :func:`fit_spectral_hyperparameters`: BFGS (optimistix) on ``log p(d | theta) + log_prior(theta)``
  inside JAX, Laplace covariance from the Hessian (returns :class:`gcrsky.inference.hyper.FitResult`);
* :func:`sample_spectral_hyperparameters`: NUTS (blackjax) on the same density
  (:func:`gcrsky.inference.collapsed.nuts_chain`), then :func:`draw_given_spectral_hyperparameters`:
  exact joint draws of ``a | theta_i, d`` for each sample (``draw_joint_dense`` / ``_mmode``);
* :func:`spectral_log_density`: that density as a pure function of the flattened ``theta``
  (vmappable over data sets, e.g. simulation-based calibration);
* :func:`evidence_table`: on the same data, the maximum log evidence of (i) independent channels
  (each channel its own isotropic prior ``A C_l (nu/nu0)^(2 beta) (1 + nugget)``, the ``xi -> 0``
  limit), (ii) the paper's power-law template (:func:`gcrsky.model.spectral_template_system`, the
  ``xi -> inf`` limit without nugget), (iii) the coupled kernel, each at its own fitted
  hyperparameters.  All three are normalised densities of the same data vector (every channel's
  unflagged samples, constants included), so their differences are log Bayes factors at the
  fitted hyperparameters (type-II maximum likelihood: the coupled model has one more
  hyperparameter than the other two, and contains both as limits).

The default hyperprior :data:`WEAK_HYPERPRIOR` is stated there; pass ``log_prior=None`` for a flat
one (the evidence alone must then make the posterior proper, which it does not as ``xi -> 0``
or ``xi -> inf``, where the evidence goes flat).
"""

from __future__ import annotations

import logging
import warnings
from functools import partial
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ..model.prior import Prior
from ..model.spectral import FrequencyPrior, frequency_prior, log_frequency_kernel, mode_variance
from ..model.system import LinearSystem
from ..model.template import spectral_template_system
from ..solvers.joint import (
    JointSystem,
    check_joint_system,
    data_system,
    draw_joint_dense,
    draw_joint_mmode,
    joint_log_evidence_dense,
    joint_log_evidence_mmode,
    prepare_joint_dense,
    prepare_joint_mmode,
)
from ..solvers.mmode import mmode_check
from ..solvers.path import is_traced
from ..solvers.registry import options_for
from .collapsed import CollapsedSamples, blackjax_module, nuts_chain
from .hyper import FitResult, fit_hyperparameters

__all__ = [
    "DENSE_SMALL",
    "HYPER_NAMES",
    "WEAK_HYPERPRIOR",
    "EvidenceTable",
    "GaussianHyperprior",
    "SpectralModel",
    "choose_method",
    "draw_given_spectral_hyperparameters",
    "evidence_table",
    "fit_spectral_hyperparameters",
    "independent_system",
    "joint_system",
    "sample_spectral_hyperparameters",
    "spectral_log_density",
    "spectral_log_evidence",
    "spectral_prior",
    "template_system",
]

log = logging.getLogger(__name__)

HYPER_NAMES = ("log_amplitude", "beta", "log_xi")

#: ``"auto"`` takes the dense path up to this joint size ``Nf n``: small factors cost less than the m-mode
#: path's per-bucket work (measured at Nf n = 64, lmax 3: the jitted evidence and gradient take 6 ms
#: dense, 180 ms m-mode, on 2 shared CPU cores; the crossover itself was not measured, and at 1024 the
#: dense factor is 8 MiB and its Cholesky 0.4 Gflop).
DENSE_SMALL = 1024


class SpectralModel(NamedTuple):
    """What the hyperparameters do not change (a PyTree of arrays: it may be traced).

    Attributes:
        freqs_hz: (Nf,) channel frequencies, Hz.
        nu0_hz: reference frequency, Hz (scalar).
        cl: (lmax+1,) the shape of the angular power spectrum at nu0, K^2 (multiplied by A).
        nugget: relative jitter of the kernel (>= 0; :func:`gcrsky.model.spectral.log_frequency_kernel`).
        mean0: (n,) prior mean at nu0, Kelvin, or None (zero); channel f's mean is
            ``(nu_f / nu0)^beta mean0``.
    """

    freqs_hz: Any
    nu0_hz: Any
    cl: Any
    nugget: Any = 1e-6
    mean0: Any = None


class GaussianHyperprior(NamedTuple):
    """Independent normal log hyperprior ``sum_k -1/2 ((theta_k - mean_k) / sd_k)^2`` over the named keys.

    Hashable (tuples of floats), so it can be a static argument of the jitted fits.  Keys of
    ``theta`` it does not name get a flat prior; names missing from ``theta`` (held fixed) are skipped.
    The value omits the normalising constant (it cancels in a fit and in NUTS).

    Attributes:
        names: keys (a subset of :data:`HYPER_NAMES`).
        mean, sd: one float each, in the unconstrained units (``log A``, ``beta``, ``log xi``).
    """

    names: tuple
    mean: tuple
    sd: tuple

    def __call__(self, theta) -> jax.Array:
        out = 0.0
        for k, mu, sd in zip(self.names, self.mean, self.sd):
            if k in theta:
                out = out - 0.5 * ((theta[k] - mu) / sd) ** 2
        return jnp.asarray(out)


#: The default weak hyperprior: ``log A ~ N(0, 3^2)`` (A within a factor ~400 of 1, i.e. of the given
#: ``C_l`` at nu0, at 2 sigma), ``beta ~ N(-2.5, 1.5^2)`` (synchrotron-like skies have -2.5 +- 0.2 in
#: brightness temperature), ``log xi ~ N(log 0.1, 2^2)`` (correlation lengths 2e-3 .. 5 in ln nu at
#: 2 sigma: from decoupled channels to one power law over any radio band).
WEAK_HYPERPRIOR = GaussianHyperprior(HYPER_NAMES, (0.0, -2.5, float(np.log(0.1))), (3.0, 1.5, 2.0))


def _full(theta, fixed) -> dict:
    p = {**(fixed or {}), **theta}
    unknown = set(p) - set(HYPER_NAMES)
    if unknown:
        raise ValueError(f"unknown hyperparameters {sorted(unknown)}; the names are {HYPER_NAMES}")
    missing = [k for k in HYPER_NAMES if k not in p]
    if missing:
        raise ValueError(f"hyperparameters {missing} are neither in theta nor fixed")
    return p


def _scale(model: SpectralModel, beta) -> jax.Array:
    return (jnp.asarray(model.freqs_hz, jnp.float64) / model.nu0_hz) ** beta  # (Nf,)


def _mean(model: SpectralModel, beta):
    if model.mean0 is None:
        return None
    return _scale(model, beta)[:, None] * jnp.asarray(model.mean0)[None, :]


def spectral_prior(model: SpectralModel, theta, fixed=None) -> FrequencyPrior:
    """The :class:`~gcrsky.model.spectral.FrequencyPrior` at ``theta`` (dict, unconstrained; module docstring).

    ``R = log_frequency_kernel(freqs, nu0, exp(log_amplitude), beta, exp(log_xi), nugget)``,
    ``mode_var`` from ``model.cl``, mean ``(nu/nu0)^beta mean0``.  Differentiable in ``theta``.
    """
    p = _full(theta, fixed)
    R = log_frequency_kernel(model.freqs_hz, model.nu0_hz, jnp.exp(p["log_amplitude"]), p["beta"],
                             jnp.exp(p["log_xi"]), nugget=model.nugget)
    return frequency_prior(model.cl, R, mean=_mean(model, p["beta"]))


def joint_system(system: JointSystem, model: SpectralModel, theta, fixed=None) -> JointSystem:
    """``system`` (its operator, data and noise) with the coupled prior at ``theta``."""
    return system._replace(prior=spectral_prior(model, theta, fixed))


def independent_system(system: JointSystem, model: SpectralModel, theta, fixed=None) -> LinearSystem:
    """The independent-channel model: channel f's own isotropic prior, variances ``c R_ff``.

    ``R_ff = A (nu_f/nu0)^(2 beta) (1 + nugget)`` (the kernel's diagonal, so this is the coupled
    model's ``xi -> 0`` limit); mean ``(nu_f/nu0)^beta mean0``.  ``log_xi`` may be absent.
    Returns a per-channel :class:`~gcrsky.model.LinearSystem` (Nf channels) for
    :func:`gcrsky.inference.evidence.log_evidence`.
    """
    p = _full(theta, {"log_xi": 0.0, **(fixed or {})})
    c = mode_variance(model.cl)
    var = jnp.exp(p["log_amplitude"]) * (1.0 + model.nugget) * _scale(model, p["beta"]) ** 2  # (Nf,)
    nf, n = var.shape[0], c.shape[0]
    mean = _mean(model, p["beta"])
    mean = jnp.zeros((nf, n), c.dtype) if mean is None else mean
    return LinearSystem(system.op, system.data, system.inv_noise, Prior(mean, 1.0 / (var[:, None] * c[None, :])))


def template_system(system: JointSystem, model: SpectralModel, theta, fixed=None) -> LinearSystem:
    """The paper's power-law template ``a(nu) = (nu/nu0)^beta a_0``, ``a_0 ~ N(mean0, A C_l)``.

    :func:`gcrsky.model.spectral_template_system` of the data: one block whose baseline axis runs
    over (channel, baseline), so its evidence is of the same data as the other models' (the
    coupled model's ``xi -> inf`` limit without nugget).  ``log_xi`` may be absent.
    """
    p = _full(theta, {"log_xi": 0.0, **(fixed or {})})
    c = mode_variance(model.cl)
    mean = jnp.zeros_like(c) if model.mean0 is None else jnp.asarray(model.mean0, c.dtype)
    prior = Prior(mean[None], 1.0 / (jnp.exp(p["log_amplitude"]) * c)[None])
    ds = data_system(system)
    return spectral_template_system(ds, model.freqs_hz, p["beta"], nu0_hz=model.nu0_hz, prior=prior)


# ---------------------------------------------------------------- the evidence and its path


#: The joint evidence's paths (names of :data:`gcrsky.solvers.registry.PATHS`): their exact joint log evidence
#: and joint draws ``(prepare, draw)`` (:mod:`gcrsky.solvers.joint`).
_EVIDENCE = {"cholesky": joint_log_evidence_dense, "mmode": joint_log_evidence_mmode}
_DRAWS = {"cholesky": (prepare_joint_dense, draw_joint_dense), "mmode": (prepare_joint_mmode, draw_joint_mmode)}


def _path_name(method: str) -> str:
    """``method`` by its registry name: ``"dense"`` (deprecated) is ``"cholesky"``."""
    if method == "dense":
        warnings.warn("method='dense' is deprecated: the joint evidence's dense path is the registry's 'cholesky'",
                      DeprecationWarning, stacklevel=3)
        return "cholesky"
    return method


def choose_method(system: JointSystem, method: str = "auto", *, memory_budget: float | None = 2**31) -> str:
    """``"mmode"`` or ``"cholesky"``: the joint evidence's path (module docstring).

    Args:
        system: the joint system (concrete arrays for ``"auto"``).
        method: ``"auto"`` (Cholesky up to ``Nf n = DENSE_SMALL``, else m-mode where it applies, else
            Cholesky), ``"mmode"`` (checked: :func:`gcrsky.solvers.mmode_check` on concrete
            arrays) or ``"cholesky"`` (``"dense"``: its deprecated former name).
        memory_budget: bytes the dense path's ``(Nf n)^2`` factor may take (None: no limit).

    Raises:
        ValueError: an unknown method, ``"auto"`` under a trace, m-mode that does not apply, or a
            dense factor beyond the budget.
    """
    method = _path_name(method)
    if method not in ("auto", *_EVIDENCE):
        raise ValueError(f"method must be 'auto' or one of the joint evidence's paths {', '.join(map(repr, _EVIDENCE))}"
                         f" (gcrsky.solvers.registry.PATHS), got {method!r}")
    traced = is_traced(system)
    if method == "auto" and traced:
        raise ValueError("method='auto' needs concrete arrays: give 'mmode' or 'dense' under a trace")
    nf, n = np.shape(system.prior.mean)
    if method == "auto" and nf * n <= DENSE_SMALL:
        return "cholesky"
    if method in ("auto", "mmode") and not traced:
        check = mmode_check(data_system(system))
        if bool(check):
            return "mmode"
        if method == "mmode":
            raise ValueError(f"the joint m-mode path does not apply: {check.reason}")
    if method == "mmode":
        return method
    need = 8.0 * (nf * n) ** 2
    if memory_budget is not None and need > memory_budget:
        raise ValueError(f"the dense joint evidence needs a ({nf * n}, {nf * n}) factor, {need / 2**30:.2f} GiB, "
                         f"beyond memory_budget = {memory_budget / 2**30:.2f} GiB (m-mode needs uniform full-day "
                         "coverage)")
    return "cholesky"


def spectral_log_evidence(system: JointSystem, model: SpectralModel, theta, *, fixed=None,
                          method: str = "cholesky") -> jax.Array:
    """``log p(d | theta)`` of all channels under the coupled prior (scalar, nats; pure, differentiable).

    ``method``: ``"cholesky"`` or ``"mmode"`` (no checks here: :func:`choose_method` first; ``"dense"``:
    the deprecated name of ``"cholesky"``).
    """
    method = _path_name(method)
    if method not in _EVIDENCE:
        raise ValueError(f"method must be one of {', '.join(map(repr, _EVIDENCE))} here, got {method!r}")
    return _EVIDENCE[method](joint_system(system, model, theta, fixed), check=False)


def spectral_log_density(system: JointSystem, model: SpectralModel, theta0, *, fixed=None,
                         log_prior: Callable | None = WEAK_HYPERPRIOR, method: str = "cholesky"):
    """The collapsed log posterior of the flattened ``theta``: ``(flat0, unravel, logdensity)``.

    ``logdensity(flat) = log p(d | theta) + log_prior(theta)``, ``theta = unravel(flat)``; pure (the
    system may be traced, e.g. one replicate's data inside a ``vmap``), for
    :func:`gcrsky.inference.collapsed.nuts_chain`.  ``method``: ``"cholesky"`` or ``"mmode"``.
    """
    flat0, unravel = ravel_pytree(theta0)
    flat0 = jnp.asarray(flat0, jnp.float64)
    if flat0.ndim != 1 or flat0.size == 0:
        raise ValueError("theta0 must hold at least one float")

    def logdensity(flat):
        theta = unravel(flat)
        lz = spectral_log_evidence(system, model, theta, fixed=fixed, method=method)
        return lz + (log_prior(theta) if log_prior is not None else 0.0)

    return flat0, unravel, logdensity


def _checked(system, model, theta0, fixed, method, memory_budget) -> str:
    _full(theta0, fixed)
    if not is_traced(system):
        check_joint_system(joint_system(system, model, theta0, fixed))
    return choose_method(system, method, memory_budget=memory_budget)


# ---------------------------------------------------------------- maximum evidence


def _bfgs_laplace(negative: Callable, flat0, unravel, log_evidence: Callable, *, rtol, atol, max_steps) -> FitResult:
    """Minimise ``negative(flat)`` by BFGS; Laplace covariance; as :func:`gcrsky.inference.hyper.fit_hyperparameters`."""
    import optimistix as optx

    sol = optx.minimise(lambda x, _: negative(x), optx.BFGS(rtol=rtol, atol=atol), flat0, max_steps=max_steps,
                        throw=False)
    flat = sol.value
    hess = jax.hessian(negative)(flat)
    hess = 0.5 * (hess + hess.T)
    cov = jnp.linalg.inv(hess)
    ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.linalg.eigvalsh(hess) > 0)
    return FitResult(theta=unravel(flat), log_evidence=log_evidence(flat), objective=-negative(flat),
                     covariance=cov, std=unravel(jnp.sqrt(jnp.abs(jnp.diagonal(cov)))), converged=ok,
                     num_steps=sol.stats["num_steps"], result=sol.result)


@partial(jax.jit, static_argnames=("log_prior", "method", "rtol", "atol", "max_steps"))
def _fit_coupled(system, model, theta0, fixed, log_prior, method, rtol, atol, max_steps):
    flat0, unravel, logd = spectral_log_density(system, model, theta0, fixed=fixed, log_prior=log_prior,
                                                method=method)
    return _bfgs_laplace(lambda x: -logd(x), flat0, unravel,
                         lambda x: spectral_log_evidence(system, model, unravel(x), fixed=fixed, method=method),
                         rtol=rtol, atol=atol, max_steps=max_steps)


def fit_spectral_hyperparameters(
    system: JointSystem,
    model: SpectralModel,
    theta0,
    *,
    fixed=None,
    log_prior: Callable | None = WEAK_HYPERPRIOR,
    method: str = "auto",
    memory_budget: float | None = 2**31,
    rtol: float = 1e-8,
    atol: float = 1e-8,
    max_steps: int = 200,
) -> FitResult:
    """Maximise ``log p(d | theta) + log_prior(theta)`` over the kernel's hyperparameters (BFGS, optimistix).

    Args:
        system: a :class:`~gcrsky.solvers.joint.JointSystem` (its prior is replaced: only the
            operator, data and noise are used).
        model: :class:`SpectralModel`.
        theta0: start, a dict of free hyperparameters (keys of :data:`HYPER_NAMES`, unconstrained).
        fixed: dict of the hyperparameters held fixed (the rest of :data:`HYPER_NAMES`).
        log_prior: ``theta -> scalar`` (hashable: a :class:`GaussianHyperprior` or a function);
            default :data:`WEAK_HYPERPRIOR`; None for flat.
        method: the evidence path, ``"auto"`` / ``"mmode"`` / ``"cholesky"`` (:func:`choose_method`).
        memory_budget: bytes for the dense path.
        rtol, atol, max_steps: BFGS's tolerances and step cap.

    Returns:
        :class:`gcrsky.inference.hyper.FitResult`: ``theta`` (the free keys), ``log_evidence`` (the
        joint ``log p(d | theta)`` at the optimum, nats), ``covariance`` (k, k) Laplace covariance in
        ``ravel_pytree(theta0)``'s order (sorted keys), ``std`` the error bars per key.  The fit is
        one jitted program (recompiled only for new shapes or settings).

    Raises:
        ValueError: bad input (names, the joint system's checks, the path).
    """
    method = _checked(system, model, theta0, fixed, method, memory_budget)
    theta0 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), dict(theta0))
    fixed = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), dict(fixed or {}))
    return _fit_coupled(system, model, theta0, fixed, log_prior, method, rtol, atol, int(max_steps))


# ---------------------------------------------------------------- collapsed sampling


def sample_spectral_hyperparameters(
    key: jax.Array,
    system: JointSystem,
    model: SpectralModel,
    theta0,
    num_samples: int,
    *,
    fixed=None,
    log_prior: Callable | None = WEAK_HYPERPRIOR,
    num_warmup: int = 500,
    method: str = "auto",
    memory_budget: float | None = 2**31,
    target_accept: float = 0.8,
    dense_mass: bool = True,
    max_num_doublings: int = 10,
) -> CollapsedSamples:
    """NUTS samples of ``p(theta | d) ∝ p(theta) p(d | theta)`` with the sky of every channel integrated out.

    The chain of :func:`gcrsky.inference.collapsed.sample_hyperparameters` (blackjax window
    adaptation for ``num_warmup`` steps, then ``num_samples`` NUTS steps;
    :func:`~gcrsky.inference.collapsed.nuts_chain`) on :func:`spectral_log_density`: the exact joint
    evidence plus ``log_prior`` (default :data:`WEAK_HYPERPRIOR`, which keeps the posterior proper
    where the evidence goes flat, ``xi -> 0`` or ``inf``).  A good ``theta0`` (the
    :func:`fit_spectral_hyperparameters` optimum) shortens the warm-up.  Each NUTS step costs
    ``num_integration_steps`` evaluations of the evidence and its gradient.

    Args:
        key: PRNG key (split into the warm-up's and the sampling's, as ``nuts_chain``).
        system, model, theta0, fixed, log_prior, method, memory_budget: as
            :func:`fit_spectral_hyperparameters`.
        num_samples, num_warmup, target_accept, dense_mass, max_num_doublings: as
            :func:`gcrsky.inference.collapsed.sample_hyperparameters`.

    Returns:
        :class:`gcrsky.inference.collapsed.CollapsedSamples` (``theta``: dict of the free keys,
        each (num_samples,)).

    Raises:
        ValueError: bad input; ``num_samples < 1`` or ``num_warmup < 0``.
    """
    num_samples, num_warmup = int(num_samples), int(num_warmup)
    if num_samples < 1 or num_warmup < 0:
        raise ValueError("need num_samples >= 1 and num_warmup >= 0")
    blackjax_module()  # fail early, naming the extra
    method = _checked(system, model, theta0, fixed, method, memory_budget)
    theta0 = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), dict(theta0))
    fixed = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), dict(fixed or {}))

    @jax.jit
    def chain(key, system, model, theta0, fixed):
        flat0, _, logd = spectral_log_density(system, model, theta0, fixed=fixed, log_prior=log_prior,
                                              method=method)
        return nuts_chain(key, logd, flat0, num_warmup=num_warmup, num_samples=num_samples,
                          target_accept=target_accept, dense_mass=dense_mass, max_num_doublings=max_num_doublings)

    positions, logd, info = chain(key, system, model, theta0, fixed)
    n_div = int(jnp.sum(info.is_divergent))
    if n_div:
        log.warning("NUTS: %d of %d samples diverged (step size %.3g): the posterior may be under-explored",
                    n_div, num_samples, float(info.step_size))
    log.info("NUTS (joint %s evidence): %d samples, step size %.3g, mean acceptance %.3f, mean %.1f leapfrog steps",
             method, num_samples, float(info.step_size), float(jnp.mean(info.acceptance_rate)),
             float(jnp.mean(info.num_integration_steps)))
    _, unravel = ravel_pytree(theta0)
    return CollapsedSamples(theta=jax.vmap(unravel)(positions), log_density=logd, info=info)


def draw_given_spectral_hyperparameters(
    key: jax.Array,
    system: JointSystem,
    model: SpectralModel,
    theta_samples,
    *,
    fixed=None,
    ndraws: int = 1,
    method: str = "auto",
    memory_budget: float | None = 2**31,
    batch_size: int | None = None,
) -> jax.Array:
    """Exact joint draws of ``a | theta_i, d`` (all channels together) for every hyperparameter sample.

    Sample ``i`` uses ``jax.random.split(key, num_samples)[i]`` and
    :func:`~gcrsky.solvers.joint.draw_joint_dense` / ``draw_joint_mmode`` on the joint system at
    ``theta_i``; samples are mapped with ``jax.lax.map`` (``batch_size`` vectorised together).

    Args:
        theta_samples: dict of the free keys, each with a leading (num_samples,) axis (e.g.
            :attr:`CollapsedSamples.theta`).
        ndraws: draws per sample.
        others: as :func:`fit_spectral_hyperparameters`.

    Returns:
        (num_samples, ndraws, Nf, n) realified coefficients, Kelvin.
    """
    leaves = jax.tree_util.tree_leaves(theta_samples)
    if not leaves:
        raise ValueError("theta_samples has no leaves")
    first = jax.tree_util.tree_map(lambda x: x[0], theta_samples)
    method = _checked(system, model, first, fixed, method, memory_budget)
    keys = jax.random.split(key, int(jnp.shape(leaves[0])[0]))
    fixed = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float64), dict(fixed or {}))
    return _draw_given(keys, system, model, theta_samples, fixed, method, int(ndraws), batch_size)


@partial(jax.jit, static_argnames=("method", "ndraws", "batch_size"))
def _draw_given(keys, system, model, theta_samples, fixed, method, ndraws, batch_size):
    def one(args):
        k, theta = args
        prepare, draw = _DRAWS[method]
        return draw(k, prepare(joint_system(system, model, theta, fixed), check=False), ndraws)

    return jax.lax.map(one, (keys, theta_samples), batch_size=batch_size)


# ---------------------------------------------------------------- the evidence table


class EvidenceTable(NamedTuple):
    """Maximum log evidences of three spectral models of the same data (nats), at their fitted hyperparameters.

    Attributes:
        independent: channels independent, ``A C_l (nu/nu0)^(2 beta)`` each (fitted: log A, beta).
        template: the power-law template, one sky for all channels (fitted: log A, beta).
        coupled: the log-frequency kernel (fitted: log A, beta, log xi).
        fits: ``{"independent": FitResult, "template": FitResult, "coupled": FitResult}``.
    """

    independent: float
    template: float
    coupled: float
    fits: dict

    @property
    def differences(self) -> dict:
        """Log Bayes factors at the fitted hyperparameters, nats."""
        return {"coupled - independent": self.coupled - self.independent,
                "coupled - template": self.coupled - self.template,
                "template - independent": self.template - self.independent}

    def __str__(self) -> str:
        rows = ["model        log evidence (nats)   fitted hyperparameters (+- Laplace sigma)"]
        for name in ("independent", "template", "coupled"):
            f = self.fits[name]
            hyp = ", ".join(f"{k} = {float(v):.4g} +- {float(f.std[k]):.2g}" for k, v in f.theta.items())
            rows.append(f"{name:<12} {getattr(self, name):>20.3f}   {hyp}")
        rows += [f"{k}: {v:+.3f} nats" for k, v in self.differences.items()]
        return "\n".join(rows)


def evidence_table(
    system: JointSystem,
    model: SpectralModel,
    theta0=None,
    *,
    log_prior: Callable | None = WEAK_HYPERPRIOR,
    method: str = "auto",
    memory_budget: float | None = 2**31,
) -> EvidenceTable:
    """Fit and compare the independent-channel, power-law-template and coupled-kernel models (module docstring).

    Each model's hyperparameters maximise its own ``log p(d | theta) + log_prior(theta)`` (``log_prior``
    restricted to the keys the model has); the table holds ``log p(d | theta_hat)``.  The independent
    model's evidence is :func:`gcrsky.inference.evidence.log_evidence_system` of
    :func:`independent_system` summed over channels, the template's of :func:`template_system` (one
    stacked data vector), the coupled model's the joint evidence: three code paths, one normalisation
    (tests check the limits ``xi -> 0`` and ``xi -> inf``).

    Args:
        system, model, log_prior, method, memory_budget: as :func:`fit_spectral_hyperparameters`
            (the same path for all three models: Cholesky or m-mode).
        theta0: start of the coupled fit (default ``log A = 0, beta = -2.5, log xi = log 0.1``); the
            other two start at its ``log_amplitude`` and ``beta``.

    Returns:
        :class:`EvidenceTable` (``print`` it).
    """
    theta0 = dict(theta0 or {"log_amplitude": 0.0, "beta": -2.5, "log_xi": float(np.log(0.1))})
    method = _checked(system, model, theta0, None, method, memory_budget)
    options = options_for(method)
    two = {k: jnp.asarray(theta0[k], jnp.float64) for k in ("log_amplitude", "beta")}
    fits = {
        "independent": _fit_linear(system, model, two, log_prior, options, "independent"),
        "template": _fit_linear(system, model, two, log_prior, options, "template"),
        "coupled": fit_spectral_hyperparameters(system, model, theta0, log_prior=log_prior, method=method,
                                                memory_budget=memory_budget),
    }
    for name, f in fits.items():
        if not bool(f.converged):
            log.warning("evidence table: the %s model's fit did not converge (%s)", name, f.message)
    return EvidenceTable(independent=float(jnp.sum(fits["independent"].log_evidence)),
                         template=float(jnp.sum(fits["template"].log_evidence)),
                         coupled=float(fits["coupled"].log_evidence), fits=fits)


@partial(jax.jit, static_argnames=("log_prior", "options", "which"))
def _fit_linear(system, model, theta0, log_prior, options, which):
    build = independent_system if which == "independent" else template_system
    return fit_hyperparameters(lambda th: build(system, model, th), theta0, log_prior=log_prior, options=options)
