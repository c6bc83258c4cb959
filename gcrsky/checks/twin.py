"""A twin of a real observation: matvis visibilities of a sky that is *not* the prior's, uncalibrated.

:func:`make_twin` takes a real visibility file (the template: HERA H1C's
``zen.2458098.45361.HH_downselected.uvh5`` in the tests) for everything but the data: its
data antennas (numbers, names, ENU positions), site, observing times, integration
time and channel width, and a choice of its channels.  It then writes what such a file
would hold for a known sky and a known calibration error:

``V_ij,pp(nu, t) = q(nu) g_i,p(nu, t) conj(g_j,p(nu, t)) [V^sky_ij,pp(nu, t) + n_ij,pp]``

* ``V^sky``: matvis (:func:`gcrsky.checks.uvsim.simulate_uvdata`: polarised, every pair and
  the autos, feed products ``xx``/``yy``, Jy, pol_convention "sum") of the twin sky
  (:func:`twin_sky`) through zenith-pointed Gaussian dishes, pyuvdata's
  ``GaussianBeam(diameter=D)`` (:func:`gcrsky.instrument.beams.gaussian_beam`, the beam
  ``gcrsky run --dish-diameter D`` builds; D = 14 m by default);
* ``n``: radiometer noise from the simulated autos, ``sigma^2 = V_ii V_jj / (2 dt dnu)``
  with the template's ``dt`` and ``dnu`` (autos noiseless);
* ``g``: per-antenna, per-feed gains smooth in frequency and slow in time
  (:func:`gcrsky.checks.gainsim.corrupt_with_gains`: 5 % rms amplitude, 5 deg rms phase,
  2 x 2 Legendre modes by default).  They multiply the *noisy* visibilities, as a receiver's
  gain follows its noise (gainsim's module docstring): the file's autos then predict its
  noise exactly;
* ``q``: the overall amplitude, a bandpass with a slope,
  ``q(nu) = amplitude (1 + slope (nu - nu0) / bandwidth)`` (``nu0`` the centre and
  ``bandwidth`` the span of the chosen channels; 0.003 and -0.3 by default: 0.00345 at the
  lowest channel to 0.00255 at the highest), applied as a common ``|g|^2``, noise and all.
  Convention: the data are ``q`` x the visibilities in calibrated units (Jy) (gains apart), so
  ``data / q`` is calibrated: ``q`` is what issue 38's ``"flux_scale"`` block reports.

The file says ``vis_units = "uncalib"`` and has no pol_convention (as the template; gcrsky
then reads "sum", which is what the simulation is).  :class:`Twin` carries the truth: ``q``
per channel, the gains, a UVCal of ``g sqrt(q)`` with which ``pyuvdata.utils.uvcalibrate``
gives back the Jy visibilities, and the sky's realified ICRS coefficients beside the GSM prior
mean it departs from.

The twin sky (:func:`twin_sky`) differs from the prior mean ``gcrsky run --prior-mean gsm``
uses (:func:`gcrsky.model.skyprior.gsm_prior_mean`: the GSM map's coefficients, l <= 16), as
the real sky differs from the GSM: brighter by ``boost`` (5 %) and modulated on large scales
by ``1 + modulation M`` (``M`` a random dipole + quadrupole field of unit rms over the sphere,
``modulation`` 5 %), with small-scale structure beyond the GSM map's resolution (20 % rms,
scaling with the local brightness) up to a degree ``lmax_sky`` above a run's.

Cost (2 shared CPU cores, 8 antennas, 10 times, 4 channels): matvis dominates; ~3-6 s at
``lmax_sky`` 64 / ``nside_matvis`` 64 (``tests/test_twin.py``), ~10 s at the defaults 256 / 128
(25 s under load; 55 s at 600 / 256).  matvis at nside 128 agrees with nside 256 on the sky to
l = 256 to 2e-4 of the noise sigma (rms; 1e-3 at most; 1e-5 of the visibilities' norm).
Command line: ``python -m gcrsky.checks.twin TEMPLATE.uvh5 OUT.uvh5 [--channels ...]``
(:func:`main`).
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

__all__ = [
    "DEFAULT_CHANNELS", "Twin", "TwinSky", "autos_against_the_prior_mean", "bandpass", "change_lmax", "make_twin",
    "twin_sky",
]

#: Channel indices of the H1C template the twin takes by default: 120.3, 140.6, 159.4 and 179.7 MHz, spread
#: over 120-180 MHz and clear of the template's RFI channels (index 4, FM at 106.25 MHz; index 24, ORBCOMM at
#: 137.5 MHz: ``shared/data/real/README.md``).
DEFAULT_CHANNELS = (13, 26, 38, 51)

#: The GSM map's degrees: the prior mean's (:data:`gcrsky.model.skyprior.GSM_MEAN_LMAX`).
_GSM_L = 16


class TwinSky(NamedTuple):
    """The twin's sky, realified ICRS coefficients (:mod:`gcrsky.sphere.modes`), Stokes I in K.

    Attributes:
        alm: (Nf, (lmax+1)^2) the sky simulated:
            ``(1 + boost) (1 + modulation M(n)) T_base(n)``, exactly (harmonic product on a
            Gauss-Legendre grid, band-limited at ``lmax``).
        base: (Nf, (lmax+1)^2) ``T_base``: the GSM prior mean (l <= 16) plus the small scales
            (16 < l <= lmax - modulation_lmax; 0 above).
        prior_mean: (Nf, (lmax+1)^2) the GSM prior mean alone
            (:func:`gcrsky.model.skyprior.gsm_prior_mean` at ``lmax``: 0 above l = 16).
        modulation_alm: ((modulation_lmax+1)^2,) the field ``M`` (no monopole, unit rms over the
            sphere), dimensionless.
        freqs_hz: (Nf,) Hz.
        lmax: degree of ``alm``.
        boost, modulation: the factors above.
        note: the construction in words.
    """

    alm: np.ndarray
    base: np.ndarray
    prior_mean: np.ndarray
    modulation_alm: np.ndarray
    freqs_hz: np.ndarray
    lmax: int
    boost: float
    modulation: float
    note: str

    def at(self, lmax: int) -> np.ndarray:
        """The sky's coefficients at a run's degree: (Nf, (lmax+1)^2), truncated (or zero-padded), what a
        run's ``Problem.a_true`` would hold."""
        return change_lmax(self.alm, self.lmax, lmax)


