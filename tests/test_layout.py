"""Tests of gcrsky.sphere.modes: the (l, m) packing and the real-harmonic basis convention.

References: healpy's ``Alm`` indexing and ``alm2map`` (independent SHT code), and
scipy's ``sph_harm_y`` (Condon-Shortley phase, ``sph_harm_y(l, m, colatitude,
longitude)``; its convention is pinned below against closed forms).

Tolerances: every comparison here is an exact identity evaluated in float64 on
O(1) numbers with at most ~100-term sums, so 1e-12 (absolute, on values of
order 1) leaves ~3 decades above rounding.
"""

from __future__ import annotations

import healpy as hp
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import sph_harm_y

from gcrsky.sphere import alm_to_map, lmax_from_nparams, mode_table, n_alm, n_params, realify, unrealify

EXACT = 1e-12  # float64 identity on O(1) values (see module docstring)


def random_alm(rng: np.random.Generator, lmax: int, batch=()) -> np.ndarray:
    """Random complex healpy-ordered alm of a real sky (Im a_l0 = 0)."""
    nalm = n_alm(lmax)
    alm = rng.standard_normal(batch + (nalm,)) + 1j * rng.standard_normal(batch + (nalm,))
    alm[..., : lmax + 1] = alm[..., : lmax + 1].real  # m = 0 block comes first in healpy order
    return alm


# ------------------------------------------------------------------ sizes and the table


@pytest.mark.parametrize("lmax", [0, 1, 2, 7, 20])
def test_sizes_match_healpy(lmax):
    assert n_alm(lmax) == hp.Alm.getsize(lmax)
    assert n_params(lmax) == (lmax + 1) ** 2
    # realified = all Re parts + Im parts of the m >= 1 entries
    assert n_params(lmax) == 2 * n_alm(lmax) - (lmax + 1)
    assert lmax_from_nparams(n_params(lmax)) == lmax


@pytest.mark.parametrize("lmax", [0, 1, 5, 16])
def test_mode_table_matches_healpy(lmax):
    tab = mode_table(lmax)
    nalm = n_alm(lmax)
    ell_hp, m_hp = hp.Alm.getlm(lmax, np.arange(nalm))
    pos = m_hp > 0
    n = n_params(lmax)
    for arr in tab:
        assert arr.shape == (n,)
    # first block: every (l, m >= 0) in healpy order, real parts
    np.testing.assert_array_equal(tab.ell[:nalm], ell_hp)
    np.testing.assert_array_equal(tab.m[:nalm], m_hp)
    assert not tab.is_imag[:nalm].any()
    # second block: (l, m >= 1) in healpy order, imaginary parts
    np.testing.assert_array_equal(tab.ell[nalm:], ell_hp[pos])
    np.testing.assert_array_equal(tab.m[nalm:], m_hp[pos])
    assert tab.is_imag[nalm:].all()
    # alm_index points at the healpy index of (l, m)
    np.testing.assert_array_equal(tab.alm_index, hp.Alm.getidx(lmax, tab.ell, tab.m))
    # each (l, m, part) appears exactly once
    keys = set(zip(tab.ell.tolist(), tab.m.tolist(), tab.is_imag.tolist()))
    assert len(keys) == n


# ------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("lmax", [0, 1, 7])
def test_realify_unrealify_round_trip_numpy(lmax):
    rng = np.random.default_rng(1)
    alm = random_alm(rng, lmax, batch=(3, 2))
    a = realify(alm, lmax)
    assert isinstance(a, np.ndarray) and a.shape == (3, 2, n_params(lmax))
    np.testing.assert_array_equal(unrealify(a, lmax), alm)
    # and the other way round, for an arbitrary real vector
    x = rng.standard_normal((4, n_params(lmax)))
    np.testing.assert_array_equal(realify(unrealify(x, lmax), lmax), x)
    # the entries are the (Re, Im) parts the mode table says they are
    tab = mode_table(lmax)
    expect = np.where(tab.is_imag, alm[..., tab.alm_index].imag, alm[..., tab.alm_index].real)
    np.testing.assert_array_equal(a, expect)


def test_realify_unrealify_round_trip_jax():
    lmax = 5
    rng = np.random.default_rng(2)
    alm = random_alm(rng, lmax, batch=(2,))
    a = realify(jnp.asarray(alm), lmax)
    assert isinstance(a, jnp.ndarray) and a.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(a), realify(alm, lmax))
    back = unrealify(a, lmax)
    assert back.dtype == jnp.complex128
    np.testing.assert_array_equal(np.asarray(back), alm)


@pytest.mark.parametrize(
    "call",
    [
        lambda: realify(np.zeros(11, complex), 3),
        lambda: unrealify(np.zeros(15), 3),
        lambda: unrealify(np.zeros(17), 3),
        lambda: lmax_from_nparams(50),
        lambda: lmax_from_nparams(0),
        lambda: n_params(-1),
        lambda: n_alm(2.5),
    ],
)
def test_bad_lengths_raise(call):
    with pytest.raises(ValueError):
        call()


def test_valid_lengths_do_not_raise():
    assert realify(np.zeros(10, complex), 3).shape == (16,)
    assert unrealify(np.zeros(16), 3).shape == (10,)


