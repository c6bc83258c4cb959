"""Direction-independent antenna gains as smooth perturbations: the model of issue 23.

Row ``b = (i, j)`` of the data (``antpairs``; the file's ``(ant_1, ant_2)``) sees

    ``V_b = g_i conj(g_j) V_b^sky``,   ``g_i(nu, t) = gbar_i(nu, t) A (1 + x_i(nu, t))``

(pyuvdata's convention: its ``uvcalibrate`` divides row ``(1, 2)`` by ``g_1 conj(g_2)``).
``gbar`` is the applied calibration (``--cal``, or 1), ``A > 0`` one overall amplitude
and ``x_i`` a small complex perturbation per gain unit (an antenna, or an antenna's feed)
on a separable smooth basis ``x_i(nu, t) = sum_kl c_ikl B_k(nu) T_l(t)``: a few modes in
delay (frequency axis) times a few in fringe rate (time axis), each axis either low-order
DPSS (``scipy.signal.windows.dpss``) or Fourier, orthogonalised with the constant first and
scaled to unit rms (so a coefficient is the rms fractional gain of its mode).

**Linearised model.**  With ``q = A^2`` (per channel, on the frequency modes) the model is

    ``V_b = q gbar_i conj(gbar_j) (1 + x_i + conj(x_j)) V_b^sky``  (:func:`gain_factor`),

linear in ``x`` (hence a Gaussian conditional for the coefficients given the sky), linear in
``q`` and linear in the sky.  The exact model (``exact=True``) keeps ``x_i conj(x_j)``: the
neglected term is second order, ``|x|^2`` of the visibility (measured by
``benchmarks/gains_mixing.py``: 0.5 % rms at 5 % amplitude and 5 deg phase errors).

**Degeneracies** (the coefficients are real-stacked in ``theta``, :func:`n_gain_params`):

* the overall phase of each feed group: in the linearised model any common imaginary part
  ``x_i -> x_i + i phi(nu, t)`` cancels in ``x_i + conj(x_j)``, for every mode.  It is
  projected out exactly: the imaginary parts of each mode are parametrised in the
  orthonormal complement of the groups' indicator vectors (``phase_proj``);
* the overall amplitude per channel: the common real part of the frequency-only modes
  ``(k, 0)`` is removed the same way (``amp_proj``) and carried by ``q(nu) = sum_k s_k B_k(nu)``
  (:func:`scale_profile`) instead, where the likelihood depends on ``q(nu) a(nu)`` only:
  ``(q, a) -> (q', a q / q')`` is an exact symmetry that only the priors break (the gauge
  move of :mod:`gcrsky.inference.gains`);
* the two phase gradients (tip-tilt, :func:`phase_gradient_directions`) and the common real
  parts of the time-varying modes stay in ``theta``, sampled, pinned by the priors and the data.

Everything here is pure NumPy set-up (:func:`gain_model`) and jittable JAX maps.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = [
    "BASES",
    "GainModel",
    "gain_factor",
    "gain_model",
    "mode_basis",
    "n_gain_params",
    "pair_gains",
    "perturbation_coefficients",
    "perturbations",
    "phase_gradient_directions",
    "scale_profile",
    "unit_gains",
]

#: The smooth bases of :func:`mode_basis`.
BASES = ("dpss", "fourier", "legendre")


def mode_basis(n: int, k: int, kind: str = "dpss") -> np.ndarray:
    """``k`` smooth modes on ``n`` samples: (n, k) real, column 0 the constant 1, orthogonal, unit rms.

    ``"dpss"``: the constant followed by the leading ``k - 1`` discrete prolate spheroidal
    sequences of half-bandwidth ``NW = max(1, k / 2)`` (at most 0.49 n) (the ``k`` best concentrated in
    ``|delay| <= NW / n``); ``"fourier"``: 1, cos, sin, cos 2, ... of the whole span; ``"legendre"``:
    the polynomials of degree 0 .. k - 1 across the span (a drift: neither of the others holds a
    straight line, e.g. 49 % (dpss) and 61 % (fourier) of a linear ramp's rms is left outside
    their 3 modes on 12 samples).  All are orthogonalised (QR) in that order and scaled to rms 1.

    Raises:
        ValueError: ``k`` outside 1..n, or an unknown ``kind``.
    """
    if kind not in BASES:
        raise ValueError(f"basis must be one of {BASES}, got {kind!r}")
    if not 1 <= k <= n:
        raise ValueError(f"{k} gain modes on an axis of {n} samples: give 1 to {n} modes")
    cols = [np.ones(n)]
    if k > 1 and kind == "dpss":
        from scipy.signal.windows import dpss

        cols += list(np.atleast_2d(dpss(n, min(max(1.0, k / 2.0), 0.49 * n), k - 1)))  # scipy: NW < n / 2
    elif k > 1 and kind == "legendre":
        u = np.linspace(-1.0, 1.0, n)
        cols += [np.polynomial.legendre.Legendre.basis(p)(u) for p in range(1, k)]
    elif k > 1:
        x = np.arange(n) / n
        for p in range(1, k):
            cols.append(np.cos(2 * np.pi * ((p + 1) // 2) * x) if p % 2 else np.sin(2 * np.pi * (p // 2) * x))
    Q, R = np.linalg.qr(np.stack(cols, axis=1))
    Q = Q * np.sign(np.diag(R))[None, :]
    return Q[:, :k] * np.sqrt(n)


class GainModel(NamedTuple):
    """The layout of the gain perturbations (built by :func:`gain_model`; a PyTree of arrays).

    Attributes:
        basis_f: (Nf, Kf) frequency modes (delay), unit rms, column 0 constant.
        basis_t: (Nt, Kt) time modes (fringe rate), unit rms, column 0 constant.
        unit_pairs: (Nbl, 2) int, the gain units ``(i, j)`` of each data row.
        amp_proj: (U, U - 1) orthonormal complement of the all-ones vector (constant mode, real parts).
        phase_proj: (U, U - G) orthonormal complement of the G feed groups' indicators (imaginary parts).
        param_mode: (P,) int, the flattened mode ``k Kt + l`` of each element of ``theta``.
        units: (U, 2) int, each unit's ``(antenna index, feed)`` (feed 0: one gain per antenna,
            1: x, 2: y), sorted.
    """

    basis_f: np.ndarray
    basis_t: np.ndarray
    unit_pairs: np.ndarray
    amp_proj: np.ndarray
    phase_proj: np.ndarray
    param_mode: np.ndarray
    units: np.ndarray


def _complement(indicators: np.ndarray) -> np.ndarray:
    """Orthonormal basis (U, U - G) of the complement of the columns of ``indicators`` (U, G)."""
    u, _, _ = np.linalg.svd(indicators, full_matrices=True)
    return u[:, indicators.shape[1]:]


def _units(antpairs: np.ndarray, pols) -> tuple[np.ndarray, np.ndarray]:
    """Gain units per row (Nbl, 2) and the units (U, 2) ``(antenna, feed)``: antennas, or feeds by ``pols``."""
    pairs = np.asarray(antpairs, dtype=int)
    if pols is None:
        feeds = np.zeros(pairs.shape[0], int)
    else:
        if len(pols) != pairs.shape[0]:
            raise ValueError(f"pols has {len(pols)} entries for {pairs.shape[0]} rows")
        bad = sorted({p for p in pols if p not in ("xx", "yy", "pI")})
        if bad:
            raise ValueError(f"gains model the feed products 'xx', 'yy' (own feeds) and 'pI' (one gain per antenna), "
                             f"not {bad}")
        feeds = np.array([{"xx": 1, "yy": 2, "pI": 0}[p] for p in pols])
    keys = np.stack([pairs, np.stack([feeds, feeds], axis=1)], axis=-1).reshape(-1, 2)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    return inv.reshape(pairs.shape), uniq


def gain_model(antpairs, n_freqs: int, n_times: int, modes=(2, 2), *, basis: str = "dpss",
               pols=None) -> GainModel:
    """The gain perturbations' layout for data rows ``antpairs`` (host-side set-up).

    Args:
        antpairs: (Nbl, 2) antenna indices of the data rows (``Problem.antpairs``).
        n_freqs, n_times: Nf and Nt of the data.
        modes: ``(Kf, Kt)``: modes in frequency (delay) and time (fringe rate); ``(1, 1)``
            is one constant complex gain per unit.
        basis: ``"dpss"``, ``"fourier"`` or ``"legendre"`` (:func:`mode_basis`), both axes.
        pols: None (one gain per antenna) or ``Problem.pols``: rows ``"xx"`` / ``"yy"`` get
            each antenna's x / y feed gain, ``"pI"`` rows one gain per antenna.

    Raises:
        ValueError: a unit seen by no cross-correlation, too many modes, or unknown pols.
    """
    kf, kt = (int(m) for m in modes)
    bf, bt = mode_basis(int(n_freqs), kf, basis), mode_basis(int(n_times), kt, basis)
    unit_pairs, units = _units(antpairs, pols)
    groups = units[:, 1]
    if np.any(unit_pairs[:, 0] == unit_pairs[:, 1]):
        raise ValueError("gain_model takes cross-correlations only: drop the autocorrelation rows")
    nu = groups.size
    ng = np.unique(groups).size
    if nu - ng < 1:
        raise ValueError("gains need at least two units in a feed group")
    amp = _complement(np.ones((nu, 1)))
    phase = _complement((groups[:, None] == np.unique(groups)[None, :]).astype(float))
    modes = np.arange(kf * kt).reshape(kf, kt)
    param_mode = np.concatenate([np.tile(modes[:, 0], nu - 1), np.tile(modes[:, 1:].ravel(), nu),
                                 np.tile(modes.ravel(), nu - ng)])
    return GainModel(bf, bt, unit_pairs, amp, phase, param_mode, units)


def n_gain_params(model: GainModel) -> int:
    """P, the length of ``theta``: ``(U - 1) Kf + U Kf (Kt - 1) + (U - G) Kf Kt``."""
    return int(model.param_mode.size)


def perturbation_coefficients(model: GainModel, theta) -> jnp.ndarray:
    """Complex coefficients ``c`` (U, Kf, Kt) of ``theta`` (P,) (real-stacked, gauge-fixed).

    Layout of ``theta``: ``[psi (U-1, Kf), u (U, Kf, Kt-1), phi (U-G, Kf Kt)]``: the real parts of
    the frequency-only modes ``(k, 0)`` are ``amp_proj psi`` (their common part is the scale's),
    those of the other modes ``u``, and the imaginary parts ``phase_proj phi``.
    """
    nu, na = model.amp_proj.shape
    ng = model.phase_proj.shape[1]
    kf, kt = model.basis_f.shape[1], model.basis_t.shape[1]
    theta = jnp.asarray(theta)
    n_psi, n_u = na * kf, nu * kf * (kt - 1)
    psi, u, phi = theta[:n_psi], theta[n_psi:n_psi + n_u], theta[n_psi + n_u:]
    real = jnp.concatenate([(model.amp_proj @ psi.reshape(na, kf))[:, :, None], u.reshape(nu, kf, kt - 1)], axis=2)
    imag = (model.phase_proj @ phi.reshape(ng, kf * kt)).reshape(nu, kf, kt)
    return real + 1j * imag


def perturbations(model: GainModel, theta) -> jnp.ndarray:
    """``x`` (Nf, Nt, U) complex: the perturbation of every unit's gain at every sample."""
    c = perturbation_coefficients(model, theta)
    return jnp.einsum("fk,tl,ukl->ftu", model.basis_f, model.basis_t, c)


def scale_profile(model: GainModel, scale) -> jnp.ndarray:
    """``q(nu)`` (Nf,): the overall amplitude squared per channel, ``basis_f s`` for coefficients
    ``s`` (Kf,) (``s = (1, 0, ...)``: q = 1), or a scalar q broadcast."""
    s = jnp.asarray(scale)
    nf = model.basis_f.shape[0]
    return model.basis_f @ s if s.ndim == 1 else jnp.broadcast_to(s, (nf,))


def pair_gains(model: GainModel, gbar=None) -> jnp.ndarray:
    """``gbar_i conj(gbar_j)`` (Nf, Nt, Nbl) of the rows; ones for ``gbar=None``.

    Args:
        gbar: (Nf, Nt, U) complex applied gains of the units (or broadcastable), or None.
    """
    nf, nt = model.basis_f.shape[0], model.basis_t.shape[0]
    if gbar is None:
        return jnp.ones((nf, nt, model.unit_pairs.shape[0]), complex)
    g = jnp.broadcast_to(jnp.asarray(gbar, complex), (nf, nt, model.amp_proj.shape[0]))
    return g[..., model.unit_pairs[:, 0]] * jnp.conj(g[..., model.unit_pairs[:, 1]])


def gain_factor(model: GainModel, theta, scale=1.0, gbar=None, *, exact: bool = False) -> jnp.ndarray:
    """The factor ``D`` (Nf, Nt, Nbl) complex with model visibilities ``D V^sky``.

    Linearised (default): ``q gbar_i conj(gbar_j) (1 + x_i + conj(x_j))``; ``exact=True``:
    ``q gbar_i conj(gbar_j) (1 + x_i) conj(1 + x_j)``.

    Args:
        model: :func:`gain_model`'s layout.
        theta: (P,) real-stacked perturbation coefficients.
        scale: ``q = A^2``, the overall amplitude squared: a scalar, or its coefficients
            ``s`` (Kf,) on the frequency modes (:func:`scale_profile`).
        gbar: (Nf, Nt, U) applied gains, or None (1).
    """
    x = perturbations(model, theta)
    xi, xj = x[..., model.unit_pairs[:, 0]], jnp.conj(x[..., model.unit_pairs[:, 1]])
    lin = (1.0 + xi) * (1.0 + xj) if exact else 1.0 + xi + xj
    return scale_profile(model, scale)[:, None, None] * pair_gains(model, gbar) * lin


def unit_gains(model: GainModel, theta, scale=1.0, gbar=None) -> jnp.ndarray:
    """The units' complex gains ``g_u = gbar_u sqrt(q(nu)) (1 + x_u)`` (Nf, Nt, U): the exact model's, with
    ``g_i conj(g_j)`` the factor of row ``(i, j)`` (up to the unobservable overall phase, fixed by the gauge).

    Args:
        theta: (P,) coefficients; scale: ``s`` (Kf,) or a scalar ``q``; gbar: (Nf, Nt, U) or None.
    """
    nf, nt, nu = model.basis_f.shape[0], model.basis_t.shape[0], model.amp_proj.shape[0]
    g = jnp.ones((nf, nt, nu), complex) if gbar is None else jnp.broadcast_to(jnp.asarray(gbar, complex), (nf, nt, nu))
    return g * jnp.sqrt(scale_profile(model, scale))[:, None, None] * (1.0 + perturbations(model, theta))


def phase_gradient_directions(model: GainModel, unit_positions_m) -> np.ndarray:
    """Unit vectors (2, P) in ``theta`` of the two phase gradients (east, north) of the constant mode.

    A phase gradient ``x_i = i k . r_i`` moves the sky's apparent position (tip-tilt);
    redundant calibration leaves it undetermined.  Its component outside the projected-out
    overall phase, normalised.

    Args:
        unit_positions_m: (U, 2 or 3) ENU positions of the gain units, metres.
    """
    r = np.asarray(unit_positions_m, float)[:, :2]
    nu, na = model.amp_proj.shape
    k = model.basis_f.shape[1] * model.basis_t.shape[1]
    kf = model.basis_f.shape[1]
    start = na * kf + nu * (k - kf)
    out = np.zeros((2, n_gain_params(model)))
    for e in range(2):
        phi = np.zeros((model.phase_proj.shape[1], k))
        phi[:, 0] = model.phase_proj.T @ r[:, e]
        out[e, start:] = phi.ravel()
        out[e] /= np.linalg.norm(out[e])
    return out
