"""Beams: pyuvdata beam objects evaluated on the sky.

:class:`JaxGaussianBeam` and :class:`JaxAiryBeam` are their JAX twins, whose width
is a traced value, so the response (:func:`gcrsky.instrument.analytic_response`)
differentiates with respect to it.

Beams are pyuvdata beam objects (``GaussianBeam``, ``AiryBeam``, ``ShortDipoleBeam``,
any ``AnalyticBeam``, ``UVBeam``, ``BeamInterface``), or files that ``UVBeam.from_file``
reads (:func:`load_beam`; per antenna: :func:`antenna_beams`).  The legacy unpolarised
response follows matvis' unpolarised mode: the feed-``x`` power beam ``P_i`` is evaluated
and ``A_i = sqrt(P_i)`` (:func:`beam_amplitude`), so identical antennas give
``A_i^* A_j = P_xx``, i.e. ``2 V_xx`` of the sum convention.  The polarisation-correct kernels
of each visibility product (``"xx"``, ``"yy"``, ``"pI"``, ...; different beams on the two
antennas) are in :mod:`gcrsky.instrument.polarization`.  Azimuth passed to pyuvdata is
in the UVBeam convention (North of East: Az(E)=0, Az(N)=pi/2), zenith angle in
radians.  A UVBeam is never extrapolated in frequency: a frequency outside its channel
range is a ``ValueError``.
"""

from __future__ import annotations

import logging
import os
from typing import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.units import SPEED_OF_LIGHT
from .beamfiles import NEGATIVE_POWER_TOL  # beamfiles imports nothing of gcrsky's

log = logging.getLogger(__name__)

__all__ = [
    "AIRY_X_MAX",
    "FREQ_TOL_HZ",
    "JaxAiryBeam",
    "JaxGaussianBeam",
    "antenna_beams",
    "beam_amplitude",
    "beam_fwhm_rad",
    "NEGATIVE_POWER_TOL",
    "check_beam_frequencies",
    "clip_power",
    "fwhm_airy_rad",
    "gaussian_beam",
    "load_beam",
    "unique_beams",
]


#: A requested frequency within this distance (Hz) of a UVBeam channel uses that channel as
#: it is (pyuvdata's ``freq_interp_tol``).
FREQ_TOL_HZ = 1.0


def resolve_beam(beam):
    """``(object, kind)``: the pyuvdata beam behind ``beam`` and how it is evaluated.

    kinds: ``"uv_efield"``, ``"uv_power"`` (UVBeam), ``"an_efield"`` (AnalyticBeam with an
    E-field), ``"an_power"`` (AnalyticBeam defining only its power).
    """
    from pyuvdata import BeamInterface, UVBeam
    from pyuvdata.analytic_beam import AnalyticBeam

    btype = None
    if isinstance(beam, BeamInterface):
        btype, beam = beam.beam_type, beam.beam
    if isinstance(beam, UVBeam):
        kind = {"efield": "uv_efield", "power": "uv_power"}.get(beam.beam_type)
        if kind is None:
            raise NotImplementedError(f"UVBeam of beam_type {beam.beam_type!r}: gcrsky needs an E-field or a power beam")
        return beam, kind
    if isinstance(beam, AnalyticBeam):
        if btype == "power" or not hasattr(beam, "_efield_eval"):
            return beam, "an_power"
        return beam, "an_efield"
    raise TypeError(f"a beam must be a pyuvdata UVBeam, AnalyticBeam or BeamInterface, got {type(beam).__name__}")


def beam_name(obj) -> str:
    """A beam's name for messages: its class and its ``model_name`` or ``telescope_name``."""
    name = type(obj).__name__
    label = getattr(obj, "model_name", None) or getattr(obj, "telescope_name", None)
    return f"{name}({label})" if isinstance(label, str) and label else name


def beam_channels(obj) -> np.ndarray:
    """A UVBeam's channel frequencies (Nfreqs,), Hz, float64."""
    return np.asarray(obj.freq_array, np.float64).ravel()


def check_beam_frequencies(beam, freqs_hz) -> None:
    """Raise ``ValueError`` unless every frequency lies within the beam's channel range.

    Analytic beams accept any frequency.  A UVBeam accepts ``[min, max]`` of its channels
    (``FREQ_TOL_HZ`` slack); a single-channel beam only its channel.

    Args:
        beam: pyuvdata beam object.
        freqs_hz: (Nf,) frequencies, Hz.
    """
    from pyuvdata import UVBeam

    obj = resolve_beam(beam)[0]
    if not isinstance(obj, UVBeam):
        return
    ch = beam_channels(obj)
    f = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    lo, hi = ch.min() - FREQ_TOL_HZ, ch.max() + FREQ_TOL_HZ
    bad = f[(f < lo) | (f > hi)]
    if bad.size:
        raise ValueError(
            f"frequencies {bad.tolist()} Hz lie outside the frequency range [{ch.min():.6g}, {ch.max():.6g}] Hz of "
            f"the beam {beam_name(obj)} ({ch.size} channels); gcrsky does not extrapolate beams in frequency"
        )


