"""Visibility response at the reference rotation angle (a sky quadrature).

``R[f, b, k] = sum_p  w_p K_b(p) exp(+2 pi i b_ij . s_p nu_f / c) f_k(p)``
over the HEALPix pixels ``p`` above the horizon at the reference local sidereal
angle, with ``b_ij = x_j - x_i`` (pyuvdata's ant2 - ant1), ``w_p = 4 pi / Npix``
(steradians), ``s_p`` the ENU unit vector of the pixel, ``K_b`` the beam kernel of
row ``b`` and ``f_k`` the real basis maps.  The fringe sign is matvis' and
pyuvdata's (``V_ij = <E_i^* E_j>``).

The kernel: with ``pols=None`` (the default, unchanged) the unpolarised
``K = A_i(p) A_j(p)``, ``A = sqrt(P_xx)``, and ``V`` is twice matvis' unpolarised
feed-x visibility (matvis gives each feed I/2; pinned in ``tests/test_matvis.py``, see
``docs/conventions.md``).  With ``pols`` (one product per row: ``"xx"``, ``"yy"``,
``"xy"``, ``"yx"``, ``"pI"``) the polarisation-correct cross power beam of
:mod:`gcrsky.instrument.polarization`, ``K_ij,pq = sum_a conj(E_i,p^a) E_j,q^a``
(``(K_xx + K_yy)/2`` for ``"pI"``), complex for different beams on the two antennas:
I-equivalent visibilities (pyuvdata's "avg" convention: ``"xx"`` = ``2 V_xx``, ``"pI"`` =
``V_xx + V_yy`` of matvis' polarised run, pinned in ``tests/test_polarized_response.py``).
The kernels are evaluated once per distinct (beam pair, product), not per baseline;
a complex kernel ``K = K_r + i K_i`` enters as ``Re = K_r cos phi - K_i sin phi``,
``Im = K_r sin phi + K_i cos phi`` (the real-kernel case keeps the cheaper real sums).
A sky in Kelvin gives visibilities in K sr (multiply by ``2 k nu^2 / c^2`` for
Jy; see :func:`gcrsky.base.kelvin_sr_to_jy`).

Frames (idealised LST mode, the paper's): the coefficients live in an equatorial
frame that co-rotates with local sidereal angle; at LST ``t`` (radians) the
direction with hour angle ``h`` sees right ascension ``t - h``.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..base.memory import check_memory
from ..base.units import SPEED_OF_LIGHT
from ..sphere.harmonics import legendre_table, real_basis
from ..sphere.modes import mode_table, n_params
from .antennas import AntennaArray, baseline_vectors
from .beams import unique_beams
from .polarization import baseline_kernels, normalise_pols
from .skygrid import SkyGrid, equatorial_to_enu, sky_grid

__all__ = [
    "RESPONSE_DUCC_MIN_LMAX",
    "RESPONSE_SHT_MIN_LMAX",
    "SkyGrid",
    "analytic_response",
    "modulated_responses",
    "equatorial_to_enu",
    "response_matrix",
    "check_response_memory",
    "sky_grid",
]


def _fringe_kernel(kern_r, kern_i, kidx, w, phase):
    """``(Re, Im)`` of ``K w exp(i phase)`` per row: ``K = kern_r[:, kidx] (+ i kern_i[:, kidx])``.

    ``kern_i`` None: a real kernel (``K_i = 0``), two products instead of six.
    """
    beam = kern_r[:, kidx] * w  # (Nf, Nbl, ...)
    c, s = jnp.cos(phase), jnp.sin(phase)
    if kern_i is None:
        return beam * c, beam * s
    beam_i = kern_i[:, kidx] * w
    return beam * c - beam_i * s, beam * s + beam_i * c


@partial(jax.jit, static_argnums=(0, 1))
def _quadrature(lmax, chunk, theta, phi, enu, weight, kern_r, kern_i, kidx, bvec_wl):
    """Accumulate R over pixel chunks.  Inputs padded to a multiple of ``chunk``.

    theta, phi, weight: (Nc, chunk); enu: (Nc, chunk, 3); kern_r, kern_i: (Nc, Nf, Nk, chunk)
    real and imaginary kernels (kern_i None for a real kernel); kidx: (Nbl,) kernel of each
    row; bvec_wl: (Nf, Nbl, 3) baselines in wavelengths.
    """
    nf, nbl = bvec_wl.shape[:2]
    n = n_params(lmax)

    def body(acc, xs):
        th, ph, s, w, Kr, Ki = xs
        F = real_basis(lmax, th, ph)  # (chunk, n)
        phase = 2 * jnp.pi * jnp.einsum("fbd,pd->fbp", bvec_wl, s)  # +: matvis/pyuvdata sign
        kr, ki = _fringe_kernel(Kr, Ki, kidx, w[None, None, :], phase)  # (Nf, Nbl, chunk)
        acc_r, acc_i = acc
        acc_r = acc_r + jnp.einsum("fbp,pk->fbk", kr, F)
        acc_i = acc_i + jnp.einsum("fbp,pk->fbk", ki, F)
        return (acc_r, acc_i), None

    zero = jnp.zeros((nf, nbl, n), theta.dtype)
    (rr, ri), _ = jax.lax.scan(body, (zero, zero), (theta, phi, enu, weight, kern_r, kern_i))
    return rr + 1j * ri


def _ring_layout(theta: np.ndarray, max_bytes_row: int, budget_bytes: float):
    """Pixels grouped by HEALPix ring: a padded (ring, slot) table, in chunks of rings.

    Args:
        theta: (Npix_up,) colatitudes of the kept pixels (any subset of a HEALPix grid).
        max_bytes_row: bytes one slot costs per chunk (to size the chunks).
        budget_bytes: target memory of one chunk's kernel.

    Returns:
        (gather (Nc, rc, J) pixel indices, -1 = padding; ring colatitudes (Nc, rc),
        padded with pi/2).
    """
    rings, inv, counts = np.unique(theta, return_inverse=True, return_counts=True)
    J = int(counts.max())
    rc = int(max(1, min(rings.size, budget_bytes // max(1, max_bytes_row * J))))
    nc = -(-rings.size // rc)
    gather = np.full((nc * rc, J), -1, np.int64)
    order = np.argsort(inv, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(theta.size) - starts[inv[order]]
    gather[inv[order], slot] = order
    ring_theta = np.full(nc * rc, np.pi / 2)
    ring_theta[: rings.size] = rings
    return gather.reshape(nc, rc, J), ring_theta.reshape(nc, rc)


@partial(jax.jit, static_argnums=(0,))
def _ring_quadrature(lmax, ring_theta, phi, enu, weight, kern_r, kern_i, kidx, bvec_wl):
    """The quadrature of :func:`_quadrature` factored through HEALPix rings.

    For a pixel ``p`` on ring ``r`` the basis map is ``f_k(p) = c_k Pbar_lm(cos theta_r)
    trig_k(m phi_p)``, so ``R[k] = c_k sum_r Pbar_lm(theta_r) sum_{p in r} K_p trig_k(m phi_p)``
    with the kernel ``K_p = w_p K_b(p) exp(+2 pi i b.s_p / lambda)``.  The inner sums cost
    O(Npix (lmax+1)) per baseline instead of the direct O(Npix (lmax+1)^2); the outer sums
    O(Nrings (lmax+1)^2).  The same terms over the same pixels: equal to rounding.

    ring_theta: (Nc, rc); phi, weight: (Nc, rc, J) (weight 0 on padding slots);
    enu: (Nc, rc, J, 3); kern_r, kern_i: (Nc, Nf, Nk, rc, J) real and imaginary beam
    kernels (kern_i None for a real kernel); kidx: (Nbl,) kernel of each row;
    bvec_wl: (Nf, Nbl, 3) baselines in wavelengths.
    """
    nf, nbl = bvec_wl.shape[:2]
    L = lmax + 1
    mvec = jnp.arange(L)

    def body(acc, xs):
        th, ph, s, w, Kr, Ki = xs
        phase = 2 * jnp.pi * jnp.einsum("fbd,rjd->fbrj", bvec_wl, s)  # +: matvis/pyuvdata sign
        kern = jnp.stack(_fringe_kernel(Kr, Ki, kidx, w[None, None], phase), axis=1)  # (Nf, 2, Nbl, rc, J)
        mphi = ph[..., None] * mvec  # (rc, J, L)
        trig = jnp.stack([jnp.cos(mphi), jnp.sin(mphi)], axis=2)  # (rc, J, 2, L)
        # per-ring Fourier sums of the real and imaginary kernels: (Nf, 2, Nbl, rc, 2, L)
        q = jnp.einsum("fcbrj,rjtm->fcbrtm", kern, trig)
        lam = legendre_table(lmax, jnp.cos(th), jnp.sin(th))  # (L, rc, L) [l, ring, m]
        t = jnp.einsum("fcbrtm,lrm->fcbtlm", q, lam)  # (Nf, re/im kernel, Nbl, cos/sin, L, L)
        return acc + (t[:, 0] + 1j * t[:, 1]), None

    zero = jnp.zeros((nf, nbl, 2, L, L), jnp.result_type(bvec_wl.dtype, 1j))
    acc, _ = jax.lax.scan(body, zero, (ring_theta, phi, enu, weight, kern_r, kern_i))
    tc, ts = acc[:, :, 0], acc[:, :, 1]
    tab = mode_table(lmax)
    ell, m = jnp.asarray(tab.ell), jnp.asarray(tab.m)
    re = jnp.where(m == 0, 1.0, 2.0) * tc[:, :, ell, m]
    return jnp.where(jnp.asarray(tab.is_imag), -2.0 * ts[:, :, ell, m], re)


#: ``response_matrix(method="auto")`` builds by healpy transforms from this lmax on (the
#: faster route there: ``benchmarks/scale.py``, section (B)), by rings below it.
RESPONSE_SHT_MIN_LMAX = 200

#: ``response_matrix(method="auto")`` builds by ducc0 transforms over the beam's rings
#: (:mod:`gcrsky.instrument.response_ducc`) from this lmax on when ducc0 imports: it was
#: the fastest route at every size measured (lmax 20..650; ``benchmarks/response_routes.py``),
#: so 0; the other routes remain by name (and "auto" falls back to them without ducc0).
RESPONSE_DUCC_MIN_LMAX = 0


def response_matrix(
    array: AntennaArray,
    pairs: np.ndarray,
    freqs_hz,
    lmax: int,
    nside: int,
    *,
    lst_ref_rad: float = 0.0,
    chunk: int = 4096,
    method: str = "auto",
    beam_floor: float = 1e-16,
    pols=None,
) -> jax.Array:
    """Complex response of each baseline and frequency to each realified mode.

    Args:
        array: the :class:`~gcrsky.instrument.AntennaArray` (positions, latitude, beams).
        pairs: (Nbl, 2) antenna index pairs (i, j); autos (i, i) allowed.
        freqs_hz: (Nf,) frequencies, Hz (within every UVBeam's channel range).
        lmax: maximum degree (static).
        nside: HEALPix nside of the quadrature grid.
        lst_ref_rad: local sidereal angle of the reference grid, radians.
        chunk: pixels per batch of the direct method; memory is
            O(chunk * (lmax+1)**2 + Nf*Nbl*chunk).
        method: ``"auto"`` (default): ``"ducc"`` for ``lmax >=`` :data:`RESPONSE_DUCC_MIN_LMAX`
            (every lmax) when ducc0 imports, else ``"sht"`` for ``lmax >=``
            :data:`RESPONSE_SHT_MIN_LMAX`, else ``"rings"``; ``"ducc"``: ducc0's adjoint
            synthesis of each row's kernel map over only the HEALPix rings that hold a pixel
            above ``beam_floor`` (:func:`gcrsky.instrument.response_ducc.response_matrix_ducc`;
            the same pixels as ``"rings"``; ``chunk`` does not apply);
            ``"rings"``: the sum factored through HEALPix rings,
            O(Nf Nbl Npix lmax + Nf Nbl Nrings lmax^2); ``"direct"``: every basis map
            on every pixel, O(Nf Nbl Npix lmax^2); ``"sht"``: healpy's transform of
            each baseline's kernel map
            (:func:`gcrsky.instrument.response_sht.response_matrix_sht`, which keeps
            every visible pixel: ``beam_floor`` and ``chunk`` do not apply).  The same
            terms summed in another order (they agree to ~1e-14 relative;
            ``tests/test_response.py``, ``tests/test_response_sht.py``,
            ``tests/test_response_ducc.py``).
        beam_floor: pixels where every beam kernel ``|K|`` (all frequencies and
            rows) is at most ``beam_floor`` times its peak are left out of the sum.
            The default 1e-16 drops only terms below float64 rounding of the result
            (a 14 m Gaussian dish at 100 MHz keeps the 45 degrees around zenith:
            29% of the visible pixels); 0 keeps every pixel above the horizon.
        pols: ``None`` (default): the unpolarised kernel ``A_i A_j``, ``A = sqrt(P_xx)``:
            ``2 V_xx`` of matvis' sum convention, exact for identical antennas (for
            different beams it is ``sqrt(P_i P_j)``, exact only for proportional E-fields;
            ask for ``"xx"`` for the exact cross kernel).  Or the visibility product of
            each row, a sequence of ``Nbl`` names from ``("xx", "yy", "xy", "yx", "pI")``
            (one name: every row): the cross power beams of
            :mod:`gcrsky.instrument.polarization` (I-equivalent, pyuvdata's "avg"
            convention).  A joint ``("xx", "yy")`` fit is the rows ``pairs`` with ``"xx"``
            stacked on the rows ``pairs`` with ``"yy"``.  Autocorrelations (i, i) follow
            the same rules (``"pI"``: ``(P_xx + P_yy)/2``).

    Returns:
        (Nf, Nbl, (lmax+1)**2) complex128 response in K sr per unit coefficient (K).
    """
    freqs, pairs, method = _checked_inputs(array, pairs, freqs_hz, lmax, method, beam_floor)
    pols = normalise_pols(pols, pairs.shape[0])
    check_response_memory(array, pairs, freqs, lmax, nside, pols, copies=1 if method == "ducc" else 2)
    grid = sky_grid(nside, array.latitude_rad, lst_ref_rad)
    if method == "ducc":
        from .response_ducc import response_matrix_ducc

        return response_matrix_ducc(array, pairs, freqs, lmax, nside, lst_ref_rad, beam_floor=beam_floor, pols=pols)
    if method == "sht":
        from .response_sht import response_matrix_sht

        return response_matrix_sht(array, pairs, freqs, lmax, nside, lst_ref_rad, pols=pols)

    grid, kern_r, kern_i, kidx = _grid_kernels(array, pairs, freqs, grid, pols, beam_floor)
    bvec = baseline_vectors(array.positions_enu_m, pairs)
    bvec_wl = jnp.asarray(bvec[None, :, :] * (freqs[:, None, None] / SPEED_OF_LIGHT))
    weight_pix = np.full(grid.theta.size, grid.weight_sr)
    if method == "rings":
        return _rings(int(lmax), grid, kern_r, kern_i, kidx, bvec_wl, weight_pix)
    return _direct(int(lmax), int(chunk), grid, kern_r, kern_i, kidx, bvec_wl, weight_pix)


def modulated_responses(array: AntennaArray, pairs: np.ndarray, freqs_hz, lmax: int, nside: int, modulation, *,
                        lst_ref_rad: float = 0.0, pols=None, beam_floor: float = 1e-16) -> jax.Array:
    """The responses of every row's beam kernel times each of ``S`` real maps: ``R^(s)`` with kernel ``K_b m_s``.

    The quadrature of :func:`response_matrix`'s ``"rings"`` method with each kernel multiplied by the maps
    ``modulation(az_uvbeam, za, freqs)`` -> (Nf, S, Np) on the grid's kept pixels (e.g. the products of
    :mod:`gcrsky.instrument.beammodes`' perturbation modes); a modulation of ones is the response itself.

    Args:
        array, pairs, freqs_hz, lmax, nside, lst_ref_rad, pols, beam_floor: as :func:`response_matrix`.
        modulation: a function of ``(az_uvbeam (Np,), za (Np,), freqs (Nf,))`` returning (Nf, S, Np) real.

    Returns:
        (Nf, S, Nbl, (lmax + 1)^2) complex128.
    """
    freqs, pairs, _ = _checked_inputs(array, pairs, freqs_hz, lmax, "rings", beam_floor)
    pols = normalise_pols(pols, pairs.shape[0])
    grid = sky_grid(nside, array.latitude_rad, lst_ref_rad)
    grid, kern_r, kern_i, kidx = _grid_kernels(array, pairs, freqs, grid, pols, beam_floor)
    scale = np.asarray(modulation(grid.az_uvbeam, grid.za, freqs), np.float64)
    if scale.ndim != 3 or scale.shape[0] != freqs.size or scale.shape[2] != grid.za.size:
        raise ValueError(f"modulation returned shape {scale.shape}, expected (Nf, S, Np) = ({freqs.size}, S, "
                         f"{grid.za.size})")
    ns, nk = scale.shape[1], kern_r.shape[1]
    check_response_memory(array, np.tile(pairs, (ns, 1)), freqs, lmax, nside,
                          None if pols is None else list(pols) * ns)
    kr = (kern_r[:, None] * scale[:, :, None, :]).reshape(freqs.size, ns * nk, -1)
    ki = None if kern_i is None else (kern_i[:, None] * scale[:, :, None, :]).reshape(freqs.size, ns * nk, -1)
    kidx_all = (np.arange(ns)[:, None] * nk + kidx[None, :]).reshape(-1)  # rows: map-major
    bvec = baseline_vectors(array.positions_enu_m, pairs)
    bvec_wl = jnp.asarray(np.tile(bvec, (ns, 1))[None, :, :] * (freqs[:, None, None] / SPEED_OF_LIGHT))
    out = _rings(int(lmax), grid, kr, ki, kidx_all, bvec_wl, np.full(grid.theta.size, grid.weight_sr))
    return jnp.reshape(out, (freqs.size, ns, pairs.shape[0], out.shape[-1]))


def _auto_method(lmax: int) -> str:
    """``response_matrix(method="auto")``'s route: ``"ducc"`` from :data:`RESPONSE_DUCC_MIN_LMAX`
    on where ducc0 imports, else ``"sht"`` from :data:`RESPONSE_SHT_MIN_LMAX` on, else ``"rings"``."""
    if lmax >= RESPONSE_DUCC_MIN_LMAX:
        from .response_ducc import ducc_available

        if ducc_available():
            return "ducc"
    return "sht" if lmax >= RESPONSE_SHT_MIN_LMAX else "rings"


def _checked_inputs(array: AntennaArray, pairs, freqs_hz, lmax: int, method: str, beam_floor: float):
    """``(freqs (Nf,), pairs (Nbl, 2), method)`` of :func:`response_matrix`, checked; ``"auto"`` resolved."""
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    if freqs.ndim != 1 or not np.all(freqs > 0):
        raise ValueError("freqs_hz must be a 1-D array of positive frequencies")
    pairs = np.asarray(pairs, np.int64)
    nant = array.positions_enu_m.shape[0]
    if pairs.ndim != 2 or pairs.shape[1] != 2 or pairs.min() < 0 or pairs.max() >= nant:
        raise ValueError(f"pairs must be (Nbl, 2) antenna indices in [0, {nant}), got shape {pairs.shape}")
    if method not in ("auto", "rings", "direct", "sht", "ducc"):
        raise ValueError(f"method must be 'auto', 'rings', 'direct', 'sht' or 'ducc', got {method!r}")
    if method == "auto":
        method = _auto_method(int(lmax))
    if not (0.0 <= beam_floor < 1.0):
        raise ValueError(f"beam_floor must be in [0, 1), got {beam_floor!r}")
    return freqs, pairs, method


#: Bytes per pixel of the full-sky HEALPix grid while the quadrature grid is built (``pix2ang`` indices and
#: angles, ENU vectors, the above-horizon mask and its index), before the kernels.
GRID_BYTES_PER_PIXEL = 80


def check_response_memory(array: AntennaArray, pairs, freqs, lmax: int, nside: int, pols, copies: int = 2) -> None:
    """Refuse a response (result, accumulator, chunk, kernels, sky grid) larger than the free memory, before
    anything of it is allocated.

    ``copies``: full-size results held at once (2: the result and the accumulator or the
    NumPy buffer JAX copies; 1: the ducc route, whose buffer JAX adopts).
    """
    out_bytes = 16.0 * freqs.size * pairs.shape[0] * n_params(lmax)
    bidx = unique_beams(array.beams)[1]
    nkern = len(set(zip(bidx[pairs[:, 0]].tolist(), bidx[pairs[:, 1]].tolist(), pols or (None,) * len(pairs))))
    npix = 12.0 * int(nside) ** 2  # the grid keeps the pixels above the horizon, about half
    check_memory(  # result, accumulator, chunk, kernels; the grid while it is built
        copies * out_bytes + 16e6 + max(32.0 * freqs.size * nkern * npix / 2, GRID_BYTES_PER_PIXEL * npix),
        f"the response ({freqs.size} freqs x {pairs.shape[0]} baselines x {n_params(lmax)} modes, complex128, on "
        f"the nside {int(nside)} grid of {npix:.3g} pixels)",
        "build only the distinct baselines of a redundant array (gcrsky.redundant_responses) or fewer "
        "frequencies per call",
    )


def _grid_kernels(array: AntennaArray, pairs, freqs, grid: SkyGrid, pols, beam_floor: float):
    """The beam kernels on the grid, once per (beam pair, product): ``(grid, kern_r, kern_i, kidx)``.

    Pixels where every kernel is at most ``beam_floor`` times the peak are dropped from
    the grid; ``kern_r``, ``kern_i``: (Nf, Nk, Npix) real and imaginary parts (``kern_i``
    None for a real kernel); ``kidx``: (Nbl,) kernel of each row.
    """
    kern = baseline_kernels(array.beams, pairs, grid.az_uvbeam, grid.za, freqs, pols)
    K, kidx = kern.kernels, kern.index  # (Nf, Nk, Np), (Nbl,)
    if beam_floor > 0:
        peak = np.max(np.abs(K), axis=(0, 1))  # (Np,)
        keep = peak > beam_floor * peak.max()
        grid = grid._replace(**{f: getattr(grid, f)[keep] for f in ("pix", "theta", "phi", "enu", "az_uvbeam", "za")})
        K = K[:, :, keep]
    kern_r, kern_i = (K, None) if np.isrealobj(K) else (np.ascontiguousarray(K.real), np.ascontiguousarray(K.imag))
    return grid, kern_r, kern_i, kidx


def _direct(lmax: int, chunk: int, grid: SkyGrid, kern_r, kern_i, kidx, bvec_wl, weight_pix) -> jax.Array:
    """The direct quadrature (every basis map on every pixel) in chunks of ``chunk`` pixels."""
    nf = bvec_wl.shape[0]
    npix = grid.theta.size
    nchunk = -(-npix // chunk)
    pad = nchunk * chunk - npix

    def padded(x, axis=0):
        widths = [(0, 0)] * x.ndim
        widths[axis] = (0, pad)
        return np.pad(x, widths)

    def chunked(k):
        if k is None:
            return None
        return jnp.asarray(padded(k, axis=2).reshape(nf, k.shape[1], nchunk, chunk).transpose(2, 0, 1, 3))

    return _quadrature(
        lmax,
        chunk,
        jnp.asarray(padded(grid.theta).reshape(nchunk, chunk)),
        jnp.asarray(padded(grid.phi).reshape(nchunk, chunk)),
        jnp.asarray(padded(grid.enu).reshape(nchunk, chunk, 3)),
        jnp.asarray(padded(weight_pix).reshape(nchunk, chunk)),
        chunked(kern_r),
        chunked(kern_i),
        jnp.asarray(kidx),
        bvec_wl,
    )


def _rings(lmax: int, grid: SkyGrid, kern_r, kern_i, kidx, bvec_wl, weight_pix) -> jax.Array:
    """The ring quadrature over ``grid``'s pixels.

    ``kern_r``, ``kern_i``: (Nf, Nk, Npix) real and imaginary kernels, NumPy or JAX (traced);
    ``kern_i`` None for a real kernel.  ``kidx``: (Nbl,) kernel of each row.
    """
    nf, nbl = bvec_wl.shape[:2]
    slot_bytes = 8 * 6 * nf * nbl  # kernels of one slot in a chunk
    gather, ring_theta = _ring_layout(grid.theta, slot_bytes, 16e6)
    valid = gather >= 0
    g = np.where(valid, gather, 0)
    take = lambda x: np.where(valid.reshape(valid.shape + (1,) * (x.ndim - 1)), x[g], 0.0)  # noqa: E731

    def ringed(k):  # (Nf, Nk, Npix) -> (Nc, Nf, Nk, rc, J)
        if k is None:
            return None
        xp = np if isinstance(k, np.ndarray) else jnp
        return jnp.asarray(xp.moveaxis(xp.where(valid, k[:, :, g], 0.0), (2, 3, 4), (0, 3, 4)))

    return _ring_quadrature(
        int(lmax),
        jnp.asarray(ring_theta),
        jnp.asarray(take(grid.phi)),
        jnp.asarray(take(grid.enu)),
        jnp.asarray(take(weight_pix)),
        ringed(kern_r),
        ringed(kern_i),
        jnp.asarray(kidx),
        bvec_wl,
    )


def analytic_response(
    positions_enu_m,
    latitude_rad: float,
    pairs: np.ndarray,
    freqs_hz,
    lmax: int,
    nside: int,
    beam,
    *,
    lst_ref_rad: float = 0.0,
) -> jax.Array:
    """The response for identical JAX-native beams, differentiable in the beam's parameters.

    The same quadrature as :func:`response_matrix` over every pixel above the horizon
    (no beam floor: which pixels matter depends on the traced width), with the beam
    amplitude computed in JAX by ``beam.amplitude(za, freqs)``
    (:class:`~gcrsky.instrument.JaxGaussianBeam`, :class:`~gcrsky.instrument.JaxAiryBeam`),
    so ``jax.grad`` / ``jax.jvp`` with respect to e.g. ``beam.diameter_m`` work.

    Args:
        positions_enu_m: (Nants, 3) ENU metres.
        latitude_rad: site latitude, radians.
        pairs: (Nbl, 2) antenna pairs.
        freqs_hz: (Nf,) Hz.
        lmax, nside: degree and HEALPix nside (static).
        beam: a JAX beam (one for every antenna).
        lst_ref_rad: the reference angle, radians.

    Returns:
        (Nf, Nbl, (lmax+1)**2) complex, K sr per K; equal to
        ``response_matrix(..., beam_floor=0)`` with ``beam.to_pyuvdata()`` (to rounding).
    """
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    pairs = np.asarray(pairs, np.int64)
    pos = np.asarray(positions_enu_m, np.float64)
    grid = sky_grid(nside, float(latitude_rad), lst_ref_rad)
    amp = beam.amplitude(jnp.asarray(grid.za), jnp.asarray(freqs))[:, None, :]  # (Nf, 1, Np)
    zeros = np.zeros(pairs.shape[0], np.int64)
    bvec_wl = jnp.asarray(baseline_vectors(pos, pairs)[None] * (freqs[:, None, None] / SPEED_OF_LIGHT))
    return _rings(int(lmax), grid, amp * amp, None, zeros, bvec_wl, np.full(grid.theta.size, grid.weight_sr))
