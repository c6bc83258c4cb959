"""Per-antenna beam perturbations in a small basis on the sky (issue 41, DESIGN section 15).

Antenna ``i``'s voltage pattern is its nominal one times a smooth perturbation,

    ``A_i(p, nu) = A0_i(p, nu) (1 + sum_k c_ik(nu) f_k(p, nu))``,

with ``f_k`` Zernike polynomials of the projected zenith angle, ``(x, y) = za (cos az, sin az)``
(East, North; pyuvdata's azimuth, North of East), on a disc of radius ``r(nu) = radius_fwhm
FWHM(nu)`` of the nominal beam (antenna 0's: one basis for the array), so the modes follow the main lobe as it shrinks with
frequency, tapered smoothly to zero from ``r`` to ``(1 + taper) r`` (the first sidelobe's
region; beyond it the nominal pattern is kept).  Each mode is the Zernike polynomial less its
value at the zenith (``Z_n^0(0) = +-1``; the others vanish there), so that no mode but the
piston changes the beam's zenith response: that is the antenna's amplitude, which the gains
carry, and the piston (``Z_0^0``) is left out by default.  The low orders are what real dishes
do: a pointing offset ``delta`` of a Gaussian main lobe is ``+ (delta . x) / sigma^2`` (the
tilts ``Z_1^{+-1}``), a fractional width change ``eps`` is ``eps |x|^2 / sigma^2`` (defocus,
``2 rho^2`` here), an ellipticity the astigmatisms ``Z_2^{+-2}``.  Measured
(``tests/test_beammodes.py``): 3 % width and 5 mrad pointing errors of a 14 m dish at 100-120
MHz change its response by 10 %; the five modes of ``nmax = 2`` leave ~0.3 % of it.  Each coefficient varies smoothly in frequency, ``c_ik(nu) = sum_q theta_ikq B_q(nu)``
(:func:`gcrsky.model.gains.mode_basis`, the constant first, unit rms).

**The response is exactly bilinear.**  With ``u_i = (1, c_i1, .., c_iM)`` and ``f_0 = 1``, the
unpolarised kernel of row ``b = (i, j)`` is ``A_i A_j = A0_i A0_j sum_kl u_ik u_jl f_k f_l``, so

    ``R_b(c) = sum_{k <= l} w_kl(u_i, u_j) R_b^(kl)``,  ``w_kl = u_ik u_jl + u_il u_jk`` (``k < l``),
    ``w_kk = u_ik u_jk``,

with ``R^(kl)`` the response to the kernel ``A0_i A0_j f_k f_l``: ``(M + 1)(M + 2) / 2`` response
sets, built once by the same quadrature as the response (:func:`mode_responses`), and combined
for any coefficients by :func:`combine_responses` (jittable, differentiable).  Given the other
antennas, a visibility is linear in one antenna's coefficients: its Gibbs conditional is
Gaussian.  With feed products (``pols``) the kernel is the cross power beam of the nominal
E-fields times the same scalar factors (the perturbation scales both feeds' patterns alike;
polarised beam errors are not modelled).
"""

from __future__ import annotations

from math import factorial
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

__all__ = [
    "BeamModes",
    "ZERNIKE_NAMES",
    "beam_modes",
    "combine_responses",
    "disc_radius",
    "mode_maps",
    "mode_pairs",
    "mode_responses",
    "perturbed_power_beam",
    "pair_weights",
    "zernike",
]

#: Names of the low Zernike orders ``(n, m)`` (``m < 0``: the sine partner).
ZERNIKE_NAMES = {(0, 0): "piston", (1, 1): "tilt_east", (1, -1): "tilt_north", (2, 0): "defocus",
                 (2, 2): "astig_0", (2, -2): "astig_45", (3, 1): "coma_east", (3, -1): "coma_north",
                 (3, 3): "trefoil_0", (3, -3): "trefoil_30", (4, 0): "spherical"}


