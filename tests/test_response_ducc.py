"""response_matrix(method="ducc") (ducc0 adjoint synthesis over the beam's rings) against sht and rings.

The same pixel sum as the healpy route (same pixels, weight 4 pi / Npix, realified
projection) and the ring quadrature; only the summation order differs, and the rings
ducc skips hold only pixels below the horizon or below ``beam_floor`` x peak (1e-16 by
default: below rounding).  Measured agreement ~1e-15 of the largest entry; the tolerance
1e-12 still catches any scaling, sign, conjugation or index error (all O(1)).
"""

from __future__ import annotations

import builtins

import numpy as np
import pytest

from gcrsky.instrument import (
    HERA_LATITUDE_DEG,
    antpairs,
    gaussian_beam,
    hex_array,
    make_array,
    response_matrix,
)
from gcrsky.instrument.response_ducc import _ducc, response_matrix_ducc

pytest.importorskip("ducc0")

FREQS = (100e6, 102e6)
RTOL = 1e-12


def _rel_err(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / np.abs(b).max())


@pytest.fixture(scope="module")
def hexagon():
    return make_array(hex_array(), HERA_LATITUDE_DEG, gaussian_beam(14.0))


@pytest.mark.parametrize("lmax,nside,lst", [(6, 32, 0.0), (12, 16, 1.3), (20, 32, -2.1)])
def test_matches_sht_and_rings(hexagon, lmax, nside, lst):
    pairs = antpairs(10, autos=True)  # 45 crosses + 10 autos
    ducc = response_matrix(hexagon, pairs, FREQS, lmax, nside, lst_ref_rad=lst, method="ducc")
    sht = response_matrix(hexagon, pairs, FREQS, lmax, nside, lst_ref_rad=lst, method="sht")
    rings = response_matrix(hexagon, pairs, FREQS, lmax, nside, lst_ref_rad=lst, method="rings")
    assert ducc.shape == sht.shape == (2, 55, (lmax + 1) ** 2)
    assert ducc.dtype == sht.dtype
    assert _rel_err(ducc, sht) < RTOL
    assert _rel_err(ducc, rings) < RTOL


def test_every_visible_ring_without_floor_and_ragged_chunks(hexagon):
    """beam_floor=0 keeps every ring above the horizon: the healpy route's sum exactly."""
    pairs = antpairs(10)[::2]
    sht = response_matrix(hexagon, pairs, FREQS, 10, 16, lst_ref_rad=0.4, method="sht")
    ducc = response_matrix_ducc(hexagon, pairs, FREQS, 10, 16, 0.4, beam_floor=0.0, chunk=3, nthreads=1)
    assert _rel_err(ducc, sht) < RTOL


@pytest.mark.parametrize("pols", ["xx", "pI", ["xx", "yy", "xy", "yx"] * 3])
def test_polarised_kernels(pols):
    """Polarised products, complex kernels (mixed beams, the cross products) included."""
    from pyuvdata.analytic_beam import ShortDipoleBeam

    beams = [ShortDipoleBeam() if k % 2 else gaussian_beam(14.0) for k in range(10)]
    arr = make_array(hex_array(), HERA_LATITUDE_DEG, beams)
    pairs = antpairs(10)[:12]
    kw = {"lst_ref_rad": 0.7, "pols": pols}
    ducc = response_matrix(arr, pairs, FREQS, 8, 16, method="ducc", **kw)
    assert _rel_err(ducc, response_matrix(arr, pairs, FREQS, 8, 16, method="sht", **kw)) < RTOL
    assert _rel_err(ducc, response_matrix(arr, pairs, FREQS, 8, 16, method="rings", **kw)) < RTOL


def test_floor_skips_rings(hexagon):
    """A high floor drops the beam's wing rings: a measurable change (the parameter acts)."""
    pairs = antpairs(10)[:4]
    full = response_matrix_ducc(hexagon, pairs, FREQS, 12, 32)
    loose = response_matrix_ducc(hexagon, pairs, FREQS, 12, 32, beam_floor=1e-2)
    assert _rel_err(loose, full) > 1e-6


def test_bad_inputs(hexagon):
    pairs = antpairs(10)[:3]
    with pytest.raises(ValueError, match="3\\*nside-1"):
        response_matrix_ducc(hexagon, pairs, FREQS, 48, 16)
    with pytest.raises(ValueError, match="chunk"):
        response_matrix_ducc(hexagon, pairs, FREQS, 6, 16, chunk=0)
    with pytest.raises(ValueError, match="beam_floor"):
        response_matrix_ducc(hexagon, pairs, FREQS, 6, 16, beam_floor=1.0)
    with pytest.raises(ValueError, match="pairs"):
        response_matrix_ducc(hexagon, np.array([[0, 10]]), FREQS, 6, 16)


def test_missing_ducc0_is_named(hexagon, monkeypatch):
    """Without ducc0 the route says which package it needs, and "auto" falls back."""
    real_import = builtins.__import__

    def no_ducc(name, *args, **kwargs):
        if name.startswith("ducc0"):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_ducc)
    with pytest.raises(ImportError, match="ducc0"):
        _ducc()
    pairs = antpairs(10)[:3]
    with pytest.raises(ImportError, match="ducc0"):
        response_matrix(hexagon, pairs, FREQS, 6, 16, method="ducc")
    auto = response_matrix(hexagon, pairs, FREQS, 6, 16)
    monkeypatch.setattr(builtins, "__import__", real_import)
    np.testing.assert_array_equal(
        np.asarray(auto), np.asarray(response_matrix(hexagon, pairs, FREQS, 6, 16, method="rings"))
    )
