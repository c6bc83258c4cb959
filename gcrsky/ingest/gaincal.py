"""The posterior-mean gains of sampled gain draws (:func:`gcrsky.io.write_gain_calibration` writes them).

The gain model is physics (:func:`gcrsky.model.gains.unit_gains`), so the average is here, above the
file layer, which only writes the (Nf, Nt, U) array it is given.
"""

from __future__ import annotations

import numpy as np

__all__ = ["posterior_mean_gains"]


def posterior_mean_gains(model, thetas, scales, gbar=None) -> np.ndarray:
    """The posterior mean of the units' gains over draws: (Nf, Nt, U) complex.

    Args:
        model: :func:`gcrsky.model.gain_model`'s layout.
        thetas: (D, P) draws of the coefficients; scales: (D, Kf) draws of the scale.
        gbar: the applied gains the draws were made about ((Nf, Nt, U) or None).
    """
    import jax

    from ..model.gains import unit_gains

    g = jax.vmap(lambda t, s: unit_gains(model, t, s, gbar))(np.asarray(thetas), np.asarray(scales))
    return np.asarray(g).mean(axis=0)
