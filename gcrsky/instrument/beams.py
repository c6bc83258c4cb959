"""Beams: pyuvdata beam objects evaluated on the sky.

:class:`JaxGaussianBeam` and :class:`JaxAiryBeam` are their JAX twins, whose width
is a traced value, so the response (:func:`gcrsky.instrument.analytic_response`)
differentiates with respect to it.

Beams are pyuvdata beam objects (``GaussianBeam``, ``AiryBeam``, any
``AnalyticBeam``, ``UVBeam``).  For Stokes-I (unpolarised) work we follow
matvis: the feed-``x`` power beam ``P_i`` is evaluated and ``A_i = sqrt(P_i)``,
so identical antennas give ``A_i^* A_j = P``.  Azimuth passed to pyuvdata is
in the UVBeam convention (North of East: Az(E)=0, Az(N)=pi/2), zenith angle in
radians.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.units import SPEED_OF_LIGHT

__all__ = [
    "AIRY_X_MAX",
    "JaxAiryBeam",
    "JaxGaussianBeam",
    "beam_amplitude",
    "beam_fwhm_rad",
    "fwhm_airy_rad",
    "gaussian_beam",
    "unique_beams",
]


def gaussian_beam(diameter_m: float):
    """pyuvdata ``GaussianBeam(diameter=D)``: FWHM ~ 1.03 lambda/D (Airy-matched)."""
    from pyuvdata.analytic_beam import GaussianBeam

    if not diameter_m > 0:
        raise ValueError(f"dish diameter must be positive, got {diameter_m}")
    return GaussianBeam(diameter=float(diameter_m))


def fwhm_airy_rad(diameter_m: float, freq_hz: float) -> float:
    """Small-angle FWHM of an Airy-disk power pattern, ``1.029 lambda/D``, radians.

    Not the width of ``GaussianBeam(diameter=D)`` (pyuvdata's, ~lambda/D: 12.28 deg at
    100 MHz for 14 m); use :func:`beam_fwhm_rad` for the beam actually simulated.
    """
    lam = SPEED_OF_LIGHT / freq_hz
    return 1.02899 * lam / diameter_m


def beam_fwhm_rad(beam, freq_hz: float, *, n_grid: int = 20001) -> float:
    """Full width at half maximum of a beam's power pattern, measured, in radians.

    The power (feed x, as used for Stokes I) is evaluated along zenith angle at
    azimuths 0 and pi/2 (UVBeam convention); the half-power angle is found by
    linear interpolation on a ``n_grid`` grid over [0, pi/2] and the two cuts are
    averaged (FWHM = 2 x mean half-power zenith angle).  Raises ``ValueError`` if the
    power never falls to half of its zenith value above the horizon.
    """
    za = np.linspace(0.0, np.pi / 2, n_grid)
    half = []
    for az in (0.0, np.pi / 2):
        p = beam_amplitude(beam, np.full_like(za, az), za, np.array([float(freq_hz)]))[0] ** 2
        below = np.flatnonzero(p <= 0.5 * p[0])
        if below.size == 0:
            raise ValueError(f"beam power does not fall to half above the horizon at {freq_hz:g} Hz")
        k = below[0]
        half.append(np.interp(0.5 * p[0], [p[k], p[k - 1]], [za[k], za[k - 1]]))
    return float(2 * np.mean(half))


def beam_amplitude(beam, az_uvbeam_rad: np.ndarray, za_rad: np.ndarray, freqs_hz: np.ndarray) -> np.ndarray:
    """Unpolarised voltage beam ``A = sqrt(P_xx)`` on a set of directions.

    Args:
        beam: pyuvdata AnalyticBeam / UVBeam / BeamInterface.
        az_uvbeam_rad: (Npix,) azimuth, UVBeam convention (North of East), radians.
        za_rad: (Npix,) zenith angle, radians (<= pi/2).
        freqs_hz: (Nfreq,) frequencies in Hz.

    Returns:
        (Nfreq, Npix) real, non-negative amplitudes.
    """
    from pyuvdata import BeamInterface

    bi = beam if isinstance(beam, BeamInterface) else BeamInterface(beam)
    if bi.beam_type == "efield":
        bi = bi.as_power_beam(include_cross_pols=False)
    if bi.Npols > 1:
        bi = bi.with_feeds(["x"])
    kw = {}
    if bi._isuvbeam:
        kw = dict(interpolation_function="az_za_map_coordinates", check_azza_domain=False)
    power = bi.compute_response(
        az_array=np.asarray(az_uvbeam_rad, np.float64),
        za_array=np.asarray(za_rad, np.float64),
        freq_array=np.asarray(freqs_hz, np.float64),
        **kw,
    )
    power = np.real(np.asarray(power)[0, 0])  # (Nfreq, Npix)
    if np.any(power < -1e-12 * np.max(np.abs(power))):
        raise ValueError("beam power is negative somewhere; cannot take an unpolarised amplitude")
    return np.sqrt(np.clip(power, 0.0, None))


def unique_beams(beams) -> tuple[list, np.ndarray]:
    """Distinct beam objects (by identity) and, per antenna, the index of its beam."""
    uniq: list = []
    idx = np.empty(len(beams), np.int64)
    for i, b in enumerate(beams):
        for j, u in enumerate(uniq):
            if u is b:
                idx[i] = j
                break
        else:
            uniq.append(b)
            idx[i] = len(uniq) - 1
    return uniq, idx


# ---------------------------------------------------------------- JAX-native analytic beams


#: Largest Airy argument ``x = (D/2) k sin(za)`` where ``jax.scipy.special.bessel_jn``
#: agrees with SciPy's J1 to 1e-15 (measured; 6e-10 at 30, 6e-5 at 40).
AIRY_X_MAX = 25.0


class JaxGaussianBeam(eqx.Module):
    """A Gaussian dish beam whose width is a JAX value (traced, differentiable).

    The same beam as pyuvdata's ``GaussianBeam``: power ``exp(-za^2 / sigma(nu)^2)``
    with the E-field width ``sigma(nu) = arcsin(2.2150894 lambda / (pi D)) 2 / 2.355``
    for a dish diameter ``D`` (pyuvdata's ``diameter_to_sigma``, Airy-matched FWHM), or
    ``sigma_rad (nu / nu_ref)^spectral_index`` when the width is given directly.
    Unpolarised amplitude ``A = sqrt(P) = exp(-za^2 / (2 sigma^2))``.

    Attributes:
        diameter_m: dish diameter, m (or None).
        sigma_rad: E-field width at ``reference_frequency_hz``, radians (or None).
        spectral_index: width power law (static).
        reference_frequency_hz: reference of the power law (static; needed with
            ``sigma_rad`` and a non-zero index).
    """

    diameter_m: object = None
    sigma_rad: object = None
    spectral_index: float = eqx.field(static=True, default=0.0)
    reference_frequency_hz: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if (self.diameter_m is None) == (self.sigma_rad is None):
            raise ValueError("give exactly one of diameter_m and sigma_rad")
        if self.sigma_rad is not None and self.spectral_index != 0 and self.reference_frequency_hz is None:
            raise ValueError("a width power law (spectral_index != 0) needs reference_frequency_hz")

    def sigmas(self, freqs_hz) -> jax.Array:
        """E-field widths (Nf,), radians."""
        freqs = jnp.asarray(freqs_hz)
        if self.diameter_m is not None:
            lam = SPEED_OF_LIGHT / freqs
            return jnp.arcsin(2.2150894 * lam / (jnp.pi * self.diameter_m)) * 2 / 2.355
        ref = self.reference_frequency_hz or 1.0
        return self.sigma_rad * (freqs / ref) ** self.spectral_index

    def amplitude(self, za_rad, freqs_hz) -> jax.Array:
        """``A = sqrt(P)`` (Nf, Npix) at zenith angles ``za_rad`` (Npix,), radians."""
        s = self.sigmas(freqs_hz)[:, None]
        return jnp.exp(-jnp.asarray(za_rad)[None, :] ** 2 / (2 * s**2))

    def to_pyuvdata(self):
        """The equivalent pyuvdata ``GaussianBeam`` (concrete values only)."""
        from pyuvdata.analytic_beam import GaussianBeam

        if self.diameter_m is not None:
            return GaussianBeam(diameter=float(self.diameter_m))
        return GaussianBeam(sigma=float(self.sigma_rad), spectral_index=float(self.spectral_index),
                            reference_frequency=self.reference_frequency_hz)


class JaxAiryBeam(eqx.Module):
    """An Airy dish beam whose diameter is a JAX value: ``A = |2 J1(x) / x|``, ``x = (D/2) k sin(za)``.

    pyuvdata's ``AiryBeam`` (E-field ``2 J1(x)/x``; the unpolarised amplitude is its
    modulus, ``sqrt(P)``).  J1 is ``jax.scipy.special.bessel_jn``, accurate to 1e-15
    for ``x <= AIRY_X_MAX`` (25): :meth:`amplitude` refuses larger arguments (a
    wider dish or a higher frequency than that covers).

    Attributes:
        diameter_m: dish diameter, m.
    """

    diameter_m: object

    def amplitude(self, za_rad, freqs_hz) -> jax.Array:
        """``|2 J1(x)/x|`` (Nf, Npix); ``1 - x^2/8`` below x = 1e-4 (J1's recurrence is 0/0 at 0)."""
        k = 2 * jnp.pi * jnp.asarray(freqs_hz)[:, None] / SPEED_OF_LIGHT
        x = (self.diameter_m / 2) * jnp.sin(jnp.asarray(za_rad))[None, :] * k
        if not isinstance(x, jax.core.Tracer) and float(jnp.max(x)) > AIRY_X_MAX:
            raise ValueError(f"Airy argument reaches {float(jnp.max(x)):.1f} > {AIRY_X_MAX}: outside the range "
                             "where JAX's Bessel J1 is accurate (use pyuvdata's AiryBeam in response_matrix)")
        small = x < 1e-4
        xs = jnp.where(small, 1.0, x)
        j1 = jax.scipy.special.bessel_jn(xs, v=1)[1]
        return jnp.abs(jnp.where(small, 1.0 - x**2 / 8, 2 * j1 / xs))

    def to_pyuvdata(self):
        """The equivalent pyuvdata ``AiryBeam`` (concrete values only)."""
        from pyuvdata.analytic_beam import AiryBeam

        return AiryBeam(diameter=float(self.diameter_m))
