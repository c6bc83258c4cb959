"""Polarisation-correct beam kernels for an unpolarised sky: what each visibility product sees.

Conventions (pinned against matvis' polarised simulator in ``tests/test_polarized_response.py``):

* Antenna ``i`` has, per feed ``p`` (``"x"`` or ``"y"``, pyuvdata's feed names; which is East
  is the beam's ``feed_angle`` / ``x_orientation``), an E-field pattern ``E_i,p^a(s)`` on the
  sky's two orthonormal polarisation basis vectors ``a`` (pyuvdata's ``az_za`` basis:
  azimuth, zenith angle).  Azimuth is UVBeam's (North of East), zenith angle in radians.
* The visibility of the pair ``(i, j)`` is ``<v_i,p^* v_j,q>`` (pyuvdata's and matvis' order,
  baseline ``b_ij = x_j - x_i``, fringe ``exp(+2 pi i b_ij . s nu / c)``).  An unpolarised sky
  of Stokes ``I`` puts ``I/2`` on each basis vector, so a single feed product is
  ``V_ij,pq = 1/2 int K_ij,pq I exp(...) dOmega`` (the "sum" convention of pyuvsim, matvis and
  hera_sim) with the *cross power beam*

      ``K_ij,pq(s) = sum_a conj(E_i,p^a(s)) E_j,q^a(s)``.

  For one beam (``i`` and ``j`` the same object) and ``p = q`` it is the real power beam
  ``P_pp = |E_p|^2`` (pyuvdata ``efield_to_power``); for ``p != q`` it is pyuvdata's
  cross power beam of polarisation ``qp`` (pyuvdata's ``pq`` is ``E_p conj(E_q)``, the
  conjugate); for different beams it is complex in general and is *not* ``sqrt(P_i P_j)``.
* gcrsky's visibilities are I-equivalent (pyuvdata's ``pol_convention="avg"``): the product
  named ``pol`` has the kernel ``K`` below and ``V = int K I exp(...) dOmega`` (K sr for I in
  K).  In matvis' sum-convention output:

  ========  ===========================  ==================================
  ``pol``   kernel ``K_ij``              equals (matvis, ``polarized=True``)
  ========  ===========================  ==================================
  ``"xx"``  ``K_ij,xx``                  ``2 V_xx``
  ``"yy"``  ``K_ij,yy``                  ``2 V_yy``
  ``"xy"``  ``K_ij,xy``                  ``2 V_xy`` (x on ``i``, y on ``j``)
  ``"yx"``  ``K_ij,yx``                  ``2 V_yx``
  ``"pI"``  ``(K_ij,xx + K_ij,yy) / 2``  ``V_xx + V_yy`` (pseudo-Stokes I)
  ========  ===========================  ==================================

  For identical antennas ``"xx"`` is today's unpolarised response (``P_xx``; gcrsky's
  ``V = 2 V_xx`` of matvis' unpolarised run).  For a dipole the two feeds' patterns are
  rotated by 90 degrees, so ``"pI"`` is *not* ``P_xx``: modelling it with ``P_xx`` alone is
  wrong by ~10-30 % (HERA's CST beam; the matvis test shows it).

Which E-field (how each beam kind is evaluated):

* pyuvdata analytic beams with an E-field (``ShortDipoleBeam``, ``AiryBeam``): the kernel is
  formed from ``efield_eval`` at the requested frequencies.  (pyuvdata's own
  ``ShortDipoleBeam.power_eval`` ignores ``x_orientation="north"``; the E-field does not.)
* power-only analytic beams (``GaussianBeam``, ``UniformBeam``, any
  ``UnpolarizedAnalyticBeam`` defining ``_power_eval``): ``P`` for every feed, and pyuvdata's
  E-field ``sqrt(P/2)`` on both basis vectors for cross kernels (so two such beams give
  ``sqrt(P_i P_j)`` exactly: their E-fields are proportional).
* an unpolarised pyuvdata beam (any ``UnpolarizedAnalyticBeam``: ``GaussianBeam``,
  ``AiryBeam``, ``UniformBeam``) on one antenna and a polarised E-field (a UVBeam, a
  ``ShortDipoleBeam``) on the other: the kernel is formed as above, as matvis and pyuvsim do,
  and a warning is logged.  pyuvdata's unpolarised E-field is a convention, not a field:
  constant components on the (azimuth, zenith angle) unit vectors, which turn with azimuth,
  so it points in opposite directions on either side of zenith.  A physical E-field's
  components change sign across zenith; the cross kernel therefore flips sign across zenith
  (``K(az + 180 deg) = -K(az)`` as ``za -> 0``, with ``|K|`` near its peak there): a
  discontinuity where both beams peak.  Every pixel sum of such a visibility converges
  slowly with the grid (gcrsky's response rotated by ``0.7`` rad against the response built
  at the rotated angle, HERA's E-field beam with a 14 m ``GaussianBeam``, lmax 20: 0.21,
  5e-2, 8e-3 of the rms at nside 32, 64, 128, where the same pair with a polarised Gaussian
  agrees to 2e-4 at nside 64), and two simulators agree only when they sum the very same
  pixels (matvis at real observing times disagrees with gcrsky by ~10 % at nside 64).  Give
  both antennas polarised E-field beams for a physical cross kernel.
* one E-field UVBeam on both antennas: converted to power on its *native* grid (pyuvdata
  ``efield_to_power``, cross polarisations only when needed), then interpolated in
  frequency and direction like any power beam (``az_za_map_coordinates`` for az/za grids).
  Power first: an E-field's phase winds with frequency (CST reference plane), and
  interpolating the complex E-field between channels decoheres it (the power falls, to
  ~0.5 for a quarter-turn per channel); the power does not wind.  In direction too the
  power is interpolated (gcrsky's unpolarised path always did), where matvis' and
  pyuvsim's polarised modes interpolate the E-field: the two differ by the grid's
  interpolation error (9e-5 of the peak for matvis' 2-degree HERA beam).  A cubic
  interpolant of the power may undershoot slightly below zero near nulls; a kernel needs
  no square root, so that is harmless here.
* a power UVBeam on both antennas: interpolated as it is (its polarisation ``pp``; ``qp``
  for ``K_pq``, ``p != q``).
* two different beams that both have an E-field: each E-field is evaluated at the
  directions *on its native channels* (UVBeams; analytic partners at the same
  frequencies), the cross kernel is formed there, and only the kernel is interpolated in
  frequency (a UVBeam partner's channels must then be shared by both beams).
* a power-only UVBeam on one antenna of a pair with a different beam on the other: the
  E-fields are unknown.  gcrsky uses ``sqrt(P_i,pp P_j,pp)`` for ``p = q`` (and ``"pI"``) and
  logs a warning: it is exact only when the two E-fields are proportional (same
  polarisation pattern and phase).  Cross-feed kernels (``"xy"``, ``"yx"``) of such pairs
  are refused.
* frequencies must lie within every UVBeam's channel range (within 1 Hz; a single-channel
  beam only at its channel): no silent extrapolation.  Between channels the interpolation
  is cubic (scipy ``interp1d``, as pyuvdata) with four or more channels, linear otherwise.

Everything here runs once per response build, in NumPy (a set-up step).
"""

