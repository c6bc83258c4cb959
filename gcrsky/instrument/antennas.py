"""Antenna arrays: layouts, baselines and the site.

Conventions:

* Antenna positions are local East-North-Up (ENU) in metres.
* A baseline (i, j) has vector ``b_ij = x_j - x_i`` (pyuvdata's ant2 - ant1), and the
  visibility is ``V_ij = sum A_i^* A_j I exp(+2 pi i b_ij . s / lambda)``, i.e.
  ``<E_i^* E_j>`` (matvis' and pyuvdata's sign, pinned against matvis in
  ``tests/test_matvis.py``).
* Beams live in :mod:`gcrsky.instrument.beams`; an :class:`AntennaArray` holds one
  beam object per antenna.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

__all__ = [
    "HERA_HEIGHT_M",
    "HERA_LATITUDE_DEG",
    "HERA_LONGITUDE_DEG",
    "AntennaArray",
    "antpairs",
    "baseline_vectors",
    "hex_array",
    "make_array",
]

#: HERA's geodetic latitude (degrees); the paper's site.  Pass it explicitly.
HERA_LATITUDE_DEG = -30.7215
#: HERA's east longitude (degrees) and height (m), for real observing times.
HERA_LONGITUDE_DEG = 21.4283
HERA_HEIGHT_M = 1073.0


class AntennaArray(NamedTuple):
    """An array of antennas at a site.

    Attributes:
        positions_enu_m: (Nants, 3) ENU antenna positions in metres.
        latitude_rad: site geodetic latitude in radians.
        beams: tuple of pyuvdata beam objects, one per antenna (may repeat the same object).
    """

    positions_enu_m: np.ndarray
    latitude_rad: float
    beams: tuple


def hex_array(rows: Sequence[int] = (3, 4, 3), spacing_m: float = 14.6) -> np.ndarray:
    """Close-packed hexagonal layout (the paper's 10 antennas: rows of 3, 4, 3).

    Rows run East-West and are stacked North-South ``spacing * sqrt(3)/2`` apart;
    each row is centred on the array centre.  Returns (Nants, 3) ENU metres,
    antennas numbered row by row (north row first), west to east.
    """
    rows = [int(r) for r in rows]
    if not rows or any(r <= 0 for r in rows):
        raise ValueError(f"rows must be positive antenna counts, got {rows}")
    if not spacing_m > 0:
        raise ValueError(f"spacing_m must be positive, got {spacing_m}")
    dy = spacing_m * np.sqrt(3.0) / 2.0
    pos = []
    nrow = len(rows)
    for r, count in enumerate(rows):
        north = ((nrow - 1) / 2.0 - r) * dy
        for k in range(count):
            east = (k - (count - 1) / 2.0) * spacing_m
            pos.append((east, north, 0.0))
    return np.asarray(pos, dtype=np.float64)


def make_array(positions_enu_m, latitude_deg: float, beams) -> AntennaArray:
    """Validate and bundle an array.

    Args:
        positions_enu_m: (Nants, 3) or (Nants, 2) ENU metres (Up = 0 if 2 columns).
        latitude_deg: site latitude in degrees (no default: HERA is
            :data:`HERA_LATITUDE_DEG`).
        beams: one pyuvdata beam object for all antennas, or a sequence of Nants.
    """
    pos = np.asarray(positions_enu_m, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] not in (2, 3) or pos.shape[0] < 2:
        raise ValueError(f"positions_enu_m must be (Nants>=2, 2 or 3), got shape {pos.shape}")
    if pos.shape[1] == 2:
        pos = np.concatenate([pos, np.zeros((pos.shape[0], 1))], axis=1)
    if not np.all(np.isfinite(pos)):
        raise ValueError("antenna positions contain non-finite values")
    if not -90.0 <= latitude_deg <= 90.0:
        raise ValueError(f"latitude_deg must be in [-90, 90], got {latitude_deg}")
    if isinstance(beams, (list, tuple)):
        if len(beams) != pos.shape[0]:
            raise ValueError(f"got {len(beams)} beams for {pos.shape[0]} antennas")
        beams = tuple(beams)
    else:
        beams = (beams,) * pos.shape[0]
    return AntennaArray(pos, float(np.deg2rad(latitude_deg)), beams)


def antpairs(nants: int, autos: bool = False) -> np.ndarray:
    """Antenna pairs (i, j) with i < j (or i <= j with ``autos``), (Nbl, 2), row-major order."""
    iu = np.triu_indices(nants, k=0 if autos else 1)
    return np.stack(iu, axis=1).astype(np.int64)


def baseline_vectors(positions_enu_m: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Baseline vectors ``x_j - x_i`` for each pair (i, j): (Nbl, 3) metres."""
    return positions_enu_m[pairs[:, 1]] - positions_enu_m[pairs[:, 0]]


