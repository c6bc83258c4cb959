"""HEALPix FITS products: maps (``healpy.write_map``) and harmonic coefficients (``healpy.write_alm``).

Conventions of both files:

- one entry per frequency channel, in the order of ``freqs_hz``: a *column* of the
  map file's binary table (named by :func:`freq_column_names`, e.g.
  ``FREQ_100.000MHZ``), an *HDU* of the alm file (HDU ``i + 1`` is channel ``i``,
  ``EXTNAME`` the same name);
- kelvin (``TUNIT`` keys); maps HEALPix RING; alm complex, healpy order
  (``index = l^2 + l + m + 1`` in the file, ``m >= 0``; ``healpy.read_alm`` returns the
  healpy-ordered array, :func:`gcrsky.sphere.realify` turns it into gcrsky's realified
  vector);
- ``COORDSYS = 'C'`` (celestial, equatorial) and ``FRAME`` saying which equatorial
  frame the coefficients live in (:data:`FRAMES`): ``'ICRS'`` for runs at real
  observing times, ``'IDEALISED'`` for the paper's idealised LSTs (the equatorial frame
  that co-rotates with the sky in the idealised model: no precession, nutation or
  aberration; the simulated truth is an ICRS sky read as coefficients of that frame);
- keys ``LMAX``, ``NSIDE`` (maps), ``NFREQ`` and ``FREQ<i>`` (Hz, 1-based like the
  columns), ``CONTENT`` (what the numbers are) and whatever the caller adds
  (``extra_header``: e.g. ``NDRAWS``, ``METHOD``).

Writes are atomic (:mod:`gcrsky.io.atomic`).  healpy and astropy are imported when a
file is written.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import numpy as np

from ..sphere.modes import n_alm, unrealify
from .atomic import atomic_path

__all__ = ["FRAMES", "freq_column_names", "frame_header", "write_alm_fits", "write_healpix_fits"]

#: The values of the ``FRAME`` key and their meaning (the frame of the sky coefficients).
FRAMES = {
    "icrs": ("ICRS", "ICRS (real observing times)"),
    "idealised": ("IDEALISED", "co-rotating frame of idealised LSTs"),
}


def freq_column_names(freqs_hz) -> list[str]:
    """Column / extension names of the channels: ``FREQ_<MHz, 3 decimals>MHZ``, e.g. ``FREQ_100.000MHZ``.

    Channels that would share a name get a suffix ``_<i>`` (their index).
    """
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    names = [f"FREQ_{f / 1e6:.3f}MHZ" for f in freqs]
    if len(set(names)) < len(names):
        names = [f"{n}_{i}" for i, n in enumerate(names)]
    return names


def frame_header(frame: str) -> list[tuple]:
    """FITS cards ``COORDSYS`` (the healpy key: ``'C'``, celestial) and ``FRAME`` for ``frame`` in :data:`FRAMES`."""
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {sorted(FRAMES)}, got {frame!r}")
    value, comment = FRAMES[frame]
    return [("FRAME", value, comment)]


def _freq_cards(freqs: np.ndarray) -> list[tuple]:
    cards = [("NFREQ", int(freqs.size), "number of frequency channels")]
    cards += [(f"FREQ{i + 1}", float(f), f"Hz, channel {i + 1}") for i, f in enumerate(freqs)]
    return cards


def write_healpix_fits(
    path,
    maps,
    freqs_hz,
    *,
    frame: str,
    lmax: int,
    content: str,
    extra_header: Iterable[tuple] = (),
) -> Path:
    """Write HEALPix RING maps, one column per frequency, to a FITS file (``healpy.write_map``).

    The file opens with ``healpy.read_map(path, field=None)``, which returns ``maps``
    (float64, bit for bit).

    Args:
        path: output file (replaced atomically if it exists).
        maps: ``(Nf, 12 nside^2)`` HEALPix RING maps, kelvin.
        freqs_hz: ``(Nf,)`` channel frequencies, Hz.
        frame: ``"icrs"`` or ``"idealised"`` (:data:`FRAMES`): the frame of the maps.
        lmax: maximum degree of the coefficients the maps were synthesised from.
        content: what the maps are (``CONTENT`` key), e.g. ``"posterior mean (Wiener filter)"``.
        extra_header: further ``(key, value, comment)`` cards.

    Returns:
        the path written.
    """
    import healpy as hp

    maps = np.asarray(maps, np.float64)
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if maps.ndim != 2 or maps.shape[0] != freqs.size:
        raise ValueError(f"maps must be (Nf, Npix) with Nf = {freqs.size} channels, got shape {maps.shape}")
    hp.npix2nside(maps.shape[1])  # raises for a length that is not 12 nside^2 (healpy writes NSIDE)
    header = frame_header(frame) + [("LMAX", int(lmax), "maximum degree l of the coefficients")]
    header += _freq_cards(freqs) + [("CONTENT", str(content)[:68])]
    header += [tuple(c) for c in extra_header]
    path = Path(path)
    with atomic_path(path) as tmp:
        hp.write_map(
            str(tmp), list(maps), nest=False, dtype=np.float64, coord="C", column_names=freq_column_names(freqs),
            column_units=["K"] * freqs.size, extra_header=header, overwrite=True,
        )
    return path


def write_alm_fits(
    path,
    a,
    lmax: int,
    freqs_hz,
    *,
    frame: str,
    content: str,
    extra_header: Iterable[tuple] = (),
) -> Path:
    """Write realified coefficients as complex healpy-ordered alm, one HDU per frequency (``healpy.write_alm``).

    ``healpy.read_alm(path, hdu=i + 1)`` returns channel ``i`` as the complex
    healpy-ordered ``unrealify(a[i], lmax)`` (``m >= 0``; ``Im a_l0 = 0``), bit for bit;
    ``hdu=(1, ..., Nf)`` returns all of them.  Each HDU's header carries ``EXTNAME``
    (the channel's name), ``FREQ`` (Hz), ``LMAX``, ``MMAX``, ``COORDSYS``, ``FRAME``,
    ``CONTENT`` and ``TUNIT2`` / ``TUNIT3`` = ``'K'`` (real and imaginary parts).

    Args:
        path: output file (replaced atomically if it exists).
        a: ``(Nf, (lmax+1)^2)`` realified coefficients (:mod:`gcrsky.sphere.modes`), kelvin.
        lmax: maximum degree.
        freqs_hz: ``(Nf,)`` channel frequencies, Hz.
        frame: ``"icrs"`` or ``"idealised"`` (:data:`FRAMES`).
        content: what the coefficients are (``CONTENT`` key).
        extra_header: further ``(key, value, comment)`` cards (in every HDU).

    Returns:
        the path written.
    """
    import healpy as hp
    from astropy.io import fits

    a = np.asarray(a, np.float64)
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if a.ndim != 2 or a.shape[0] != freqs.size:
        raise ValueError(f"a must be (Nf, n) with Nf = {freqs.size} channels, got shape {a.shape}")
    alm = np.asarray(unrealify(a, lmax))  # (Nf, nalm), checks n against lmax
    assert alm.shape[-1] == n_alm(lmax)
    names = freq_column_names(freqs)
    cards: list[tuple] = [("COORDSYS", "C", "celestial (equatorial)")] + frame_header(frame)
    cards += [("LMAX", int(lmax), "maximum degree l"), ("MMAX", int(lmax), "maximum order m")]
    cards += [("CONTENT", str(content)[:68])]
    cards += [tuple(c) for c in extra_header]
    path = Path(path)
    with atomic_path(path) as tmp:
        hp.write_alm(str(tmp), list(alm), lmax=lmax, mmax=lmax, out_dtype=np.float64, overwrite=True)
        with fits.open(tmp, mode="update") as hdul:
            for i, (name, f) in enumerate(zip(names, freqs)):
                h = hdul[i + 1].header
                h["EXTNAME"] = name
                h["TUNIT2"] = "K"
                h["TUNIT3"] = "K"
                h["FREQ"] = (float(f), "Hz")
                for c in cards:
                    h[c[0]] = tuple(c[1:]) if len(c) > 2 else c[1]
    return path