from __future__ import annotations

import logging
from typing import NamedTuple, Sequence

import numpy as np

from .beams import (
    FREQ_TOL_HZ,
    beam_amplitude,
    beam_channels,
    beam_name,
    check_beam_frequencies,
    clip_power,
    freq_interp_kind,
    resolve_beam,
    spatial_interp_kwargs,
    unique_beams,
)

__all__ = [
    "PRODUCTS",
    "BaselineKernels",
    "baseline_kernels",
    "cross_power_kernel",
    "normalise_pols",
]

logger = logging.getLogger(__name__)

#: Visibility products gcrsky models (see the module docstring for their kernels).
PRODUCTS = ("xx", "yy", "xy", "yx", "pI")


class BaselineKernels(NamedTuple):
    """Beam kernels of a set of visibility rows, one per distinct (beam pair, product).

    Attributes:
        kernels: (Nf, Nk, Npix) float64 when every kernel is real (identical antennas,
            ``p = q``), complex128 otherwise; the kernel ``K`` of the module docstring.
        index: (Nbl,) int64, the kernel of each row: row ``b`` has ``kernels[:, index[b]]``.
        keys: (Nk,) tuples ``(beam index i, beam index j, product)`` (beam indices of
            :func:`gcrsky.instrument.unique_beams`; product ``None`` for the legacy ``A_i A_j``).
    """

    kernels: np.ndarray
    index: np.ndarray
    keys: tuple