class Twin(NamedTuple):
    """What :func:`make_twin` returns.

    Attributes:
        uvdata: the pyuvdata ``UVData`` (``vis_units`` "uncalib", pols xx/yy, no flags).
        path: the UVH5 file written, or None.
        channels: (Nf,) indices of the template's channels taken.
        freqs_hz: (Nf,) their frequencies, Hz.
        amplitude: (Nf,) the true ``q`` per channel (data = q x calibrated Jy visibilities).
        gains: (Nant, Nf, Nt, 2) complex per-antenna gains (feeds x, y), pyuvdata's
            ``gain_array`` layout, antennas in ``uvcal``'s ``ant_array`` order; without ``q``.
        uvcal: pyuvdata ``UVCal`` of ``g sqrt(q)`` (``gain_convention`` "divide", ``gain_scale``
            "Jy", pol_convention "sum"): ``uvcalibrate(uvdata, uvcal)`` gives the Jy visibilities.
        sky: the :class:`TwinSky` simulated.
        model: (Nblts, Nf, 2) complex noiseless visibilities as written (with ``q`` and gains).
        sigma: (Nblts, Nf, 2) the per-component noise std of ``uvdata`` (``q |g_i g_j|`` x the
            radiometer sigma; 0 for autos).
        reach: the reach of the longest baseline at the highest channel
            (:func:`gcrsky.checks.hera_sim.reach_lmax`): the lmax a run with ``--dish-diameter``
            chooses by default.
        settings: the simulation's settings (JSON-friendly), timings in ``"seconds"``.
    """

    uvdata: object
    path: Path | None
    channels: np.ndarray
    freqs_hz: np.ndarray
    amplitude: np.ndarray
    gains: np.ndarray
    uvcal: object
    sky: TwinSky
    model: np.ndarray
    sigma: np.ndarray
    reach: int
    settings: dict


