"""``log det`` of the prior-whitened precision by stochastic Lanczos quadrature (matfree), for CG.

On the matrix-free path there is no factor: ``log det(I + H)`` (``I + H = S^1/2 P S^1/2``)
is split as ``log det(M) + log det(M^-1/2 (I + H) M^-1/2)`` with ``M`` the rank-k Nystrom
approximation of ``I + H`` (:func:`gcrsky.solvers.preconditioners.nystrom_preconditioner`), whose
log-determinant is exact; only the last, nearly-identity term is estimated, with
Rademacher probes and a few Lanczos steps each (:class:`~gcrsky.solvers.SLQOptions`).
The estimate differentiates through matfree's Lanczos adjoint with the preconditioner
held fixed, so for a fixed key it is a deterministic, differentiable function of the system.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..model.system import LinearSystem, data_apply
from .options import SLQOptions
from .preconditioners import NystromPreconditioner

__all__ = ["whitened_logdet_slq"]


def _one_channel(system_f: LinearSystem, pc: NystromPreconditioner, f, slq: SLQOptions, key):
    """SLQ of ``log det(M^-1/2 (I + H) M^-1/2)`` for one frequency (leading axis 1): (mean, sem)."""
    from matfree import decomp, funm, stochtrace

    U, lam = pc.U[f], pc.lam[f]
    shrink = 1.0 / jnp.sqrt(1.0 + lam) - 1.0  # M^-1/2 = I + U diag((1+lam)^-1/2 - 1) U^T

    def matvec(v, sys_f, U, shrink):  # everything as parameters: matfree's adjoint sees no closures
        def mhalf(x):
            return x + U @ (shrink * (U.T @ x))

        s = 1.0 / jnp.sqrt(sys_f.prior.inv_var[0])  # S^1/2, differentiable in the prior
        u = mhalf(v)
        hu = u + s * data_apply(sys_f, (s * u)[None])[0]
        return mhalf(hu)

    n = system_f.prior.mean.shape[1]
    integrand = funm.monte_carlo_funm_sym_logdet(decomp.tridiag_sym(min(slq.lanczos, n)))
    sampler = stochtrace.sampler_signs(jnp.zeros(n), num=slq.probes)
    estimate = stochtrace.estimator_monte_carlo_mean_and_sem(integrand, sampler)
    mean, sem = estimate(matvec, key, system_f, U, shrink)
    return mean + jnp.sum(jnp.log1p(lam)), sem


def whitened_logdet_slq(system: LinearSystem, pc: NystromPreconditioner, slq: SLQOptions, key, freq_slice):
    """``log det(I + H)`` per channel (Nf,) and its standard error (Nf,), one key per channel.

    ``freq_slice(system, f)`` gives the one-channel system (traced ``f``).
    """
    pc = jax.lax.stop_gradient(pc)
    nf = system.prior.mean.shape[0]
    keys = jax.random.split(key, nf)
    return jax.vmap(lambda f, k: _one_channel(freq_slice(system, f), pc, f, slq, k))(jnp.arange(nf), keys)
