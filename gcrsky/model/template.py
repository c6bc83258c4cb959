"""Hyperparameter families of the linear system: a spectral template, noise and prior scales.

The paper's section 2.1 models the sky as ``I(nu, n) = sum_k a_k f_k(n) (nu / nu0)^beta``:
one set of coefficients shared by every channel, scaled by a power law.
:func:`spectral_template_system` writes that model as an ordinary
:class:`~gcrsky.model.LinearSystem` with a single "frequency" block whose baseline axis
runs over (channel, baseline): every sampler, the evidence and the gradients accept
it, and ``beta`` may be traced (fitted, differentiated).  :func:`scale_noise` and
:func:`with_prior` are the other hyperparameters of the fits.
"""

from __future__ import annotations

import jax.numpy as jnp

from .prior import Prior
from .system import LinearSystem

__all__ = ["scale_noise", "spectral_template_system", "with_prior"]


def spectral_template_system(system: LinearSystem, freqs_hz, beta, *, nu0_hz=None, prior: Prior | None = None):
    """One coefficient vector for all channels, ``I(nu) = (nu/nu0)^beta sum_k a_k f_k``.

    Args:
        system: the per-channel system (Nf channels, response (Nf, Nbl, n)).
        freqs_hz: (Nf,) channel frequencies, Hz.
        beta: the spectral index (scalar; may be traced).
        nu0_hz: reference frequency (default the first channel): the coefficients are
            the sky at ``nu0``.
        prior: the prior on the shared coefficients, arrays (1, n) or (n,); default
            the prior of the first channel.

    Returns:
        a :class:`LinearSystem` with Nf = 1: response ``(1, Nf Nbl, n)`` (channel f's
        rows scaled by ``(nu_f/nu0)^beta``), data and inverse noise ``(1, Nt, Nf Nbl)``,
        the same angles and frame.  Its posterior is that of the shared coefficients
        given every channel's data.
    """
    freqs = jnp.asarray(freqs_hz)
    nf, nbl, n = system.op.response.shape
    if freqs.shape != (nf,):
        raise ValueError(f"freqs_hz has shape {freqs.shape}, the system has {nf} channels")
    nu0 = freqs[0] if nu0_hz is None else nu0_hz
    scale = (freqs / nu0) ** beta  # (Nf,)
    resp = (system.op.response * scale[:, None, None]).reshape(1, nf * nbl, n)
    nt = system.data.shape[1]

    def stack(x):  # (Nf, Nt, Nbl) -> (1, Nt, Nf Nbl), channel-major along the new baseline axis
        return jnp.moveaxis(x, 0, 1).reshape(1, nt, nf * nbl)

    if prior is None:
        prior = Prior(system.prior.mean[:1], system.prior.inv_var[:1])
    prior = Prior(jnp.reshape(prior.mean, (1, -1)), jnp.reshape(prior.inv_var, (1, -1)))
    if prior.mean.shape[1] != system.prior.mean.shape[1]:
        raise ValueError(f"the prior has {prior.mean.shape[1]} coefficients, the system {system.prior.mean.shape[1]}")
    return LinearSystem(system.op._replace(response=resp), stack(system.data), stack(system.inv_noise), prior)


def scale_noise(system: LinearSystem, scale) -> LinearSystem:
    """The system with the noise *variance* multiplied by ``scale`` (scalar or broadcastable to (Nf, 1, 1))."""
    return system._replace(inv_noise=system.inv_noise / jnp.asarray(scale))


def with_prior(system: LinearSystem, prior: Prior) -> LinearSystem:
    """The system with another prior (e.g. :func:`gcrsky.model.prior_from_cl` of traced ``C_l``)."""
    mean = jnp.broadcast_to(prior.mean, system.prior.mean.shape)
    inv_var = jnp.broadcast_to(prior.inv_var, system.prior.inv_var.shape)
    return system._replace(prior=Prior(mean, inv_var))