def change_lmax(a, lmax_in: int, lmax_out: int) -> np.ndarray:
    """Realified coefficients ``(..., (lmax_in+1)^2)`` at another degree: truncated, or zero-padded.

    Returns:
        (..., (lmax_out+1)^2) float64; the entries with ``l <= min(lmax_in, lmax_out)`` kept.
    """
    from ..sphere.modes import mode_table

    a = np.asarray(a, np.float64)
    if a.shape[-1] != (lmax_in + 1) ** 2:
        raise ValueError(f"a has last axis {a.shape[-1]}, not (lmax_in + 1)^2 = {(lmax_in + 1) ** 2}")
    lo, hi = min(lmax_in, lmax_out), max(lmax_in, lmax_out)
    idx = np.flatnonzero(mode_table(hi).ell <= lo)  # the low layout inside the high one, in order
    if lmax_out <= lmax_in:
        return a[..., idx].copy()
    out = np.zeros(a.shape[:-1] + ((lmax_out + 1) ** 2,))
    out[..., idx] = a
    return out


def bandpass(freqs_hz, amplitude: float = 0.003, slope: float = -0.3) -> np.ndarray:
    """``q(nu) = amplitude (1 + slope (nu - nu0) / bandwidth)``: (Nf,), ``nu0`` the centre and
    ``bandwidth`` the span of ``freqs_hz`` (one channel: ``amplitude``).

    Raises:
        ValueError: a non-positive ``q`` at some channel.
    """
    f = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    span = f.max() - f.min()
    u = np.zeros_like(f) if span == 0 else (f - 0.5 * (f.max() + f.min())) / span
    q = amplitude * (1.0 + slope * u)
    if not np.all(q > 0):
        raise ValueError(f"the bandpass q = {amplitude} (1 + {slope} (nu - nu0) / bandwidth) is not positive: {q}")
    return q


def _unit_rms_field(lmax: int, lmin: int, slope: float, rng) -> np.ndarray:
    """Realified coefficients of a Gaussian field with ``C_l ~ l^slope`` at ``lmin <= l <= lmax``, scaled to unit
    rms over the sphere (the realisation's, exactly)."""
    from ..sphere.modes import mode_table

    tab = mode_table(lmax)
    ell = np.maximum(tab.ell, 1).astype(np.float64)
    sd = np.sqrt(ell**slope * np.where(tab.m == 0, 1.0, 0.5))  # Var(a_l0) = C_l, Var(Re a_lm) = Var(Im a_lm) = C_l / 2
    a = np.where(tab.ell >= lmin, sd * rng.standard_normal(tab.ell.size), 0.0)
    # int I^2 dOmega = sum_{m=0} a^2 + 2 sum_{m>0} (Re^2 + Im^2) for the realified vector
    power = np.sum(np.where(tab.m == 0, 1.0, 2.0) * a**2) / (4.0 * np.pi)
    return a / np.sqrt(power)


class _GLGrid:
    """Spin-0 transforms on one Gauss-Legendre grid (ducc0) of ``lmax + 1`` rings and ``2 lmax + 2`` longitudes.

    The grid integrates every polynomial of degree <= 2 lmax + 1 exactly, so the analysis of a
    product of fields whose degrees add up to at most ``lmax`` is exact to rounding.
    """

    def __init__(self, lmax: int):
        self.lmax, self.shape = lmax, (lmax + 1, 2 * lmax + 2)

    def synth(self, a, lmax: int) -> np.ndarray:
        import ducc0

        from ..sphere.modes import unrealify

        alm = np.ascontiguousarray(unrealify(np.asarray(a, np.float64), lmax), np.complex128)[None, :]
        return ducc0.sht.synthesis_2d(alm=alm, spin=0, lmax=lmax, geometry="GL", ntheta=self.shape[0],
                                      nphi=self.shape[1])[0]

    def analyse(self, m: np.ndarray, lmax: int) -> np.ndarray:
        import ducc0

        from ..sphere.modes import realify

        alm = ducc0.sht.analysis_2d(map=np.ascontiguousarray(m, np.float64)[None], spin=0, lmax=lmax, geometry="GL")
        return np.asarray(realify(np.asarray(alm[0], np.complex128), lmax), np.float64)


