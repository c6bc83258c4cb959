"""A complete inference problem: instrument response, operator, data, noise and prior.

:func:`build_problem` assembles a :class:`Problem` from explicit ingredients in four
steps, each usable on its own:

1. :func:`observation_geometry`: the rotation angles and the frame map (the paper's
   idealised LSTs, or real observing times at a site);
2. :func:`problem_responses`: the cross and auto responses at the reference angle
   (or precomputed ones, shape-checked);
3. :func:`simulate_data`: model visibilities of a truth plus radiometer noise (when
   no data are given);
4. :func:`assemble_problem`: flags to weights, data cleaned under flags, the prior,
   the :class:`Problem`.

A :class:`Problem` is an equinox Module (a PyTree), so it can be passed through
``jax.jit``; its configuration is static metadata.  The paper's standard case and
its :class:`~gcrsky.sim.Config` live in :mod:`gcrsky.sim`.
"""

from __future__ import annotations

import logging
from typing import NamedTuple, Optional

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base.dtypes import require_x64
from ..instrument.antennas import AntennaArray, antpairs
from ..instrument.beams import unique_beams
from ..instrument.response import response_matrix
from ..sphere.frames import FrameMap
from ..sphere.frames import observing_geometry as _times_geometry
from ..sphere.modes import ModeTable, lmax_from_nparams, mode_table, n_params
from .noise import clean_data, draw_noise, inverse_variance, radiometer_sigma, weights_from_flags
from .operator import VisOperator, apply, frame_shape
from .prior import Prior, flat_prior
from .system import LinearSystem, precision_matrix

__all__ = [
    "Geometry",
    "Problem",
    "assemble_problem",
    "build_problem",
    "observation_geometry",
    "problem_responses",
    "simulate_data",
]

log = logging.getLogger(__name__)


class Problem(eqx.Module):
    """Data, noise, prior and operator of one inference problem.

    Array attributes (leading Nf = number of frequencies; n = (lmax+1)**2):
        freqs_hz (Nf,); lsts_rad (Nt,); antpairs (Nbl, 2) with baseline x_j - x_i;
        response (Nf, Nbl, n) complex at ``lst_ref_rad``; auto_response (Nf, Nant, n);
        data (Nf, Nt, Nbl) complex (K sr); sigma (Nf, Nt, Nbl) per-component noise std;
        weights (Nf, Nt, Nbl) in [0, 1]; prior (mean, inv_var (Nf, n));
        a_true (Nf, n) or None; frame: None (parameters are coefficients of the
        co-rotating frame, the paper's idealised LSTs) or the map from the
        parameters' frame (e.g. ICRS) to it (dense (n_resp, n) or a
        :class:`gcrsky.sphere.FrameMap`), with the response at the map's output degree;
        antpos_enu_m (Nant, 3) ENU metres and beam_ids (Nant,) (antennas with the same
        id share one beam object), or None when not recorded; pols: None (every row the
        unpolarised ``A_i A_j`` model of a simulation) or a tuple with the feed product
        each row of ``antpairs`` models (``"xx"``, ``"yy"``, ``"pI"``; I-equivalent
        visibilities: :mod:`gcrsky.ingest.uvdata`); sigma_sky: None, or (Nf, Nt, Nbl) the part of
        ``sigma`` that is sky signal rather than radiometer noise (the sky above lmax marginalised as
        noise, :func:`gcrsky.model.bandlimit.marginalise_rows`), which passes through the antenna
        gains (:mod:`gcrsky.run.gains` scales it with them).
    """

    freqs_hz: jax.Array
    lsts_rad: jax.Array
    antpairs: np.ndarray
    response: jax.Array
    auto_response: jax.Array
    data: jax.Array
    sigma: jax.Array
    weights: jax.Array
    prior: Prior
    a_true: Optional[jax.Array]
    frame: Optional[object]
    lst_ref_rad: float = eqx.field(static=True)
    lmax: int = eqx.field(static=True)
    nside: int = eqx.field(static=True)
    config: Optional[object] = eqx.field(static=True, default=None)
    sky_note: str = eqx.field(static=True, default="")
    antpos_enu_m: Optional[np.ndarray] = None
    beam_ids: Optional[np.ndarray] = None
    pols: Optional[tuple] = eqx.field(static=True, default=None)
    sigma_sky: Optional[jax.Array] = None

    @property
    def n(self) -> int:
        return n_params(self.lmax)

    @property
    def modes(self) -> ModeTable:
        return mode_table(self.lmax)

    def operator(self) -> VisOperator:
        """The visibility operator for this problem's LSTs."""
        return VisOperator(self.response, self.lsts_rad - self.lst_ref_rad, self.frame)

    def system(self) -> LinearSystem:
        """The linear system (operator, data, inverse noise, prior)."""
        iv = self.weights / self.sigma**2
        return LinearSystem(self.operator(), self.data, iv, self.prior)

    def visibilities(self, a) -> jax.Array:
        """Noiseless model visibilities for realified ``a`` (Nf, n): complex (Nf, Nt, Nbl)."""
        return apply(self.operator(), jnp.asarray(a))

    def auto_visibilities(self, a) -> jax.Array:
        """Real auto-correlations ``V_ii`` (Nf, Nt, Nant) of the sky ``a``."""
        return apply(VisOperator(self.auto_response, self.lsts_rad - self.lst_ref_rad, self.frame), jnp.asarray(a)).real

    def precision_matrix(self) -> jax.Array:
        """Dense realified posterior precision P, (Nf, n, n)."""
        return precision_matrix(self.system())


