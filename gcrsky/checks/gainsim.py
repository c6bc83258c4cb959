"""Known antenna gains for simulated visibility files: a UVData corrupted and the UVCal of its gains.

:func:`smooth_gains` draws direction-independent gains per antenna and feed,
``g = (1 + a) exp(i phi)``, with ``a`` and ``phi`` real fields that are smooth in frequency
(the first ``delay_modes`` Legendre polynomials across the band) and slow in time (the first
``time_modes`` across the observation), scaled so that the realisation's rms of ``a`` is
``amp`` and of ``phi`` is ``phase_deg``.  The low-order modes are a generic gain model
independent of gcrsky's (:mod:`gcrsky.model.gains` uses DPSS or Fourier modes and the
linearised ``1 + x``), so a sampler's gain basis only approximates them: the second-order
and basis mismatch is what a test on them sees as modelling error.

:func:`corrupt_with_gains` applies them with pyuvdata's convention: the product ``pq`` of row
``(ant_1, ant_2) = (i, j)`` becomes ``g_{i,p} conj(g_{j,q}) V_ij`` (autocorrelations too), and
returns the UVCal of the same gains with ``gain_convention = "divide"`` (``cal_style`` "sky"),
so that ``pyuvdata.utils.uvcalibrate(corrupted, uvcal)`` divides them out again.

Noise: the gains multiply whatever the UVData holds.  Given a noisy simulation (as
:func:`gcrsky.checks.uvsim.simulate_uvdata` returns) the noise is scaled with the signal,
as in a real receiver, where the gain follows the noise-adding front end: the per-row noise
is then ``|g_i g_j|`` times the uncorrupted one, which is exactly the radiometer equation
on the corrupted autocorrelations (``|g_i|^2 V_ii``), so an ingest that takes its noise
from the file's autos (``noise="autos"``) sees the right sigma.  Corrupting the noiseless
model and adding noise afterwards would leave the autos' prediction wrong by ``|g_i g_j|``.
The corrupted data divided by the uncorrupted ones is then the pair gain exactly, noise
and all, which is what a test of a calibration can compare against.
"""

from __future__ import annotations

import numpy as np

__all__ = ["corrupt_with_gains", "smooth_gains"]


def _legendre_modes(x: np.ndarray, k: int) -> np.ndarray:
    """(len(x), k) Legendre polynomials P_0..P_{k-1} of ``x`` mapped onto [-1, 1] (P_0 only for one sample)."""
    x = np.asarray(x, float)
    span = x.max() - x.min()
    u = np.zeros_like(x) if span == 0 else 2.0 * (x - x.min()) / span - 1.0
    return np.stack([np.polynomial.legendre.Legendre.basis(p)(u) for p in range(k)], axis=1)


def smooth_gains(n_ant: int, freqs_hz, times_jd, *, n_feeds: int = 2, amp: float = 0.05, phase_deg: float = 5.0,
                 delay_modes: int = 2, time_modes: int = 2, seed: int = 0) -> np.ndarray:
    """Known gains ``g = (1 + a) exp(i phi)`` (Nant, Nf, Nt, Nfeed) complex, smooth in frequency and time.

    ``a`` and ``phi`` of every antenna and feed are ``sum_kl c_kl P_k(nu) P_l(t)`` over the first
    ``delay_modes`` x ``time_modes`` Legendre polynomials of frequency and time (each axis mapped
    onto [-1, 1] over its span), with independent standard normal ``c_kl`` damped by ``2^-(k + l)``
    (the constant dominates; the slopes across the band and the observation are half of it),
    then scaled so that the realisation's rms over antennas, feeds, channels and times is
    exactly ``amp`` for ``a`` and ``phase_deg`` (degrees) for ``phi``.

    Args:
        n_ant: Nant antennas (in the order the caller indexes them).
        freqs_hz: (Nf,) channel frequencies, Hz.
        times_jd: (Nt,) times, JD (any monotonic time axis: only its span matters).
        n_feeds: Nfeed feeds per antenna (x, y for a linear-feed file).
        amp: rms fractional amplitude error.
        phase_deg: rms phase error, degrees.
        delay_modes, time_modes: polynomial order + 1 along frequency and time (1: constant).
        seed: the draw's seed (NumPy ``default_rng``).

    Returns:
        (Nant, Nf, Nt, Nfeed) complex gains, pyuvdata's ``gain_array`` layout.
    """
    freqs, times = np.atleast_1d(np.asarray(freqs_hz, float)), np.atleast_1d(np.asarray(times_jd, float))
    bf, bt = _legendre_modes(freqs, delay_modes), _legendre_modes(times, time_modes)
    damp = 2.0 ** -np.add.outer(np.arange(delay_modes), np.arange(time_modes))
    rng = np.random.default_rng(seed)

    def field(rms):
        c = rng.standard_normal((n_ant, n_feeds, delay_modes, time_modes)) * damp
        f = np.einsum("fk,tl,apkl->aftp", bf, bt, c)
        return f * (rms / np.sqrt(np.mean(f**2)))

    a, phi = field(amp), field(np.deg2rad(phase_deg))
    return (1.0 + a) * np.exp(1j * phi)