def freq_interp_kind(nchan: int, kind: str | None) -> str:
    """pyuvdata's frequency interpolation for a beam of ``nchan`` channels: ``kind`` if given, else cubic
    from 4 channels and linear below."""
    if kind is not None:
        return kind
    return "cubic" if nchan >= 4 else "linear"


def spatial_interp_kwargs(obj) -> dict:
    """Spatial interpolation of a UVBeam: matvis' (``az_za_map_coordinates``) on az/za grids."""
    if obj.pixel_coordinate_system == "az_za":
        return dict(interpolation_function="az_za_map_coordinates", check_azza_domain=False)
    return {}


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
    power at the zenith is not positive or never falls to half of it above the horizon.
    """
    za = np.linspace(0.0, np.pi / 2, n_grid)
    half = []
    for az in (0.0, np.pi / 2):
        p = beam_amplitude(beam, np.full_like(za, az), za, np.array([float(freq_hz)]))[0] ** 2
        if not (np.isfinite(p[0]) and p[0] > 0):
            raise ValueError(f"beam power at the zenith is {p[0]:g} at {freq_hz:g} Hz: no FWHM about the zenith")
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

    Raises:
        ValueError: a frequency outside a UVBeam's channel range.  Interpolation undershoot
            below 0 is clipped (:func:`clip_power`).
    """
    from pyuvdata import BeamInterface

    check_beam_frequencies(beam, freqs_hz)
    bi = beam if isinstance(beam, BeamInterface) else BeamInterface(beam)
    if bi.beam_type == "efield":
        bi = bi.as_power_beam(include_cross_pols=False)  # power on the native grid, then interpolate
    power = None
    if bi.Npols > 1:
        try:
            bi = bi.with_feeds(["x"])
        except NotImplementedError:  # pyuvdata cannot drop a ShortDipoleBeam's y feed: P_xx from its E-field
            e = bi.beam.efield_eval(az_array=np.asarray(az_uvbeam_rad, np.float64),
                                    za_array=np.asarray(za_rad, np.float64),
                                    freq_array=np.asarray(freqs_hz, np.float64))
            x = int(np.flatnonzero(np.asarray(bi.beam.feed_array) == "x")[0])
            power = np.sum(np.abs(e[:, x]) ** 2, axis=0)
    if power is None:
        kw = {}
        if bi._isuvbeam:
            kw = dict(spatial_interp_kwargs(bi.beam), freq_interp_kind=freq_interp_kind(bi.beam.Nfreqs, None))
        power = bi.compute_response(
            az_array=np.asarray(az_uvbeam_rad, np.float64),
            za_array=np.asarray(za_rad, np.float64),
            freq_array=np.asarray(freqs_hz, np.float64),
            **kw,
        )
        power = np.real(np.asarray(power)[0, 0])  # (Nfreq, Npix)
    return np.sqrt(clip_power(power, beam_name(bi.beam)))


#: Beams (by name) whose interpolated power was clipped in this process: the first time is a warning.
_CLIPPED: set = set()


def clip_power(power: np.ndarray, name: str = "beam") -> np.ndarray:
    """An interpolated power pattern with its undershoot below 0 clipped to 0 (the count logged).

    Cubic interpolation (pyuvdata's spatial spline; its frequency interpolation with four or
    more channels) of a power beam that is clipped to 0 or drops steeply undershoots below
    0 next to the drop; power is never negative, so those values are 0, and the result
    equals the interpolant wherever that is >= 0 (why clipping rather than another
    interpolant: :mod:`gcrsky.instrument.beamprep`, with the undershoot measured on matvis'
    HERA dipole beam).  The first clipping of each beam (by ``name``) in a process is logged as
    a warning with the fraction clipped and its depth relative to the peak; later ones at
    debug level, unless deeper than ``NEGATIVE_POWER_TOL`` x the peak (the beam's sampling
    is coarse for its structure).
    """
    power = np.asarray(power, np.float64)
    neg = power < 0
    if not np.any(neg):
        return power
    peak = np.max(np.abs(power))
    deep = np.min(power) < -NEGATIVE_POWER_TOL * peak
    first = name not in _CLIPPED
    _CLIPPED.add(name)
    log.log(logging.WARNING if deep or first else logging.DEBUG, "%s: %d interpolated power values below 0 (%.3g %% "
            "of them, min %.3g of the peak) clipped to 0", name, int(neg.sum()), 100 * neg.mean(), np.min(power) / peak)
    return np.where(neg, 0.0, power)