class Geometry(NamedTuple):
    """When and in which frame the sky is observed (:func:`observation_geometry`).

    Attributes:
        lsts_rad: (Nt,) rotation angles (LSTs / local Earth rotation angles), radians.
        frame: None (idealised frame) or the parameters' frame map.
        lmax_response: degree of the response (``lmax``, or the frame map's output).
    """

    lsts_rad: np.ndarray
    frame: Optional[object]
    lmax_response: int


def observation_geometry(
    array: AntennaArray,
    lmax: int,
    *,
    lsts_rad=None,
    frame=None,
    times=None,
    location=None,
    frame_pad: int = 4,
) -> Geometry:
    """The rotation angles and frame map of an observation (DESIGN section 2).

    * idealised (the paper's): ``lsts_rad`` (Nt,) radians; the parameters are
      coefficients of the co-rotating frame (an explicit ``frame`` map, dense
      (n_resp, n) or a :class:`~gcrsky.sphere.FrameMap`, may be added).
    * real observing times: ``times`` (astropy ``Time`` (Nt,)) and ``location``
      (astropy ``EarthLocation``, whose latitude must be the array's).  The
      parameters are then ICRS coefficients at ``lmax``;
      :func:`gcrsky.sphere.observing_geometry` supplies the local Earth rotation
      angles and the fixed ICRS -> CIRS-of-date map, at ``lmax + frame_pad``.
    """
    if times is not None:
        if lsts_rad is not None or frame is not None:
            raise ValueError("give either times (with location) or lsts_rad (with an optional frame), not both")
        if location is None:
            raise ValueError("real observing times need the site: pass location (astropy EarthLocation)")
        geom = _times_geometry(times, location, lmax, pad=frame_pad)
        if abs(geom.latitude_deg - float(np.rad2deg(array.latitude_rad))) > 1e-6:
            raise ValueError(
                f"the array is at latitude {float(np.rad2deg(array.latitude_rad))} deg but location is at "
                f"{geom.latitude_deg} deg; build the array with make_array(..., location latitude, ...)"
            )
        lsts_rad, frame = geom.lsts_rad, geom.frame
    elif location is not None:
        raise ValueError("location is only used with times")
    if lsts_rad is None:
        raise ValueError("give lsts_rad (idealised frame) or times and location (real observing times)")
    lsts = np.atleast_1d(np.asarray(lsts_rad, np.float64))
    lmax_resp = lmax
    if frame is not None:
        if not isinstance(frame, FrameMap):
            frame = jnp.asarray(frame, jnp.float64)
        n_resp, n_frame = frame_shape(frame)
        if n_frame != n_params(lmax):
            raise ValueError(f"frame map takes {n_frame} coefficients, lmax={lmax} has {n_params(lmax)}")
        lmax_resp = lmax_from_nparams(n_resp)
    return Geometry(lsts, frame, int(lmax_resp))


def problem_responses(
    array: AntennaArray,
    freqs_hz,
    lmax_response: int,
    nside: int,
    *,
    lst_ref_rad: float = 0.0,
    responses: tuple | None = None,
) -> tuple[jax.Array, jax.Array]:
    """``(cross, auto)`` responses of every pair ``antpairs(Nant)`` and every antenna.

    Shapes (Nf, Nbl, n_resp) and (Nf, Nant, n_resp), complex, K sr per K
    (:func:`gcrsky.instrument.response_matrix`).  ``responses``: precomputed
    ``(cross, auto)`` for exactly this array, frequencies, degree, nside and
    ``lst_ref_rad`` (shapes are checked, the contents cannot be).
    """
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    nant = array.positions_enu_m.shape[0]
    pairs = antpairs(nant)
    if responses is None:
        resp = response_matrix(array, pairs, freqs, lmax_response, nside, lst_ref_rad=lst_ref_rad)
        auto = response_matrix(
            array, np.stack([np.arange(nant)] * 2, 1), freqs, lmax_response, nside, lst_ref_rad=lst_ref_rad
        )
        return resp, auto
    resp, auto = responses
    want = ((freqs.size, pairs.shape[0], n_params(lmax_response)), (freqs.size, nant, n_params(lmax_response)))
    if (tuple(resp.shape), tuple(auto.shape)) != want:
        raise ValueError(f"precomputed responses have shapes {resp.shape}, {auto.shape}; expected {want}")
    return resp, auto