def _feed_index(obj, feed: str) -> int:
    feeds = [str(f) for f in np.asarray(obj.feed_array).ravel()]
    if feed not in feeds:
        raise ValueError(f"{beam_name(obj)} has feeds {feeds}, not {feed!r}")
    return feeds.index(feed)


def _pol_index(obj, pol: str) -> int:
    from pyuvdata.utils.pol import polnum2str

    pols = [polnum2str(int(p)) for p in np.asarray(obj.polarization_array).ravel()]
    if pol not in pols:
        raise ValueError(f"power beam {beam_name(obj)} has polarisations {pols}, not {pol!r}")
    return pols.index(pol)


def _on_channels(freqs: np.ndarray, ch: np.ndarray) -> bool:
    return bool(np.all(np.min(np.abs(freqs[:, None] - ch[None, :]), axis=1) < FREQ_TOL_HZ))


# --------------------------------------------------------------------- kernels of one beam


class _Evaluator:
    """Evaluates and caches per-beam quantities on one set of directions and frequencies."""

    def __init__(self, az, za, freqs, freq_interp_kind):
        self.az = np.ascontiguousarray(az, np.float64)
        self.za = np.ascontiguousarray(za, np.float64)
        if self.az.ndim != 1 or self.az.shape != self.za.shape:
            raise ValueError(f"az and za must be 1-d of one length, got {self.az.shape} and {self.za.shape}")
        self.freqs = np.atleast_1d(np.asarray(freqs, np.float64))
        self.kind = freq_interp_kind
        self._power: dict = {}
        self._efield: dict = {}

    # one beam: power (cross) beam -------------------------------------------------
    def same(self, beam, p: str, q: str) -> np.ndarray:
        """``K_pq`` of one beam on both antennas: (Nf, Npix), real for ``p == q``."""
        obj, kind = resolve_beam(beam)
        if kind in ("uv_efield", "uv_power"):
            check_beam_frequencies(obj, self.freqs)
            cross = p != q
            if kind == "uv_efield":
                key = (id(obj), cross)
                if key not in self._power:
                    pw = obj.efield_to_power(calc_cross_pols=cross, inplace=False)
                    self._power[key] = (pw, self._uv_response(pw))
                pw, resp = self._power[key]
            else:
                key = (id(obj), "power")
                if key not in self._power:
                    self._power[key] = (obj, self._uv_response(obj))
                pw, resp = self._power[key]
            k = resp[0, _pol_index(pw, q + p)]  # pyuvdata's "qp" = E_q conj(E_p) = our K_pq
            if p == q:  # interpolated power (spatial spline, cubic in frequency) undershoots next to a drop
                return clip_power(np.real(k), beam_name(obj))
            return np.asarray(k, np.complex128)
        if kind == "an_power" and p == q:
            pw = obj.power_eval(az_array=self.az, za_array=self.za, freq_array=self.freqs)
            return np.real(pw[0, _pol_index(obj, p + p)]).astype(np.float64)
        e = self.efield(obj, kind, self.freqs)
        k = np.sum(np.conj(e[:, _feed_index(obj, p)]) * e[:, _feed_index(obj, q)], axis=0)
        return np.real(k) if p == q else k

    def _uv_response(self, pw) -> np.ndarray:
        """A power UVBeam at the directions and frequencies: (1, Npols, Nf, Npix)."""
        from pyuvdata import BeamInterface

        ch = beam_channels(pw)
        return np.asarray(
            BeamInterface(pw).compute_response(
                az_array=self.az,
                za_array=self.za,
                freq_array=np.clip(self.freqs, ch.min(), ch.max()),  # within FREQ_TOL_HZ of the range: its edge
                freq_interp_kind=freq_interp_kind(pw.Nfreqs, self.kind),
                **spatial_interp_kwargs(pw),
            )
        )

    # E-fields ----------------------------------------------------------------------
    def efield(self, obj, kind: str, freqs: np.ndarray) -> np.ndarray:
        """(2, Nfeeds, Nf, Npix) complex E-field components (az, za basis) at ``freqs``."""
        key = (id(obj), freqs.tobytes())
        if key in self._efield:
            return self._efield[key]
        if kind == "uv_efield":
            from pyuvdata import BeamInterface

            _check_orthonormal_basis(obj)
            e = BeamInterface(obj).compute_response(
                az_array=self.az,
                za_array=self.za,
                freq_array=freqs,
                freq_interp_kind=freq_interp_kind(obj.Nfreqs, self.kind),
                **spatial_interp_kwargs(obj),
            )
        elif kind in ("an_efield", "an_power"):
            e = obj.efield_eval(az_array=self.az, za_array=self.za, freq_array=freqs)
        else:
            raise ValueError(f"{beam_name(obj)} is a power beam: it has no E-field")
        e = np.asarray(e, np.complex128)
        if e.shape[0] != 2:
            raise NotImplementedError(f"{beam_name(obj)}: E-fields with {e.shape[0]} vector components are not supported")
        self._efield[key] = e
        return e

    # two different beams ------------------------------------------------------------
    def mixed(self, beam_i, beam_j, p: str, q: str) -> np.ndarray:
        """``K_ij,pq`` of two different beams: (Nf, Npix) complex (or real, ``sqrt`` route)."""
        (oi, ki), (oj, kj) = resolve_beam(beam_i), resolve_beam(beam_j)
        for o in (oi, oj):
            check_beam_frequencies(o, self.freqs)
        if "uv_power" in (ki, kj):
            if p != q:
                raise ValueError(
                    f"cannot form the cross-feed kernel {p + q!r} of two different beams when one is a power-only "
                    f"UVBeam ({beam_name(oi)}, {beam_name(oj)}): give E-field beams"
                )
            pi, pj = self.same(beam_i, p, p), self.same(beam_j, p, p)
            for name, pw in ((beam_name(oi), pi), (beam_name(oj), pj)):
                if np.min(pw) < -1e-3 * np.max(np.abs(pw)):
                    raise ValueError(f"beam power of {name} is substantially negative; cannot take sqrt(P_i P_j)")
            return np.sqrt(np.clip(pi, 0.0, None) * np.clip(pj, 0.0, None))
        uv = [o for o, k in ((oi, ki), (oj, kj)) if k == "uv_efield"]
        f_eval, interp = self.freqs, False
        if uv and not all(_on_channels(self.freqs, beam_channels(o)) for o in uv):
            ch = beam_channels(uv[0])
            if len(uv) == 2 and (ch.shape != beam_channels(uv[1]).shape or np.abs(ch - beam_channels(uv[1])).max() > FREQ_TOL_HZ):
                raise ValueError(
                    f"two different E-field UVBeams ({beam_name(oi)}, {beam_name(oj)}) on different channels cannot be "
                    "combined between channels: put them on one frequency grid, or ask for channel frequencies"
                )
            kind = freq_interp_kind(ch.size, self.kind)
            if kind == "linear":  # only the channels bracketing the requested band
                lo = max(0, int(np.searchsorted(ch, self.freqs.min(), side="right")) - 1)
                hi = min(ch.size, int(np.searchsorted(ch, self.freqs.max(), side="left")) + 1)
                ch = ch[lo:hi]
            f_eval, interp = ch, True
        ei, ej = self.efield(oi, ki, f_eval), self.efield(oj, kj, f_eval)
        k = np.sum(np.conj(ei[:, _feed_index(oi, p)]) * ej[:, _feed_index(oj, q)], axis=0)  # (Nf_eval, Npix)
        if interp:
            from scipy.interpolate import interp1d

            kind = freq_interp_kind(f_eval.size, self.kind)
            f = np.clip(self.freqs, f_eval.min(), f_eval.max())
            k = interp1d(f_eval, k.real, kind=kind, axis=0)(f) + 1j * interp1d(f_eval, k.imag, kind=kind, axis=0)(f)
        return np.asarray(k, np.complex128)