def load_beam(beam, *, peak_normalize: bool = False, **read_kwargs):
    """A pyuvdata beam object from a beam object or a beam file.

    Args:
        beam: a pyuvdata ``UVBeam``, ``AnalyticBeam`` (e.g. ``GaussianBeam``, ``AiryBeam``,
            ``ShortDipoleBeam``) or ``BeamInterface`` (returned as they are), or the path of
            any file ``UVBeam.from_file`` reads (beamfits, CST text files or their yaml
            settings file, MWA beam files), or a one-plane primary-beam image in a SIN RA/Dec
            projection about the zenith (converted to az/za:
            :func:`gcrsky.instrument.beamfiles.image_beam`).
        peak_normalize: normalise a UVBeam to a peak of 1 per frequency (pyuvdata
            ``peak_normalize``, on a copy; gcrsky's visibilities scale with the beam's
            normalisation, which the file keeps as it is by default).
        **read_kwargs: passed to ``UVBeam.from_file`` (CST files need e.g. ``beam_type``,
            ``frequency``, ``feed_pol``, ``telescope_name``, ``feed_name``, ...).

    Returns:
        The beam object (an E-field or power UVBeam, or the analytic beam).

    Raises:
        TypeError: neither a beam object nor a path; read options with a beam object.
        ValueError: a UVBeam that is neither an E-field nor a power beam; a file that is not a
            beam file or whose values cannot be a beam
            (:func:`gcrsky.instrument.beamfiles.check_beam_values`), naming the file.
    """
    from pyuvdata import BeamInterface, UVBeam
    from pyuvdata.analytic_beam import AnalyticBeam

    if isinstance(beam, (str, os.PathLike)):
        from .beamfiles import read_beam  # UVBeam files, and SIN beam images converted to az/za

        obj = read_beam(beam, **read_kwargs)[0]
    elif isinstance(beam, (UVBeam, AnalyticBeam, BeamInterface)):
        if read_kwargs:
            raise TypeError(f"read options {sorted(read_kwargs)} apply only to beam files, not to a beam object")
        obj = beam
    else:
        raise TypeError(f"a beam must be a pyuvdata beam object or a beam file path, got {type(beam).__name__}")
    if isinstance(obj, UVBeam):
        if obj.beam_type not in ("efield", "power"):
            raise ValueError(f"UVBeam of beam_type {obj.beam_type!r}: gcrsky needs an E-field or a power beam")
        if peak_normalize:
            obj = obj.copy() if obj is beam else obj
            obj.peak_normalize()
    elif peak_normalize:
        raise ValueError("peak_normalize applies to UVBeams only")
    return obj


def antenna_beams(beam, antenna_numbers, *, antenna_names=None, **load_kwargs) -> tuple:
    """One beam object per antenna, from one beam, a list, or a mapping by antenna number or name.

    Identical antennas share one object (gcrsky groups beams by identity:
    :func:`unique_beams`), so each distinct file path is read once.

    Args:
        beam: a beam object or file path for every antenna; a sequence of ``Nant`` of them, in
            the order of ``antenna_numbers``; or a mapping from antenna number (int) or name
            (str, with ``antenna_names``) to a beam object or path, covering every antenna.
        antenna_numbers: (Nant,) the array's antenna numbers, in its antenna order.
        antenna_names: (Nant,) the antennas' names, same order (for a mapping by name).
        **load_kwargs: passed to :func:`load_beam` for every file.

    Returns:
        ``Nant``-tuple of pyuvdata beam objects (what :func:`~gcrsky.instrument.make_array` takes).

    Raises:
        ValueError: a sequence of the wrong length; a mapping missing antennas or naming
            unknown ones.
    """
    numbers = [int(n) for n in np.atleast_1d(np.asarray(antenna_numbers))]
    names = None if antenna_names is None else [str(n) for n in antenna_names]
    if names is not None and len(names) != len(numbers):
        raise ValueError(f"{len(names)} antenna names for {len(numbers)} antenna numbers")
    loaded: dict = {}

    def get(b):
        key = ("path", os.path.abspath(os.fspath(b))) if isinstance(b, (str, os.PathLike)) else ("obj", id(b))
        if key not in loaded:
            loaded[key] = load_beam(b, **load_kwargs)
        return loaded[key]

    if isinstance(beam, Mapping):
        out = []
        known = set(numbers) | set(names or ())
        unknown = [k for k in beam if (int(k) if isinstance(k, (int, np.integer)) else str(k)) not in known]
        if unknown:
            raise ValueError(f"beam mapping names antennas {unknown} that are not in the array")
        missing = []
        for n, num in enumerate(numbers):
            if num in beam:
                out.append(get(beam[num]))
            elif names is not None and names[n] in beam:
                out.append(get(beam[names[n]]))
            else:
                missing.append(num if names is None else f"{num} ({names[n]})")
        if missing:
            raise ValueError(f"the beam mapping has no beam for antennas {missing}")
        return tuple(out)
    if isinstance(beam, Sequence) and not isinstance(beam, (str, bytes)):
        if len(beam) != len(numbers):
            raise ValueError(f"got {len(beam)} beams for {len(numbers)} antennas")
        return tuple(get(b) for b in beam)
    one = get(beam)
    return (one,) * len(numbers)


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