def simulate_data(
    response,
    auto_response,
    angles,
    frame,
    a_true,
    pairs: np.ndarray,
    *,
    sigma=None,
    dt_s: float = 60.0,
    dnu_hz: float = 1e6,
    noise_scale: float = 1.0,
    key: jax.Array | None = None,
) -> tuple[jax.Array, np.ndarray]:
    """Simulated visibilities ``X a_true + n`` and their per-component noise std.

    Args:
        response, auto_response: (Nf, Nbl, n_resp) and (Nf, Nant, n_resp).
        angles: (Nt,) rotation angles ``lst - lst_ref``, radians.
        frame: the frame map or None.
        a_true: (Nf, n) realified truth, K.
        pairs: (Nbl, 2) antenna pairs of the response rows.
        sigma: per-component noise std (broadcastable to (Nf, Nt, Nbl)); default the
            radiometer equation on the simulated autos,
            ``sigma^2 = V_ii V_jj / (2 dt dnu)``.
        dt_s, dnu_hz: integration time (s) and channel width (Hz).
        noise_scale: factor on the noise *variance*.
        key: PRNG key of the noise (default PRNGKey(0)).

    Returns:
        (data (Nf, Nt, Nbl) complex, sigma (Nf, Nt, Nbl) or broadcastable).
    """
    key = jax.random.PRNGKey(0) if key is None else key
    angles = jnp.asarray(angles)
    if sigma is None:
        autos = np.asarray(apply(VisOperator(auto_response, angles, frame), a_true).real)  # (Nf, Nt, Nant)
        sigma = radiometer_sigma(autos[:, :, pairs[:, 0]], autos[:, :, pairs[:, 1]], dt_s, dnu_hz)
    model = apply(VisOperator(response, angles, frame), a_true)
    # a scalar or broadcastable sigma still means independent noise in every sample
    sigma = np.broadcast_to(np.asarray(sigma, np.float64) * np.sqrt(noise_scale), model.shape)
    return model + draw_noise(key, jnp.asarray(sigma)), sigma


def assemble_problem(
    array: AntennaArray,
    freqs_hz,
    geometry: Geometry,
    responses: tuple,
    lmax: int,
    nside: int,
    data,
    sigma,
    *,
    a_true=None,
    weights=None,
    flags=None,
    prior: Prior | None = None,
    lst_ref_rad: float = 0.0,
    config=None,
    sky_note: str = "",
    pairs=None,
    pols=None,
) -> Problem:
    """The :class:`Problem` from its parts: weights from flags, data cleaned, prior checked.

    Flags: ``flags`` (bool, True = bad, broadcastable to (Nf, Nt, Nbl)) and/or
    ``weights`` (in [0, 1]) set the per-sample weights (0 under a flag); flagged data
    may hold anything, NaN and Inf included, and are stored as 0; an unflagged
    non-finite sample is an error naming its (freq, time, baseline) and antennas.
    The prior defaults to flat.  ``pairs`` (Nbl, 2): the antenna pairs of the rows
    (default every ``i < j``); ``pols``: the feed product of each row (see
    :class:`Problem`).
    """
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    nant = array.positions_enu_m.shape[0]
    pairs = antpairs(nant) if pairs is None else np.asarray(pairs, np.int64)
    if pols is not None:
        pols = tuple(str(p) for p in pols)
        if len(pols) != pairs.shape[0]:
            raise ValueError(f"pols names {len(pols)} rows but there are {pairs.shape[0]} pairs")
    n = n_params(lmax)
    shape = (freqs.size, geometry.lsts_rad.size, pairs.shape[0])
    data = np.asarray(data)
    if data.shape != shape:
        raise ValueError(f"data have shape {data.shape}, expected (Nf, Nt, Nbl) = {shape}")
    sigma = np.broadcast_to(np.asarray(sigma, np.float64), shape)
    if flags is not None:
        w = weights_from_flags(flags, weights, shape=shape)
    elif weights is None:
        w = np.ones(shape)
    else:
        w = weights_from_flags(np.zeros((), bool), weights, shape=shape)
    iv = inverse_variance(sigma, w)
    data = clean_data(data, iv, antpairs=pairs)
    if prior is None:
        prior = flat_prior(freqs.size, n)
    if prior.mean.shape != (freqs.size, n) or prior.inv_var.shape != (freqs.size, n):
        raise ValueError(f"prior arrays must be (Nf, n) = {(freqs.size, n)}")
    resp, auto = responses
    return Problem(
        freqs_hz=jnp.asarray(freqs),
        lsts_rad=jnp.asarray(geometry.lsts_rad),
        antpairs=pairs,
        response=resp,
        auto_response=auto,
        data=jnp.asarray(data, jnp.complex128),
        sigma=jnp.asarray(sigma),
        weights=jnp.asarray(w),
        prior=Prior(jnp.asarray(prior.mean, jnp.float64), jnp.asarray(prior.inv_var, jnp.float64)),
        a_true=a_true,
        frame=geometry.frame,
        lst_ref_rad=float(lst_ref_rad),
        lmax=int(lmax),
        nside=int(nside),
        config=config,
        sky_note=sky_note,
        antpos_enu_m=np.array(array.positions_enu_m, np.float64),
        beam_ids=unique_beams(array.beams)[1],
        pols=pols,
    )