def _check_orthonormal_basis(obj) -> None:
    bv = getattr(obj, "basis_vector_array", None)
    if bv is None:
        return
    eye = np.eye(2).reshape((2, 2) + (1,) * (bv.ndim - 2))
    if bv.shape[:2] != (2, 2) or not np.allclose(bv, eye, atol=1e-10):
        raise NotImplementedError(
            f"{beam_name(obj)}: E-field basis vectors other than the (azimuth, zenith angle) unit vectors are not supported "
            "for cross kernels of different beams"
        )


def _unpolarized(obj, kind: str) -> bool:
    """Whether ``obj`` carries pyuvdata's unpolarised stand-in E-field (``sqrt(P/2)`` on both basis vectors)."""
    from pyuvdata.analytic_beam import UnpolarizedAnalyticBeam

    return kind == "an_power" or isinstance(obj, UnpolarizedAnalyticBeam)


def _pair_kernel(ev: _Evaluator, beam_i, beam_j, pol: str, warned: set) -> np.ndarray:
    """The kernel of product ``pol`` for beams ``beam_i`` on ``i`` and ``beam_j`` on ``j``."""
    if pol == "pI":
        return 0.5 * (_pair_kernel(ev, beam_i, beam_j, "xx", warned) + _pair_kernel(ev, beam_i, beam_j, "yy", warned))
    p, q = pol[0], pol[1]
    (oi, ki), (oj, kj) = resolve_beam(beam_i), resolve_beam(beam_j)
    if oi is oj:
        return ev.same(beam_i, p, q)
    k = ev.mixed(beam_i, beam_j, p, q)
    if (id(oi), id(oj)) in warned:
        return k
    if "uv_power" in (ki, kj):
        warned.add((id(oi), id(oj)))
        logger.warning(
            "antennas with different beams %s and %s, one a power-only UVBeam: using sqrt(P_i P_j) as their "
            "kernel, exact only if the two E-fields are proportional (same polarisation pattern and phase); "
            "give E-field beams for the exact cross kernel",
            beam_name(oi),
            beam_name(oj),
        )
    elif _unpolarized(oi, ki) != _unpolarized(oj, kj):
        warned.add((id(oi), id(oj)))
        unpol, pol_obj = (oi, oj) if _unpolarized(oi, ki) else (oj, oi)
        logger.warning(
            "antennas with different beams %s and %s: %s is an unpolarised pyuvdata beam, whose E-field "
            "(sqrt(P/2) on both the azimuth and zenith-angle unit vectors) is a convention, not a physical field; "
            "crossed with the polarised E-field of %s the kernel depends on that convention and changes sign across "
            "zenith, where both beams peak, so pixel sums converge slowly with nside (~5e-2 of the rms at nside 64) "
            "and other simulators agree only on the same pixels; give both antennas polarised E-field beams",
            beam_name(oi),
            beam_name(oj),
            beam_name(unpol),
            beam_name(pol_obj),
        )
    return k