class BeamModes(NamedTuple):
    """The perturbation basis (hashable settings; no arrays).

    Attributes:
        orders: the Zernike orders ``(n, m)`` of the modes, in order (``M`` of them).
        radius_fwhm: the disc's radius in units of the nominal beam's power FWHM at each
            frequency (measured, :func:`gcrsky.instrument.beams.beam_fwhm_rad`).
        taper: the cosine taper's width beyond the disc, in units of its radius.
    """

    orders: tuple
    radius_fwhm: float = 1.5
    taper: float = 0.5

    @property
    def names(self) -> list[str]:
        return [ZERNIKE_NAMES.get(o, f"Z{o[0]}^{o[1]}") for o in self.orders]

    @property
    def n_modes(self) -> int:
        return len(self.orders)


def beam_modes(nmax: int = 2, *, piston: bool = False, radius_fwhm: float = 1.5, taper: float = 0.5) -> BeamModes:
    """Every Zernike order ``(n, m)`` with ``n <= nmax`` (``n - |m|`` even), piston only if asked.

    The default ``nmax = 2`` gives the five modes of a dish's main-lobe errors: two tilts
    (pointing), defocus (width), two astigmatisms (ellipticity).

    Raises:
        ValueError: ``nmax`` outside 0..6, no mode left, or a non-positive radius or negative taper.
    """
    if int(nmax) != nmax or not 0 <= nmax <= 6:
        raise ValueError(f"nmax must be an integer 0..6 (Zernike degree), got {nmax!r}")
    if not (np.isfinite(radius_fwhm) and radius_fwhm > 0):
        raise ValueError(f"radius_fwhm must be positive, got {radius_fwhm!r}")
    if not (np.isfinite(taper) and taper >= 0):
        raise ValueError(f"taper must be >= 0, got {taper!r}")
    orders = tuple((n, m) for n in range(int(nmax) + 1) for m in range(n, -n - 1, -1)
                   if (n - abs(m)) % 2 == 0 and (piston or n > 0))
    if not orders:
        raise ValueError("no beam mode: nmax 0 without the piston leaves none")
    return BeamModes(orders, float(radius_fwhm), float(taper))