# ------------------------------------------------------------------ the real basis


def test_scipy_convention_closed_forms():
    """Pin scipy's argument order (l, m, colatitude, longitude) and Condon-Shortley phase."""
    th, ph = 0.7, 1.3
    np.testing.assert_allclose(sph_harm_y(0, 0, th, ph), 1 / np.sqrt(4 * np.pi), rtol=EXACT)
    np.testing.assert_allclose(sph_harm_y(1, 0, th, ph), np.sqrt(3 / (4 * np.pi)) * np.cos(th), rtol=EXACT)
    np.testing.assert_allclose(
        sph_harm_y(1, 1, th, ph), -np.sqrt(3 / (8 * np.pi)) * np.sin(th) * np.exp(1j * ph), rtol=EXACT
    )
    np.testing.assert_allclose(
        sph_harm_y(2, 2, th, ph), 0.25 * np.sqrt(15 / (2 * np.pi)) * np.sin(th) ** 2 * np.exp(2j * ph), rtol=EXACT
    )
    # reality relation Y_{l,-m} = (-1)^m conj(Y_lm)
    np.testing.assert_allclose(sph_harm_y(3, -2, th, ph), np.conj(sph_harm_y(3, 2, th, ph)), rtol=EXACT)
    np.testing.assert_allclose(sph_harm_y(3, -1, th, ph), -np.conj(sph_harm_y(3, 1, th, ph)), rtol=EXACT)


def full_complex_synthesis(alm: np.ndarray, lmax: int, theta, phi) -> np.ndarray:
    """sum over l and ALL m in [-l, l] of a_lm Y_lm, with a_{l,-m} = (-1)^m conj(a_lm).

    A reference for the real-basis convention that never uses the "2 Re Y" rule.
    """
    out = np.zeros(np.shape(theta), complex)
    for l in range(lmax + 1):
        for m in range(0, l + 1):
            a = alm[hp.Alm.getidx(lmax, l, m)]
            out += a * sph_harm_y(l, m, theta, phi)
            if m > 0:
                out += (-1) ** m * np.conj(a) * sph_harm_y(l, -m, theta, phi)
    return out


def test_alm_to_map_equals_healpy_and_full_sum():
    lmax, nside = 6, 8
    rng = np.random.default_rng(3)
    alm = random_alm(rng, lmax, batch=(2,))
    a = realify(alm, lmax)
    maps = alm_to_map(a, lmax, nside)
    assert maps.shape == (2, hp.nside2npix(nside))
    for k in range(2):
        np.testing.assert_allclose(maps[k], hp.alm2map(alm[k], nside, lmax=lmax), rtol=0, atol=EXACT)
    # independent: the full complex sum over +-m at the pixel centres is real and equals the map
    theta, phi = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    ref = full_complex_synthesis(alm[0], lmax, theta, phi)
    np.testing.assert_allclose(ref.imag, 0.0, atol=EXACT)
    np.testing.assert_allclose(maps[0], ref.real, rtol=0, atol=EXACT)


def test_basis_map_of_each_unit_vector():
    """alm_to_map(e_k) = Y_l0 (m = 0), 2 Re Y_lm (Re, m > 0), -2 Im Y_lm (Im, m > 0)."""
    lmax, nside = 4, 8
    n = n_params(lmax)
    tab = mode_table(lmax)
    theta, phi = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    maps = alm_to_map(np.eye(n), lmax, nside)  # (n, Npix)
    for k in range(n):
        y = sph_harm_y(tab.ell[k], tab.m[k], theta, phi)
        if tab.m[k] == 0:
            expect = y.real
        elif not tab.is_imag[k]:
            expect = 2 * y.real
        else:
            expect = -2 * y.imag
        msg = f"entry {k}: l={tab.ell[k]} m={tab.m[k]} imag={tab.is_imag[k]}"
        np.testing.assert_allclose(maps[k], expect, rtol=0, atol=EXACT, err_msg=msg)


def test_basis_closed_forms_l1():
    """A hand-checked case: the l = 1 basis maps are dipoles along z, x and y."""
    lmax, nside = 1, 4
    theta, phi = hp.pix2ang(nside, np.arange(hp.nside2npix(nside)))
    maps = alm_to_map(np.eye(4), lmax, nside)  # order: Re a00, Re a10, Re a11, Im a11
    c = np.sqrt(3 / (4 * np.pi))
    np.testing.assert_allclose(maps[0], 1 / np.sqrt(4 * np.pi), atol=EXACT)
    np.testing.assert_allclose(maps[1], c * np.cos(theta), atol=EXACT)
    # 2 Re Y_11 = -2 sqrt(3/8pi) sin(theta) cos(phi) = -sqrt(2) c x ; -2 Im Y_11 = +sqrt(2) c y
    np.testing.assert_allclose(maps[2], -np.sqrt(2) * c * np.sin(theta) * np.cos(phi), atol=EXACT)
    np.testing.assert_allclose(maps[3], np.sqrt(2) * c * np.sin(theta) * np.sin(phi), atol=EXACT)