def _feed_index(uvd, jones_feeds):
    """Per polarization of ``uvd``: (feed index on ant_1, feed index on ant_2) into ``jones_feeds`` ("x", "y").

    By polarization number (-5..-8: xx, yy, xy, yx), as pyuvdata pairs them with the Jones terms -5 (Jxx)
    and -6 (Jyy), whatever the x_orientation calls them (ee, nn).
    """
    from pyuvdata import utils

    out = []
    for num in np.asarray(uvd.polarization_array):
        name = utils.polnum2str(int(num)).lower()
        if len(name) != 2 or any(c not in jones_feeds for c in name):
            raise ValueError(f"corrupt_with_gains takes linear feed products (xx, yy, xy, yx), not {name!r}")
        out.append((jones_feeds.index(name[0]), jones_feeds.index(name[1])))
    return out


def corrupt_with_gains(uvd, *, amp: float = 0.05, phase_deg: float = 5.0, delay_modes: int = 2, time_modes: int = 2,
                       seed: int = 0):
    """Apply known smooth gains to a UVData: ``V_ij,pq -> g_{i,p} conj(g_{j,q}) V_ij,pq``; and their UVCal.

    The gains are :func:`smooth_gains`' (per antenna of the telescope and feed x, y; see there
    for ``amp``, ``phase_deg``, ``delay_modes``, ``time_modes``, ``seed``) at the data's channels
    and unique times.  Every row is corrupted, autocorrelations included; whatever noise the
    data hold is scaled with them (module docstring: why).

    Args:
        uvd: a pyuvdata ``UVData`` with linear feed products (``xx``, ``yy``, ``xy``, ``yx``;
            ``ee``/``nn`` names through its x_orientation), one spectral window. Not modified.

    Returns:
        ``(corrupted, uvcal)``: a corrupted copy of ``uvd``, and a pyuvdata ``UVCal``
        (``cal_type`` "gain", ``cal_style`` "sky", ``gain_convention`` "divide", Jones
        ``Jxx``, ``Jyy``; ``gain_array`` (Nant_telescope, Nf, Nt, 2), the data's frequencies
        and unique times, no flags) with which ``uvcalibrate(corrupted, uvcal)`` gives back
        ``uvd``'s data.
    """
    from pyuvdata import UVCal

    out = uvd.copy()
    freqs = np.asarray(uvd.freq_array, float).reshape(-1)
    times = np.unique(uvd.time_array)
    numbers = np.asarray(uvd.telescope.antenna_numbers, int)
    g = smooth_gains(numbers.size, freqs, times, amp=amp, phase_deg=phase_deg, delay_modes=delay_modes,
                     time_modes=time_modes, seed=seed)
    row = {int(n): k for k, n in enumerate(numbers)}
    i = np.array([row[int(a)] for a in uvd.ant_1_array])
    j = np.array([row[int(a)] for a in uvd.ant_2_array])
    t = np.searchsorted(times, uvd.time_array)
    for p, (fi, fj) in enumerate(_feed_index(uvd, ("x", "y"))):
        gi = g[i, :, t, fi]  # (Nblts, Nf)
        gj = g[j, :, t, fj]
        factor = gi * np.conj(gj)
        if fi == fj:  # an antenna's own-feed autocorrelation stays real (|g|^2, not its rounding)
            factor = np.where((i == j)[:, None], np.abs(gi) ** 2, factor)
        out.data_array[:, :, p] = uvd.data_array[:, :, p] * factor
    out.history += (f"\ngcrsky.checks.gainsim: corrupted with smooth gains (amp {amp}, phase {phase_deg} deg, "
                    f"{delay_modes} x {time_modes} Legendre modes, seed {seed})")
    cal = UVCal.initialize_from_uvdata(uvd, gain_convention="divide", cal_style="sky", metadata_only=True,
                                       jones_array=np.array([-5, -6]), time_array=times, ant_array=numbers,
                                       ref_antenna_name="none (true gains)",
                                       sky_catalog="gcrsky.checks.gainsim: the true gains of a simulation")
    cal.gain_array = g
    cal.gain_scale = uvd.vis_units  # the gains carry no unit change; uvcalibrate keeps the data's units
    cal.pol_convention = uvd.pol_convention
    cal.flag_array = np.zeros(g.shape, bool)
    cal.quality_array = np.zeros(g.shape)
    cal.check()
    return out, cal