# --------------------------------------------------------------------------- public API


def normalise_pols(pols, nrows: int) -> tuple | None:
    """``None``, or a tuple of ``nrows`` product names from :data:`PRODUCTS`.

    Args:
        pols: ``None`` (the legacy unpolarised ``A_i A_j``), one product name for every row,
            or a sequence of ``nrows`` names.
        nrows: number of visibility rows (pairs).
    """
    if pols is None:
        return None
    if isinstance(pols, str):
        pols = (pols,) * nrows
    pols = tuple(str(p) for p in pols)
    if len(pols) != nrows:
        raise ValueError(f"pols must name one product per row of pairs: got {len(pols)} for {nrows} rows")
    bad = sorted(set(pols) - set(PRODUCTS))
    if bad:
        raise ValueError(f"unknown visibility products {bad}; gcrsky models {list(PRODUCTS)}")
    return pols


def cross_power_kernel(
    beam_i,
    beam_j,
    pol: str,
    az_uvbeam_rad,
    za_rad,
    freqs_hz,
    *,
    freq_interp_kind: str | None = None,
) -> np.ndarray:
    """The kernel of product ``pol`` on a pair with beam ``beam_i`` on ``i`` and ``beam_j`` on ``j``.

    ``V_ij,pol = int K I exp(+2 pi i b_ij . s nu / c) dOmega`` for an unpolarised sky ``I``
    (I-equivalent, pyuvdata's "avg" convention; see the module docstring):
    ``K = sum_a conj(E_i,p^a) E_j,q^a`` for ``pol = "pq"``, ``(K_xx + K_yy)/2`` for ``"pI"``.

    Args:
        beam_i, beam_j: pyuvdata beams (UVBeam, AnalyticBeam, BeamInterface); pass the same
            object twice for identical antennas (compared by identity).
        pol: one of :data:`PRODUCTS`.
        az_uvbeam_rad: (Npix,) azimuth, UVBeam convention (North of East), radians.
        za_rad: (Npix,) zenith angle, radians.
        freqs_hz: (Nf,) frequencies, Hz (within every UVBeam's channel range).
        freq_interp_kind: scipy ``interp1d`` kind between UVBeam channels; default cubic with
            four or more channels, linear otherwise.

    Returns:
        (Nf, Npix) complex128 kernel (dimensionless, in the beams' normalisation).

    Raises:
        ValueError: unknown product, a feed the beam lacks, a frequency outside a UVBeam's
            range, a cross-feed kernel needing a power-only UVBeam's E-field.
    """
    if pol not in PRODUCTS:
        raise ValueError(f"unknown visibility product {pol!r}; gcrsky models {list(PRODUCTS)}")
    ev = _Evaluator(az_uvbeam_rad, za_rad, freqs_hz, freq_interp_kind)
    return np.asarray(_pair_kernel(ev, beam_i, beam_j, pol, set()), np.complex128)