def twin_sky(freqs_hz, lmax: int, *, boost: float = 0.05, modulation: float = 0.05, modulation_lmax: int = 2,
             small_scale: float = 0.2, small_scale_slope: float = -2.5, small_scale_kind: str = "brightness",
             seed: int = 0) -> TwinSky:
    """The twin's sky: the GSM prior mean with small scales added, brighter and modulated on large scales.

    ``T(n, nu) = (1 + boost) (1 + modulation M(n)) T_base(n, nu)``, ``T_base = T_gsm + [T_gsm delta]_{l > 16}``:

    * ``T_gsm``: the GSM prior mean (:func:`gcrsky.model.skyprior.gsm_prior_mean`: the GSM
      map's coefficients at l <= 16, exactly what ``--prior-mean gsm`` uses);
    * ``delta``: a Gaussian field at ``17 <= l <= lmax - modulation_lmax - 16`` with
      ``C_l ~ l^small_scale_slope`` (-2.5: the diffuse synchrotron sky's slope), scaled to rms
      ``small_scale`` over the sphere (0.2), the same at every frequency: small-scale structure
      that scales with the local brightness (bright where the Galaxy is, and positive: the
      sky stays positive where ``delta > -1``), with the GSM's spectrum.  Its product with
      ``T_gsm`` is kept above l = 16 only, so that ``T_base`` *is* the prior mean at l <= 16.
      (The prior's own C_l beyond l = 16, :func:`gcrsky.model.skyprior.gsm_cl`, has about the
      same total power, ~0.2 x the rms brightness at l = 17-190; an isotropic Gaussian field of
      that power would make 2-4 % of the sky negative.)  Skipped where the degrees leave no
      room (``lmax - modulation_lmax < 33``) or ``small_scale`` is 0.  ``small_scale_kind``
      ``"isotropic"`` instead adds one draw from that prior C_l at ``16 < l <= lmax -
      modulation_lmax`` (the same unit normals at every frequency; ``small_scale`` then only
      switches it on): small scales the prior's covariance describes exactly, as bright off
      the Galactic plane as on it (and 2-4 % of the sky negative);
    * ``M``: a random field at ``1 <= l <= modulation_lmax`` (dipole + quadrupole by default;
      equal power per degree), no monopole, unit rms over the sphere, the same at every
      frequency.

    Every product is taken on a Gauss-Legendre grid exact for its degrees (band-limited at
    ``lmax``): no aliasing.  With ``modulation`` 0 ``T_base`` reaches ``lmax``; with ``boost``
    and ``modulation`` both 0 the coefficients at l <= 16 are the prior mean's, bit for bit.
    Over the sphere the mean of ``T / T_base`` is ``1 + boost`` (``M`` has no monopole); the
    sky's mean brightness is ``(1 + boost) (1 + modulation <M T_base> / <T_base>)`` x the
    GSM's (the modulation correlates with the Galaxy).

    Args:
        freqs_hz: (Nf,) Hz, 30-250 MHz (the GSM maps').
        lmax: degree of the sky (>= 16 + ``modulation_lmax``).
        boost: fractional brightening, > -1.
        modulation: rms of ``modulation M`` (keep it well below 1: the sky stays positive).
        modulation_lmax: highest degree of ``M`` (>= 1).
        small_scale, small_scale_slope: rms and C_l slope of ``delta``.
        small_scale_kind: ``"brightness"`` (``delta``, above) or ``"isotropic"`` (the prior's C_l).
        seed: NumPy ``default_rng`` seed of ``M`` and ``delta``.

    Returns:
        :class:`TwinSky`.
    """
    from ..model.skyprior import gsm_prior_mean
    from ..sphere.modes import mode_table

    f = np.atleast_1d(np.asarray(freqs_hz, np.float64))
    lmax, modulation_lmax = int(lmax), int(modulation_lmax)
    if modulation_lmax < 1:
        raise ValueError(f"modulation_lmax must be at least 1, got {modulation_lmax}")
    if lmax < _GSM_L + modulation_lmax:
        raise ValueError(f"lmax must be at least {_GSM_L} + modulation_lmax = {_GSM_L + modulation_lmax}, got {lmax}")
    if not boost > -1:
        raise ValueError(f"boost must be > -1, got {boost}")
    if not small_scale >= 0:
        raise ValueError(f"small_scale must be >= 0, got {small_scale}")
    if small_scale_kind not in ("brightness", "isotropic"):
        raise ValueError(f"small_scale_kind must be 'brightness' or 'isotropic', got {small_scale_kind!r}")
    rng = np.random.default_rng(seed)
    mfield = _unit_rms_field(modulation_lmax, 1, 0.0, rng)
    grid = _GLGrid(lmax)
    lb = lmax - modulation_lmax if modulation else lmax
    ld = lb - _GSM_L
    base = gsm_prior_mean(f, lb)
    note = f"(1 + {boost:g}) x (1 + {modulation:g} M) x [GSM prior mean (l <= {_GSM_L})"
    if small_scale and small_scale_kind == "isotropic" and lb > _GSM_L:
        from ..model.prior import isotropic_prior
        from ..model.skyprior import gsm_cl

        sd = 1.0 / np.sqrt(isotropic_prior(gsm_cl(f, lb), (lb + 1) ** 2).inv_var)  # (Nf, n): sqrt(C_l [/ 2])
        z = np.where(mode_table(lb).ell > _GSM_L, rng.standard_normal((lb + 1) ** 2), 0.0)
        base = base + sd * z[None, :]
        note += f" + a draw from the prior's C_l (gsm_cl) at {_GSM_L} < l <= {lb}"
    elif small_scale and ld > _GSM_L:
        delta = small_scale * _unit_rms_field(ld, _GSM_L + 1, small_scale_slope, rng)
        dmap = grid.synth(delta, ld)
        high = mode_table(lb).ell > _GSM_L
        for k in range(f.size):
            prod = grid.analyse(grid.synth(change_lmax(base[k], lb, _GSM_L), _GSM_L) * dmap, lb)
            base[k] = base[k] + np.where(high, prod, 0.0)
        note += (f" + [its product with delta]_(l > {_GSM_L}), delta a Gaussian field at {_GSM_L + 1} <= l <= {ld}, "
                 f"C_l ~ l^{small_scale_slope:g}, rms {small_scale:g}")
    note += f"]; M a random l = 1..{modulation_lmax} field of unit rms; seed {seed}"
    if modulation:
        fmap = (1.0 + boost) * (1.0 + modulation * grid.synth(mfield, modulation_lmax))
        alm = np.stack([grid.analyse(grid.synth(b, lb) * fmap, lmax) for b in base])
    else:
        alm = (1.0 + boost) * base
    return TwinSky(alm=alm, base=change_lmax(base, lb, lmax), prior_mean=gsm_prior_mean(f, lmax),
                   modulation_alm=mfield, freqs_hz=f, lmax=lmax, boost=float(boost), modulation=float(modulation),
                   note=note)


