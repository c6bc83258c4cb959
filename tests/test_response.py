"""The ring-factored quadrature and the beam floor of ``response_matrix``.

``method="rings"`` sums ``K_p trig(m phi_p)`` along each HEALPix ring, then contracts
with ``Pbar_lm(theta_ring)``; ``method="direct"`` evaluates every basis map on every
pixel.  Same terms, same pixels, another summation order: they agree to rounding
(measured 2-3e-15 relative); 1e-12 leaves room for platform differences while any
error of index, sign, conjugation or Legendre normalisation is O(1).

``beam_floor`` drops pixels whose every beam product is <= floor x peak.  With the
default 1e-16 the dropped terms total at most ``1e-16 x (dropped pixels) x peak x w``,
below 1e-11 of the result for these grids (measured ~3e-15); a floor of 1e-3 must
change the response measurably (it drops the beam's wings): that is the control that
shows the parameter acts.
"""

from __future__ import annotations

import numpy as np
import pytest
from pyuvdata.analytic_beam import AiryBeam

from gcrsky.instrument import (
    HERA_LATITUDE_DEG,
    antpairs,
    gaussian_beam,
    hex_array,
    make_array,
    response_matrix,
    sky_grid,
)

FREQS = (100e6, 102e6)


def _rel(a, b) -> float:
    """max |a - b| / max |b|."""
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b))))


@pytest.mark.parametrize("lmax,nside,lst", [(8, 32, 0.0), (15, 16, 1.3), (12, 32, -2.1)])
def test_rings_equal_direct(small_array, lmax, nside, lst):
    pairs = np.concatenate([antpairs(10), [[3, 3], [7, 2]]])  # autos and a reversed pair too
    kw = dict(lst_ref_rad=lst, beam_floor=0.0)
    rings = response_matrix(small_array, pairs, FREQS, lmax, nside, method="rings", **kw)
    direct = response_matrix(small_array, pairs, FREQS, lmax, nside, method="direct", **kw)
    assert rings.shape == direct.shape == (2, pairs.shape[0], (lmax + 1) ** 2)
    assert _rel(rings, direct) < 1e-12


def test_rings_mixed_beams():
    """Two beam kinds: every (beam_i, beam_j) combination goes through the ring sums."""
    pos = hex_array()
    beams = [gaussian_beam(14.0) if i % 2 else AiryBeam(diameter=14.0) for i in range(pos.shape[0])]
    arr = make_array(pos, HERA_LATITUDE_DEG, beams)
    pairs = antpairs(pos.shape[0])[:20]
    rings = response_matrix(arr, pairs, FREQS, 10, 32, method="rings", beam_floor=0.0)
    direct = response_matrix(arr, pairs, FREQS, 10, 32, method="direct", beam_floor=0.0)
    assert _rel(rings, direct) < 1e-12


def test_beam_floor_default_is_rounding_level(small_array):
    pairs = antpairs(10)
    full = response_matrix(small_array, pairs, FREQS, 12, 64, beam_floor=0.0)
    cut = response_matrix(small_array, pairs, FREQS, 12, 64)  # default 1e-16
    assert _rel(cut, full) < 1e-11
    # and it does drop most of the sky: the 14 m dish is below 1e-16 beyond ~45 deg
    grid = sky_grid(64, small_array.latitude_rad)
    assert np.degrees(grid.za.max()) > 89.0
    loose = response_matrix(small_array, pairs, FREQS, 12, 64, beam_floor=1e-3)
    assert _rel(loose, full) > 1e-4  # control: a coarse floor is visible


def test_bad_arguments(small_array):
    pairs = antpairs(10)
    with pytest.raises(ValueError, match="method"):
        response_matrix(small_array, pairs, FREQS, 4, 16, method="fft")
    with pytest.raises(ValueError, match="beam_floor"):
        response_matrix(small_array, pairs, FREQS, 4, 16, beam_floor=1.0)


def test_response_refuses_what_does_not_fit(small_array, monkeypatch):
    from gcrsky.base import InsufficientMemoryError

    monkeypatch.setenv("GCRSKY_MEMORY_BUDGET_GB", "0.01")  # 10 MiB
    with pytest.raises(InsufficientMemoryError, match=r"response \(2 freqs x 45 baselines x 441 modes.*redundant"):
        response_matrix(small_array, antpairs(10), FREQS, 20, 16)