def baseline_kernels(
    beams: Sequence,
    pairs,
    az_uvbeam_rad,
    za_rad,
    freqs_hz,
    pols=None,
    *,
    freq_interp_kind: str | None = None,
) -> BaselineKernels:
    """Kernels of every row ``(pairs[b], pols[b])``, computed once per distinct (beam pair, product).

    Args:
        beams: per-antenna beams (``AntennaArray.beams``; identical antennas share one object).
        pairs: (Nbl, 2) antenna index pairs (i, j).
        az_uvbeam_rad, za_rad: (Npix,) directions (UVBeam azimuth North of East, zenith angle), radians.
        freqs_hz: (Nf,) Hz.
        pols: ``None``: the legacy unpolarised kernel ``A_i A_j`` with ``A = sqrt(P_xx)``
            (:func:`gcrsky.instrument.beam_amplitude`; exact for identical antennas, where it is
            ``K_xx``; for different beams it is ``sqrt(P_i,xx P_j,xx)``, exact only for
            proportional E-fields); or one product name per row (or one for all rows), see
            :func:`cross_power_kernel`.
        freq_interp_kind: as for :func:`cross_power_kernel`.

    Returns:
        :class:`BaselineKernels`; ``kernels[:, index]`` is the (Nf, Nbl, Npix) kernel of every row.
    """
    pairs = np.asarray(pairs, np.int64)
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    pols = normalise_pols(pols, pairs.shape[0])
    uniq, beam_idx = unique_beams(beams)
    bi, bj = beam_idx[pairs[:, 0]], beam_idx[pairs[:, 1]]
    row_keys = list(zip(bi.tolist(), bj.tolist(), pols if pols is not None else [None] * pairs.shape[0]))
    keys = tuple(dict.fromkeys(row_keys))
    where = {k: n for n, k in enumerate(keys)}
    index = np.fromiter((where[k] for k in row_keys), np.int64, count=len(row_keys))

    if pols is None:  # legacy: unpolarised amplitudes, products A_i A_j (bit for bit today's)
        used = sorted({k[0] for k in keys} | {k[1] for k in keys})
        amp = {b: beam_amplitude(uniq[b], az_uvbeam_rad, za_rad, freqs) for b in used}
        kern = np.stack([amp[a] * amp[b] for a, b, _ in keys], axis=1)
        return BaselineKernels(kern, index, keys)

    ev = _Evaluator(az_uvbeam_rad, za_rad, freqs, freq_interp_kind)
    warned: set = set()
    parts = [_pair_kernel(ev, uniq[a], uniq[b], pol, warned) for a, b, pol in keys]
    if all(np.isrealobj(k) or not np.any(np.imag(k)) for k in parts):
        kern = np.stack([np.real(k) for k in parts], axis=1).astype(np.float64)
    else:
        kern = np.stack(parts, axis=1).astype(np.complex128)
    return BaselineKernels(kern, index, keys)