def build_problem(
    array: AntennaArray,
    freqs_hz,
    lsts_rad,
    lmax: int,
    nside: int,
    *,
    a_true=None,
    data=None,
    sigma=None,
    weights=None,
    flags=None,
    prior: Prior | None = None,
    dt_s: float = 60.0,
    dnu_hz: float = 1e6,
    noise_scale: float = 1.0,
    key: jax.Array | None = None,
    lst_ref_rad: float = 0.0,
    frame=None,
    times=None,
    location=None,
    frame_pad: int = 4,
    responses: tuple | None = None,
    config=None,
    sky_note: str = "",
) -> Problem:
    """Assemble a :class:`Problem`: the four steps of this module in order.

    Either give ``data`` (Nf, Nt, Nbl) complex with ``sigma`` (per-component std), or
    give ``a_true`` (Nf, n) to simulate: model visibilities plus radiometer noise
    whose sigma comes from the simulated autos (``sigma^2 = V_ii V_jj / (2 dt dnu)``,
    times ``noise_scale``), drawn with ``key`` (:func:`simulate_data`).  Given data
    keep their ``sigma`` times ``sqrt(noise_scale)``.

    Frames (:func:`observation_geometry`): ``lsts_rad`` (Nt,) radians for the
    paper's idealised co-rotating frame (optionally with a ``frame`` map), or
    ``lsts_rad=None`` with ``times`` and ``location`` for real observing times (the
    parameters, ``a_true`` and the prior are then ICRS coefficients at ``lmax``; the
    response is built at ``lmax + frame_pad``).

    ``responses``: optional precomputed ``(cross, auto)`` responses
    (:func:`problem_responses`).  Flags, weights and the prior:
    :func:`assemble_problem`.  ``config`` and ``sky_note`` are stored as static
    metadata (e.g. a :class:`gcrsky.sim.Config`).
    """
    require_x64("build_problem")
    freqs = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    geom = observation_geometry(array, lmax, lsts_rad=lsts_rad, frame=frame, times=times, location=location,
                                frame_pad=frame_pad)
    resp, auto = problem_responses(array, freqs, geom.lmax_response, nside, lst_ref_rad=lst_ref_rad,
                                   responses=responses)
    n = n_params(lmax)
    if a_true is not None:
        a_true = jnp.asarray(a_true, jnp.float64)
        if a_true.shape != (freqs.size, n):
            raise ValueError(f"a_true has shape {a_true.shape}, expected {(freqs.size, n)}")
    if data is None:
        if a_true is None:
            raise ValueError("give either data (with sigma) or a_true to simulate from")
        pairs = antpairs(array.positions_enu_m.shape[0])
        data, sigma = simulate_data(resp, auto, geom.lsts_rad - lst_ref_rad, geom.frame, a_true, pairs, sigma=sigma,
                                    dt_s=dt_s, dnu_hz=dnu_hz, noise_scale=noise_scale, key=key)
    else:
        if sigma is None:
            raise ValueError("real data need their per-component noise sigma")
        sigma = np.asarray(sigma, np.float64) * np.sqrt(noise_scale)
    return assemble_problem(array, freqs, geom, (resp, auto), lmax, nside, data, sigma, a_true=a_true,
                            weights=weights, flags=flags, prior=prior, lst_ref_rad=lst_ref_rad, config=config,
                            sky_note=sky_note)