def _template(template):
    """The template's metadata: a UVData (data not needed) from a path or a UVData."""
    from pyuvdata import UVData

    if isinstance(template, UVData):
        return template
    return UVData.from_file(str(template), read_data=False)


def make_twin(template, out=None, *, channels=DEFAULT_CHANNELS, lmax_sky: int = 256, nside_matvis: int = 128,
              boost: float = 0.05, modulation: float = 0.05, small_scale: float = 0.2,
              small_scale_kind: str = "brightness", amplitude: float = 0.003,
              slope: float = -0.3, gain_amp: float = 0.05, gain_phase_deg: float = 5.0, dish_diameter_m: float = 14.0,
              noise: bool = True, sky_seed: int = 0, gain_seed: int = 0, noise_seed: int = 0,
              overwrite: bool = False, beams=None) -> Twin:
    """A twin of ``template``: matvis visibilities of :func:`twin_sky` with gains, a bandpass and noise.

    The model is the module docstring's.  Defaults: 4 channels over 120-180 MHz
    (:data:`DEFAULT_CHANNELS`), a sky to l = 256 (beyond the reach of H1C's longest baseline at
    180 MHz, 223, the lmax a default run takes: above it the data see nothing; runs at lower
    lmax see a sky far beyond theirs), matvis at nside 128, 5 % boost and 5 % modulation,
    q = 0.003 with slope -0.3, 5 % / 5 deg gains, 14 m dish.

    Args:
        template: path of a visibility file pyuvdata reads, or a ``UVData``: its data antennas,
            site, unique times, integration time and channel width are used, not its data.
        out: UVH5 path to write, or None.
        channels: indices into the template's channels.
        lmax_sky, nside_matvis: degree of the sky and HEALPix nside of matvis' pixel sky.
        boost, modulation, small_scale, small_scale_kind: :func:`twin_sky`'s (with ``sky_seed``).
        amplitude, slope: :func:`bandpass`'s ``q``; 1 and 0 for data in Jy (``vis_units`` still
            "uncalib").
        gain_amp, gain_phase_deg: rms fractional amplitude and phase (degrees) of the gains
            (:func:`gcrsky.checks.gainsim.smooth_gains`, 2 x 2 Legendre modes, ``gain_seed``);
            0 and 0: unit gains.
        dish_diameter_m: the Gaussian dish.
        noise: add radiometer noise (``noise_seed``).
        overwrite: replace an existing ``out``.
        beams: None (every antenna the Gaussian dish), or one pyuvdata beam per data antenna of the
            template, in its ``get_enu_data_ants`` order (e.g. :func:`gcrsky.checks.beamsim.scattered_beams`'
            dishes, each its own: a non-redundant array).

    Returns:
        :class:`Twin`.
    """
    import time

    from astropy.time import Time
    from pyuvdata import UVCal

    from ..instrument.beams import gaussian_beam
    from .gainsim import corrupt_with_gains
    from .hera_sim import reach_lmax
    from .uvsim import simulate_uvdata

    t0 = time.perf_counter()
    seconds = {}
    tpl = _template(template)
    chans = np.atleast_1d(np.asarray(channels, np.int64))
    all_freqs = np.asarray(tpl.freq_array, np.float64).reshape(-1)
    if chans.size == 0 or np.any(chans < 0) or np.any(chans >= all_freqs.size) or np.unique(chans).size != chans.size:
        raise ValueError(f"channels must be distinct indices into the template's {all_freqs.size} channels, "
                         f"got {chans.tolist()}")
    chans = np.sort(chans)
    freqs = all_freqs[chans]
    widths = np.broadcast_to(np.asarray(tpl.channel_width, np.float64).reshape(-1), all_freqs.shape)[chans]
    if not np.allclose(widths, widths[0], rtol=1e-9):
        raise ValueError(f"the chosen channels have different widths {widths}: one width is simulated")
    dt = float(np.median(tpl.integration_time))
    pos, numbers = tpl.get_enu_data_ants()
    numbers = np.asarray(numbers, np.int64)
    names = dict(zip(np.asarray(tpl.telescope.antenna_numbers).tolist(), tpl.telescope.antenna_names))
    times = Time(np.unique(tpl.time_array), format="jd", scale="utc")
    location = tpl.telescope.location

    sky = twin_sky(freqs, lmax_sky, boost=boost, modulation=modulation, small_scale=small_scale,
                   small_scale_kind=small_scale_kind, seed=sky_seed)
    seconds["sky"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    if beams is not None and len(beams) != numbers.size:
        raise ValueError(f"beams: {len(beams)} beams for the template's {numbers.size} data antennas")
    sim = simulate_uvdata(pos, location, times, freqs, gaussian_beam(dish_diameter_m) if beams is None else list(beams),
                          sky.alm, lmax_sky, beam_idx=None if beams is None else np.arange(numbers.size),
                          nside_matvis=nside_matvis, pols=("xx", "yy"), vis_units="Jy", pol_convention="sum", dt_s=dt,
                          dnu_hz=float(widths[0]), noise_seed=noise_seed if noise else None, antenna_numbers=numbers)
    seconds["matvis"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    sim.uvdata.telescope.name = tpl.telescope.name
    sim.uvdata.telescope.antenna_names = np.asarray([names[int(n)] for n in sim.uvdata.telescope.antenna_numbers])
    sim.uvdata.telescope.antenna_diameters = np.full(numbers.size, float(dish_diameter_m))
    cor, cal = corrupt_with_gains(sim.uvdata, amp=gain_amp, phase_deg=gain_phase_deg, seed=gain_seed)
    q = bandpass(freqs, amplitude, slope)
    # the noiseless model and the noise std through the same gains and q
    ratio = np.divide(cor.data_array, sim.uvdata.data_array, out=np.ones_like(cor.data_array),
                      where=sim.uvdata.data_array != 0) * q[None, :, None]
    model, sigma = sim.model * ratio, sim.sigma * np.abs(ratio)
    uvd = cor
    uvd.data_array = cor.data_array * q[None, :, None]
    uvd.vis_units = "uncalib"
    uvd.pol_convention = None
    uvd.history += (f"\ngcrsky.checks.twin: a twin of {tpl.telescope.name} data (channels {chans.tolist()}): "
                    f"{sky.note}; bandpass q = {amplitude:g} (1 + {slope:g} (nu - nu0)/bandwidth); "
                    f"{dish_diameter_m:g} m Gaussian dish; vis_units uncalib")
    uvd.check()

    full = UVCal.initialize_from_uvdata(sim.uvdata, gain_convention="divide", cal_style="sky", metadata_only=True,
                                        jones_array=np.array([-5, -6]), time_array=np.unique(sim.uvdata.time_array),
                                        ant_array=np.asarray(cal.ant_array), ref_antenna_name="none (true gains)",
                                        sky_catalog="gcrsky.checks.twin: the true gains x sqrt(q)")
    full.gain_array = cal.gain_array * np.sqrt(q)[None, :, None, None]
    full.gain_scale = "Jy"
    full.pol_convention = "sum"
    full.flag_array = np.zeros(full.gain_array.shape, bool)
    full.quality_array = np.zeros(full.gain_array.shape)
    full.check()
    seconds["corrupt"] = time.perf_counter() - t1

    path = None
    if out is not None:
        t1 = time.perf_counter()
        path = Path(out)
        uvd.write_uvh5(str(path), clobber=overwrite)
        seconds["write"] = time.perf_counter() - t1
    seconds["total"] = time.perf_counter() - t0
    reach = reach_lmax(pos, float(freqs.max()), dish_diameter_m)
    settings = dict(template=str(template) if not hasattr(template, "data_array") else "a UVData",
                    channels=chans.tolist(), freqs_hz=freqs.tolist(), lmax_sky=int(lmax_sky),
                    nside_matvis=int(nside_matvis), boost=float(boost), modulation=float(modulation),
                    small_scale=float(small_scale), small_scale_kind=small_scale_kind, amplitude=float(amplitude),
                    slope=float(slope),
                    gain_amp=float(gain_amp), gain_phase_deg=float(gain_phase_deg),
                    dish_diameter_m=float(dish_diameter_m), noise=bool(noise), sky_seed=int(sky_seed),
                    gain_seed=int(gain_seed), noise_seed=int(noise_seed), dt_s=dt,
                    beams="nominal" if beams is None else f"{len(beams)} per antenna", dnu_hz=float(widths[0]),
                    reach=int(reach), sky=sky.note, seconds=seconds)
    return Twin(uvdata=uvd, path=path, channels=chans, freqs_hz=freqs, amplitude=q, gains=np.asarray(cal.gain_array),
                uvcal=full, sky=sky, model=model, sigma=sigma, reach=int(reach), settings=settings)


def autos_against_the_prior_mean(twin: Twin, *, nside_matvis: int | None = None) -> np.ndarray:
    """Per channel, the twin's calibrated autos over matvis' autos of the GSM prior mean: (Nf,).

    The truth an autos' flux-scale check can be held to: the prior-mean sky
    (:attr:`TwinSky.prior_mean`, l <= 16) simulated by matvis for the same antennas, times and
    beam (no noise), and the twin's noiseless autos with ``q |g_i|^2`` divided out; the median
    over antennas, times and both feeds of their ratio.  Near ``1 + boost`` (the modulation and
    the small scales inside the beam move it by a few per cent: 1.044 to 1.029 over the default
    channels at the defaults, 1.066 to 1.121 with the sky to l = 64); ``q`` x this is what the
    uncalibrated file's autos say against that sky.

    Args:
        twin: :func:`make_twin`'s result.
        nside_matvis: matvis' nside for the prior mean (default: the twin's).
    """
    from astropy.time import Time

    from ..instrument.beams import gaussian_beam
    from .uvsim import simulate_uvdata

    uvd, st = twin.uvdata, twin.settings
    pos, numbers = uvd.get_enu_data_ants()
    sim = simulate_uvdata(pos, uvd.telescope.location, Time(np.unique(uvd.time_array), format="jd", scale="utc"),
                          twin.freqs_hz, gaussian_beam(st["dish_diameter_m"]),
                          change_lmax(twin.sky.prior_mean, twin.sky.lmax, _GSM_L), _GSM_L,
                          nside_matvis=int(nside_matvis or st["nside_matvis"]), pols=("xx", "yy"), dt_s=st["dt_s"],
                          dnu_hz=st["dnu_hz"], noise_seed=None, antenna_numbers=np.asarray(numbers, np.int64))
    ref = sim.uvdata
    row = {int(a): k for k, a in enumerate(twin.uvcal.ant_array)}
    times = np.unique(uvd.time_array)
    out = []
    for f in range(twin.freqs_hz.size):
        ratios = []
        for k in np.flatnonzero(uvd.ant_1_array == uvd.ant_2_array):
            a, t = row[int(uvd.ant_1_array[k])], int(np.searchsorted(times, uvd.time_array[k]))
            r = np.flatnonzero((ref.ant_1_array == uvd.ant_1_array[k]) & (ref.ant_2_array == uvd.ant_1_array[k])
                               & (ref.time_array == uvd.time_array[k]))[0]
            for p in range(2):
                cal = twin.model[k, f, p].real / (twin.amplitude[f] * np.abs(twin.gains[a, f, t, p]) ** 2)
                ratios.append(cal / ref.data_array[r, f, p].real)
        out.append(np.median(ratios))
    return np.asarray(out)


def main(argv=None) -> int:  # pragma: no cover - exercised through tests/test_twin.py's subprocess
    """``python -m gcrsky.checks.twin TEMPLATE OUT [--channels i,j,...] [...]``: write a twin file and its truth.

    Beside ``OUT`` (``X.uvh5``): ``X.truth.calh5``, the UVCal of ``g sqrt(q)`` (``--cal`` it to get the
    Jy data), and ``X.truth.npz`` (``freqs_hz``, ``amplitude`` q, ``gains``, ``ant_array``, the sky's
    ``alm``, ``base``, ``prior_mean``, ``modulation_alm`` at ``lmax``, ``settings`` as JSON); the
    settings are printed as JSON.
    """
    import argparse
    import json

    p = argparse.ArgumentParser(prog="python -m gcrsky.checks.twin", description=make_twin.__doc__.splitlines()[0])
    p.add_argument("template", help="the real visibility file (e.g. zen.2458098.45361.HH_downselected.uvh5)")
    p.add_argument("out", help="the twin's UVH5 path")
    p.add_argument("--channels", default=",".join(map(str, DEFAULT_CHANNELS)),
                   help="comma-separated channel indices of the template")
    for name, kind, default in (("lmax-sky", int, 256), ("nside-matvis", int, 128), ("boost", float, 0.05),
                                ("modulation", float, 0.05), ("amplitude", float, 0.003), ("slope", float, -0.3),
                                ("gain-amp", float, 0.05), ("gain-phase-deg", float, 5.0),
                                ("dish-diameter", float, 14.0), ("seed", int, 0)):
        p.add_argument(f"--{name}", type=kind, default=default)
    p.add_argument("--small-scale-kind", choices=("brightness", "isotropic"), default="brightness")
    p.add_argument("--overwrite", action="store_true")
    a = p.parse_args(argv)
    twin = make_twin(a.template, a.out, channels=[int(c) for c in a.channels.split(",")], lmax_sky=a.lmax_sky,
                     nside_matvis=a.nside_matvis, boost=a.boost, modulation=a.modulation, amplitude=a.amplitude,
                     slope=a.slope, small_scale_kind=a.small_scale_kind, gain_amp=a.gain_amp,
                     gain_phase_deg=a.gain_phase_deg, dish_diameter_m=a.dish_diameter, sky_seed=a.seed,
                     gain_seed=a.seed, noise_seed=a.seed, overwrite=a.overwrite)
    stem = twin.path.with_suffix("")
    cal_path, npz_path = Path(f"{stem}.truth.calh5"), Path(f"{stem}.truth.npz")
    twin.uvcal.write_calh5(str(cal_path), clobber=a.overwrite)
    sky = twin.sky
    np.savez(npz_path, freqs_hz=twin.freqs_hz, amplitude=twin.amplitude, gains=twin.gains,
             ant_array=np.asarray(twin.uvcal.ant_array), alm=sky.alm, base=sky.base, prior_mean=sky.prior_mean,
             modulation_alm=sky.modulation_alm, lmax=sky.lmax, settings=json.dumps(twin.settings))
    autos = autos_against_the_prior_mean(twin)
    truth = {**twin.settings, "amplitude_q": twin.amplitude.tolist(), "autos_over_prior_mean": autos.tolist(),
             "q_times_autos_over_prior_mean": (twin.amplitude * autos).tolist(), "path": str(twin.path),
             "truth_calibration": str(cal_path), "truth_arrays": str(npz_path)}
    print(json.dumps(truth, indent=1))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
