"""Real observations in: a :class:`~gcrsky.model.Problem` from any file pyuvdata reads.

:func:`ingest` turns a visibility file (UVH5; UVFITS, Measurement Sets, MIRIAD where
pyuvdata's optional readers are installed) or a ``UVData`` object into the inference
problem whose parameters are the ICRS coefficients of the sky (DESIGN section 2, mode (b):
the file's real observing times at the file's site), as an :class:`~gcrsky.ingest.IngestSpec`
says; :func:`from_uvdata` is the same with the spec's settings as keywords.
:func:`gcrsky.ingest.inspect_uvdata` says what would be used without solving.

The stages, each a function here or in its module:

1. read, calibrate and check (:func:`checked_observation`): :func:`gcrsky.io.read_observation`
   (the file, selected and read partially, in gcrsky's conventions, as an
   :class:`~gcrsky.io.Observation`), the calibration and the data checks
   (:mod:`gcrsky.ingest.datachecks`);
2. the beams (:func:`gcrsky.ingest.beams.prepared_beams`) and the flux-scale check through them;
3. the band limit (:func:`band_limited`: lmax and the quadrature check, :mod:`gcrsky.model.bandlimit`);
4. the prior (:func:`prepared_prior`: :mod:`gcrsky.ingest.prior`, the prior's mean);
5. the Problem (:func:`gcrsky.model.problem_from_observation`: modelled products, units,
   radiometer noise, weights, responses, redundant compression).

The conventions are on the docs' ingest page (``docs/ingest.md``).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import NamedTuple

from ..io.visdata import Observation, parse_products
from ..model.bandlimit import check_quadrature, observation_lmax, observation_reach
from ..model.observed import check_observation, noise_kind, problem_from_observation
from ..model.prior import Prior
from ..model.problem import Problem
from ..model.skyprior import check_gsm_cl_frequencies
from .beamprior import apply_prior_mean, feed_pol_of, with_checks
from .beams import PreparedBeams, prepared_beams
from .datachecks import CheckedObservation, amplitude_checks, flag_checks, flux_checks, read_checked
from .prior import resolve_prior
from .spec import IngestSpec

__all__ = [
    "BandLimit",
    "PreparedPrior",
    "band_limited",
    "checked_observation",
    "from_uvdata",
    "ingest",
    "ingest_with_beams",
    "prepared_prior",
    "read_selection",
]

log = logging.getLogger(__name__)


class BandLimit(NamedTuple):
    """The band limit: ``lmax`` and its record (``DataConfig.checks["band_limit"]``'s source)."""

    lmax: int
    note: dict


class PreparedPrior(NamedTuple):
    """The prior at the data's frequencies and ``lmax``, its description and ``checks["prior"]``."""

    prior: Prior
    note: str
    record: dict


def read_selection(spec: IngestSpec) -> dict:
    """The read keywords of ``spec`` (:func:`gcrsky.io.read_observation`'s selection and memory budget)."""
    s = spec.selection
    return dict(freq_chans=s.freq_chans, freq_range_hz=s.freq_range_hz, times_jd=s.times_jd,
                lst_range_hours=s.lst_range_hours, antennas=s.antennas, bls=s.bls,
                memory_budget=spec.memory_budget)


def checked_observation(data, spec: IngestSpec, pol) -> CheckedObservation:
    """The file read (and calibrated), checked, its outliers flagged, checked again; the GSM prior's band
    checked too: everything that can refuse a file before a beam is read or a response built.

    Args:
        data: a visibility file or a ``UVData``.
        spec: the settings (selection, checks, noise, prior).
        pol: the modelled product(s) in the file's feed names (:func:`gcrsky.ingest.beamprior.feed_pol_of`).
    """
    obs, checks = read_checked(data, cal=spec.checks.cal, pol=pol, autos=noise_kind(spec.noise) == "autos",
                               **read_selection(spec))
    for line in obs.notes:
        log.warning(line)
    obs, amp = amplitude_checks(obs, checks, spec.checks.amplitude)
    checks.update(amp)
    check_observation(obs, pol, spec.noise)  # units, products, autos, data
    prior = spec.prior.prior
    if prior is None or (isinstance(prior, str) and prior == "gsm"):
        check_gsm_cl_frequencies(obs.freqs_hz)  # the prior's band
    obs, flags = flag_checks(obs, flag=spec.checks.flag_outliers)
    checks.update(flags)
    check_observation(obs, pol, spec.noise)  # still something to fit once the outliers are flagged
    return CheckedObservation(obs, checks)


def band_limited(obs: Observation, beams: list, spec: IngestSpec, pol) -> BandLimit:
    """``lmax`` (``spec.lmax``, or every used baseline's reach capped by memory) and the check that
    ``spec.nside``'s quadrature resolves the kept rows (:mod:`gcrsky.model.bandlimit`)."""
    lmax, note = observation_lmax(obs, beams, spec.lmax, n_products=len(parse_products(pol)[0]),
                                  frame_pad=spec.frame_pad, budget_bytes=spec.memory_budget,
                                  compress=spec.compress and spec.band_limit != "marginalise")
    check_quadrature(observation_reach(obs, beams, isotropic=True)[0], lmax, spec.nside, spec.band_limit,
                     frame_pad=spec.frame_pad)
    return BandLimit(lmax, note)


def prepared_prior(spec: IngestSpec, freqs_hz, lmax: int) -> PreparedPrior:
    """The prior of ``spec.prior`` (:func:`gcrsky.ingest.prior.resolve_prior`) with the mean ``prior_mean``
    asks for (:func:`gcrsky.ingest.beamprior.apply_prior_mean`), at ``freqs_hz`` (Nf,) and ``lmax``."""
    p = spec.prior
    return PreparedPrior(*apply_prior_mean(*resolve_prior(p.prior, p.prior_scale, freqs_hz, lmax),
                                           p.prior_mean, p.prior, freqs_hz, lmax))


def ingest(data, spec: IngestSpec) -> Problem:
    """The inference problem of a visibility file: ICRS coefficients at ``lmax`` (module docstring).
    :func:`ingest_with_beams` also returns the prepared beams.

    Args:
        data: a path to any file ``UVData.from_file`` reads, a ``UVData`` (not modified), or a list of
            paths, glob patterns or directories: several files of one array and band read as one
            observation (:mod:`gcrsky.io.manyfiles`; with ``spec.checks.cal`` one solutions file for all
            or one per file).
        spec: what to make of it (:class:`~gcrsky.ingest.IngestSpec`; ``spec.nside`` is required).

    Returns:
        a :class:`~gcrsky.model.Problem` (``pols``: each row's product; ``config``: a
        :class:`~gcrsky.ingest.DataConfig` whose ``checks`` say what was checked: calibration, flags,
        flux_scale, beam, prior, band_limit, pol).
    """
    return ingest_with_beams(data, spec)[0]


def ingest_with_beams(data, spec: IngestSpec) -> tuple[Problem, list]:
    """``(problem, beams)``: :func:`ingest`'s problem and the prepared nominal beams it was built with, one
    pyuvdata beam object per antenna in the order of ``problem.antpos_enu_m`` (what a run that perturbs them,
    :mod:`gcrsky.run.beams`, starts from)."""
    from ..base.dtypes import require_x64

    require_x64("from_uvdata")
    if isinstance(data, (list, tuple)):  # several files (globs, directories): one observation of their union
        from ..io.files import expand_data_paths

        data = expand_data_paths(data)
    if not isinstance(spec, IngestSpec):
        raise TypeError(f"spec must be an IngestSpec, got {type(spec).__name__}")
    if spec.nside is None:
        raise ValueError("nside must be given: the HEALPix nside of the response quadrature (IngestSpec.nside)")
    pol, pol_rec = feed_pol_of(data, spec.selection.pol)
    parse_products(pol)
    obs, checks = checked_observation(data, spec, pol)
    b = spec.beam
    beams: PreparedBeams = prepared_beams(b.beam, b.dish_diameter_m, obs, normalization=b.beam_normalization,
                                          freq_scaling=b.beam_freq_scaling,
                                          accept_x_orientation_mismatch=b.accept_x_orientation_mismatch)
    infer = checks["amplitude"]["mode"] == "infer"
    checks.update(flux_checks(obs, beams.beams[0], pol=pol, mode=spec.checks.flux_scale, inferred=infer))
    band = band_limited(obs, beams.beams, spec, pol)
    if infer and spec.prior.prior_mean is None:  # the amplitude is anchored by a sky model: the GSM's coefficients
        spec = dataclasses.replace(spec, prior=dataclasses.replace(spec.prior, prior_mean="gsm"))
    prior = prepared_prior(spec, obs.freqs_hz, band.lmax)
    prob = problem_from_observation(obs, beams.beams, lmax=band.lmax, nside=spec.nside, pol=pol, prior=prior.prior,
                                    noise=spec.noise, compress=spec.compress, frame_pad=spec.frame_pad,
                                    beam_note=beams.note, prior_note=prior.note, band_limit=spec.band_limit,
                                    band_note=band.note, checks=checks)
    prob = with_checks(prob, {"beam": beams.record, "prior": prior.record, **({"pol": pol_rec} if pol_rec else {})})
    return prob, list(beams.beams)


def from_uvdata(data, spec: IngestSpec | None = None, **keywords) -> Problem:
    """:func:`ingest` with the settings as keywords (:meth:`IngestSpec.from_keywords`), or a spec.

    Args:
        data: a path to any file ``UVData.from_file`` reads, a ``UVData`` (not modified), or a list of
            paths, globs or directories (several files as one observation, :func:`ingest`).
        lmax: degree of the ICRS coefficients; None: every used baseline's reach at the highest
            frequency, capped by memory (:func:`gcrsky.model.bandlimit.observation_lmax`).
        beam: a pyuvdata beam object (``UVBeam``, ``AnalyticBeam``, ``BeamInterface``), a beam
            file's path (UVBeam files, SIN beam images), a dict from antenna numbers or names
            to beams, or a list of beams in the file's ``antenna_numbers`` order.
        dish_diameter_m: instead of ``beam``: a Gaussian beam with the Airy FWHM of that dish.
        pol: ``"pI"`` (``xx + yy``), ``"xx"``, ``"yy"``, ``("xx", "yy")`` / ``"xx,yy"`` (both, of one sky).
        prior: ``None`` / ``"gsm"`` (isotropic, zero mean, the GSM's C_l, :func:`gcrsky.model.gsm_cl`),
            ``"flat"``, a :class:`~gcrsky.model.Prior`, a C_l array ((lmax+1,) or (Nf, lmax+1),
            K^2) or file (``.npy``, or text: l and C_l per frequency), or a HEALPix map / alm
            FITS file (ICRS, K: the prior's *mean*, with the GSM's C_l as its variance).
        prior_scale, nside: factor on the prior variance; HEALPix nside of the response quadrature.
        noise: ``"autos"`` (radiometer equation on the autos), ``"diff"`` (time-adjacent
            differences), or each raw product's per-component sigma in the file's units
            (broadcastable to (Nf, Nt, Nbl)).
        freq_chans, freq_range_hz: channel indices, and/or a (lo, hi) range in Hz.
        times_jd, lst_range_hours: times (JD) to keep, and/or an LST range (h; ``(22, 2)`` wraps).
        antennas, bls: antenna numbers or names to keep (pairs among them); antenna pairs to keep.
        compress: merge redundant baselines (only identical responses, :func:`gcrsky.compress_problem`).
        frame_pad, memory_budget: degree margin of the ICRS -> of-date map; bytes the read may use.
        beam_normalization, beam_freq_scaling, accept_x_orientation_mismatch: how a beam is
            prepared (:func:`gcrsky.instrument.beamprep.prepare_beam`): ``"peak"`` (a physical
            UVBeam peak-normalised) or ``"physical"``; a single-frequency beam's ``"none"`` or
            ``"lambda"`` scaling; whether the beam's feed x may point elsewhere than the file's.
        prior_mean: None / ``"zero"`` (the prior's own mean) or ``"gsm"`` (the GSM's
            coefficients at the data's frequencies, :func:`gcrsky.model.skyprior.gsm_prior_mean`).
        band_limit: rows whose reach exceeds ``lmax`` (:mod:`gcrsky.model.bandlimit`): ``"cut"``
            (the CLI's default), ``"marginalise"`` (the sky above ``lmax`` as noise) or
            ``"truncate"`` (default here, with a warning: right for data simulated at ``lmax``).
        cal: a gain solutions file (calfits, calh5) applied first (:mod:`gcrsky.io.calibration`); with several
            visibility files one for all or a list, one per file.
        flag_outliers: flag the noise-excess outliers (:mod:`gcrsky.model.datachecks`).
        flux_scale: ``"accept"`` (default: the data / GSM autos ratio recorded, a warning outside
            :data:`gcrsky.model.fluxscale.FLUX_BOUNDS`), ``"check"`` (refused outside them: the
            CLI's default) or ``"off"``.

    ``pol`` may name products by compass direction (``"ee"``, ``"nn"``): the file's feed
    products through its ``x_orientation``.

    Returns:
        :func:`ingest`'s Problem.

    Raises:
        TypeError: an unknown keyword, or both a spec and keywords.
        ValueError: a bad setting (naming it), or a file that cannot give a Problem.
    """
    if spec is None:
        spec = IngestSpec.from_keywords(**keywords)
    elif keywords:
        raise TypeError(f"give an IngestSpec or keywords, not both (got {sorted(keywords)})")
    return ingest(data, spec)