def zernike(n: int, m: int, rho: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """The (unnormalised) Zernike polynomial ``R_n^|m|(rho) cos(m phi)`` (``sin(|m| phi)`` for ``m < 0``).

    ``R_n^m(rho) = sum_s (-1)^s (n - s)! / (s! ((n + m)/2 - s)! ((n - m)/2 - s)!) rho^(n - 2s)``;
    ``R_n^m(1) = 1``.  Defined for every ``rho >= 0`` (the taper takes it beyond 1).
    """
    am = abs(int(m))
    if (n - am) % 2 or am > n:
        raise ValueError(f"no Zernike polynomial (n, m) = ({n}, {m}): need |m| <= n and n - |m| even")
    radial = np.zeros_like(rho, dtype=np.float64)
    for s in range((n - am) // 2 + 1):
        c = (-1) ** s * factorial(n - s) / (factorial(s) * factorial((n + am) // 2 - s) * factorial((n - am) // 2 - s))
        radial = radial + c * rho ** (n - 2 * s)
    ang = np.cos(am * phi) if m >= 0 else np.sin(am * phi)
    return radial * ang


def _taper(rho: np.ndarray, width: float) -> np.ndarray:
    if width == 0:
        return (rho <= 1.0).astype(np.float64)
    t = np.clip((rho - 1.0) / width, 0.0, 1.0)
    return np.where(t < 1.0, np.cos(0.5 * np.pi * t) ** 2, 0.0)


def mode_maps(modes: BeamModes, az_uvbeam: np.ndarray, za: np.ndarray, radius_rad: np.ndarray) -> np.ndarray:
    """The modes ``f_k`` on a set of directions, per frequency.

    Args:
        modes: the basis.
        az_uvbeam, za: (Np,) azimuth (North of East) and zenith angle, radians.
        radius_rad: (Nf,) the disc's radius at each frequency, radians of zenith angle.

    Returns:
        (Nf, M, Np) real: ``(Z_k(rho, phi) - Z_k(0)) taper(rho)`` with ``rho = za / radius``, ``phi = az``
        (every mode but the piston vanishes at the zenith: module docstring).
    """
    za = np.asarray(za, np.float64)
    phi = np.asarray(az_uvbeam, np.float64)
    radius = np.atleast_1d(np.asarray(radius_rad, np.float64))
    rho = za[None, :] / radius[:, None]  # (Nf, Np)
    w = _taper(rho, modes.taper)
    zero = np.zeros(1)
    return np.stack([(zernike(n, m, rho, phi[None, :]) - (zernike(n, m, zero, zero)[0] if (n, m) != (0, 0) else 0.0))
                     * w for n, m in modes.orders], axis=1)


def mode_pairs(n_modes: int) -> np.ndarray:
    """(P, 2) the index pairs ``(k, l)``, ``0 <= k <= l <= M`` (0 the unperturbed pattern), of :func:`mode_responses`."""
    return np.array([(k, l) for k in range(n_modes + 1) for l in range(k, n_modes + 1)], np.int64)


def pair_weights(u_i: jnp.ndarray, u_j: jnp.ndarray) -> jnp.ndarray:
    """``w_kl`` of every pair of :func:`mode_pairs` (module docstring), jittable.

    Args:
        u_i, u_j: (..., M + 1) ``(1, c_1, .., c_M)`` of the row's two antennas.

    Returns:
        (..., P) real.
    """
    kl = mode_pairs(u_i.shape[-1] - 1)
    k, l = kl[:, 0], kl[:, 1]
    w = u_i[..., k] * u_j[..., l] + u_i[..., l] * u_j[..., k]
    return jnp.where(k == l, 0.5 * w, w)


def combine_responses(stack: jnp.ndarray, pairs: np.ndarray, coeffs: jnp.ndarray) -> jnp.ndarray:
    """The response of the perturbed beams: ``R_b = sum_{k<=l} w_kl(u_i, u_j) R_b^(kl)``.

    Args:
        stack: (Nf, P, Nbl, n) the response sets of :func:`mode_responses`.
        pairs: (Nbl, 2) antenna indices of each row (as given to :func:`mode_responses`; may be traced).
        coeffs: (Nant, Nf, M) the perturbation coefficients ``c_ik(nu)``.

    Returns:
        (Nf, Nbl, n) complex; ``coeffs = 0`` gives ``stack[:, 0]``, the nominal response.
    """
    pairs = jnp.asarray(pairs)
    u = jnp.concatenate([jnp.ones(coeffs.shape[:2] + (1,), coeffs.dtype), coeffs], axis=-1)  # (Nant, Nf, M+1)
    w = pair_weights(u[pairs[:, 0]], u[pairs[:, 1]])  # (Nbl, Nf, P)
    return jnp.einsum("bfp,fpbn->fbn", w.astype(stack.real.dtype), stack)


def disc_radius(beam, freqs_hz, modes: BeamModes) -> np.ndarray:
    """(Nf,) the disc's radius ``radius_fwhm FWHM(nu)`` of the nominal ``beam``, radians."""
    from .beams import beam_fwhm_rad

    return np.array([modes.radius_fwhm * beam_fwhm_rad(beam, float(f)) for f in np.atleast_1d(freqs_hz)])


def mode_responses(array, pairs, freqs_hz, lmax: int, nside: int, modes: BeamModes, *, lst_ref_rad: float = 0.0,
                   pols=None, beam_floor: float = 1e-16) -> np.ndarray:
    """The response sets ``R^(kl)`` of every mode pair (module docstring), by the rings quadrature
    (:func:`gcrsky.instrument.response.modulated_responses` of the modes' products).

    Args:
        array: the :class:`~gcrsky.instrument.AntennaArray` with the *nominal* beams (one per antenna;
            the disc follows antenna 0's nominal FWHM: one basis for the whole array).
        pairs: (Nbl, 2) antenna index pairs.
        freqs_hz, lmax, nside, lst_ref_rad, pols, beam_floor: as
            :func:`gcrsky.instrument.response_matrix` (its ``"rings"`` method: the same quadrature).
        modes: the basis (:func:`beam_modes`).

    Returns:
        (Nf, P, Nbl, (lmax + 1)^2) complex128, ``P = (M + 1)(M + 2) / 2`` in the order of
        :func:`mode_pairs`; ``[:, 0]`` is ``response_matrix(..., method="rings")``.
    """
    from .response import modulated_responses

    kl = mode_pairs(modes.n_modes)
    radius = disc_radius(array.beams[0], freqs_hz, modes)  # one basis for the array: R^(kl) = R^(lk)

    def products(az, za, freqs):
        fk = mode_maps(modes, az, za, radius)  # (Nf, M, Np)
        f_all = np.concatenate([np.ones((fk.shape[0], 1, fk.shape[-1])), fk], axis=1)  # (Nf, M+1, Np)
        return f_all[:, kl[:, 0]] * f_all[:, kl[:, 1]]  # (Nf, P, Np)

    return modulated_responses(array, pairs, freqs_hz, lmax, nside, products, lst_ref_rad=lst_ref_rad, pols=pols,
                               beam_floor=beam_floor)


def perturbed_power_beam(nominal, coeffs, freqs_hz, modes: BeamModes, *, n_az: int = 73, n_za: int = 181,
                         telescope_name: str = "gcrsky", antenna: str = ""):
    """One antenna's perturbed beam as a pyuvdata ``UVBeam`` power beam (what files of it hold).

    The model's voltage beam is ``A_i = A_0 (1 + sum_k c_ik(nu) f_k)`` (module docstring; ``A_0`` the
    nominal beam's unpolarised amplitude ``sqrt(P_xx)``, :func:`gcrsky.instrument.beams.beam_amplitude`),
    so its power beam is ``P_i = A_i^2``, written as the ``"xx"`` power beam that gcrsky and pyuvdata read
    back (``beam_amplitude`` of it is ``|A_i|``), peak-normalised as the nominal one (not renormalised:
    a perturbation that changes the zenith gain would show; the modes vanish at the zenith).

    Args:
        nominal: the nominal beam (pyuvdata AnalyticBeam, UVBeam or BeamInterface).
        coeffs: (Nf, M) the antenna's ``c_ik(nu)``.
        freqs_hz: (Nf,) frequencies, Hz.
        modes: the basis (:func:`beam_modes`).
        n_az, n_za: the az/za grid (0..360 deg and 0..90 deg, inclusive of both ends in za).
        telescope_name, antenna: recorded in the beam's header and history.

    Returns:
        a ``UVBeam`` (``beam_type="power"``, ``pixel_coordinate_system="az_za"``, ``polarization_array``
        ``["xx"]``, ``Nfreqs = Nf``).
    """
    from pyuvdata import UVBeam

    from .beams import beam_amplitude

    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    c = np.asarray(coeffs, np.float64).reshape(freqs.size, modes.n_modes)
    az = np.linspace(0.0, 2 * np.pi, n_az, endpoint=False)
    za = np.linspace(0.0, np.pi / 2, n_za)
    AZ, ZA = np.meshgrid(az, za)  # (n_za, n_az): UVBeam's (Naxes2, Naxes1)
    a0 = beam_amplitude(nominal, AZ.ravel(), ZA.ravel(), freqs)  # (Nf, Np)
    f = mode_maps(modes, AZ.ravel(), ZA.ravel(), disc_radius(nominal, freqs, modes))  # (Nf, M, Np)
    amp = a0 * (1.0 + np.einsum("fm,fmp->fp", c, f))
    power = (amp**2).reshape(freqs.size, n_za, n_az)
    return UVBeam.new(telescope_name=telescope_name, data_normalization="peak", freq_array=freqs,
                      beam_type="power", polarization_array=["xx"], x_orientation="east",
                      pixel_coordinate_system="az_za", axis1_array=az, axis2_array=za,
                      data_array=power[None, None], feed_name="gcrsky-perturbed", model_name=f"antenna {antenna}",
                      history=f"gcrsky: posterior-mean perturbed beam of antenna {antenna} (modes "
                              f"{', '.join(modes.names)}; A = A0 (1 + sum c_k f_k))")
