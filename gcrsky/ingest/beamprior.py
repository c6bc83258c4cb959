"""Beams as they come and a prior for the whole band, where a file is read (:func:`gcrsky.ingest.from_uvdata`).

* :func:`feed_pol_of`: ``--pol ee`` / ``nn`` (``en``, ``ne``) as the file's feed products, through
  the file's ``x_orientation`` (``Telescope.get_x_orientation_from_feeds``).
* :func:`prepare_beams`: every distinct beam through :func:`gcrsky.instrument.beamprep.prepare_beam`
  (normalisation, frequencies without negative power, image beams, feed orientation
  against the file's), with the record that goes to ``DataConfig.checks["beam"]``.
* :func:`apply_prior_mean`: ``prior_mean="gsm"``: the GSM's coefficients at the data's
  frequencies as the prior's mean (:func:`gcrsky.model.skyprior.gsm_prior_mean`), and the
  record of ``DataConfig.checks["prior"]``.
* :func:`with_checks`: sections added to a Problem's ``config.checks``.
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from ..io.visdata import COMPASS_POLS, feed_pol, parse_products
from ..model.prior import Prior

__all__ = ["PRIOR_MEANS", "apply_prior_mean", "feed_pol_of", "prepare_beams", "with_checks"]

#: What ``prior_mean`` may be: the prior's own mean (zero for the GSM's C_l) or the GSM's coefficients.
PRIOR_MEANS = ("zero", "gsm")


def _uses_compass(pol) -> bool:
    names = pol.split(",") if isinstance(pol, str) else list(pol)
    return any(str(n).strip().lower() in COMPASS_POLS for n in names)


def feed_pol_of(data, pol) -> tuple[object, dict | None]:
    """``(pol in feed names, record or None)``: compass names translated through the file's ``x_orientation``.

    Args:
        data: a visibility file path, a list of them (the first's metadata is read) or a ``UVData`` (only its
            metadata is read).
        pol: the modelled product(s) as given (``"ee"``, ``"nn,ee"``, ``("ee", "nn")``, ``"pI"``, ...).
    """
    if pol is None or not _uses_compass(pol):
        return pol, None
    from pyuvdata import UVData

    from ..io.manyfiles import first_file

    data = first_file(data)  # several files share one array (checked when read)
    if isinstance(data, UVData):
        tel = data.telescope
    else:
        from ..io.files import check_input_file, reading
        from ..io.selection import VIS_FORMATS

        path = check_input_file(data, "visibility file", measurement_set=True)
        with reading(path, "a visibility file", VIS_FORMATS):
            tel = UVData.from_file(os.fspath(path), read_data=False).telescope
    xo = tel.get_x_orientation_from_feeds()
    out = feed_pol(pol, xo)
    try:
        parse_products(out)
    except ValueError as err:
        raise ValueError(f"{err} (pol {pol!r} is {out!r} where feed x points {xo})") from None
    return out, {"given": pol if isinstance(pol, str) else list(pol),
                 "as": out if isinstance(out, str) else list(out), "x_orientation": xo}


def prepare_beams(beams, beam_arg, obs, *, normalization="peak", freq_scaling=None,
                  accept_x_orientation_mismatch=False) -> tuple[list, dict]:
    """``(beams, record)``: each distinct beam of ``beams`` (one per antenna) prepared for ``obs``.

    Args:
        beams: one pyuvdata beam object per antenna (identical antennas share one object).
        beam_arg: what the user gave (a path is recorded as the beam's file).
        obs: the :class:`~gcrsky.io.Observation` (frequencies, ``x_orientation``).
        normalization, freq_scaling, accept_x_orientation_mismatch: as
            :func:`gcrsky.instrument.beamprep.prepare_beam`.

    Returns:
        The prepared beams (same sharing) and ``DataConfig.checks["beam"]``: the one beam's
        record, or ``{"per_beam": [...]}`` for several.
    """
    from ..instrument.beamprep import prepare_beam

    done: dict = {}
    recs = []
    for b in beams:
        if id(b) in done:
            continue
        new, rec = prepare_beam(b, obs.freqs_hz, normalization=normalization, freq_scaling=freq_scaling,
                                x_orientation=obs.x_orientation,
                                accept_x_orientation_mismatch=accept_x_orientation_mismatch)
        if isinstance(beam_arg, (str, os.PathLike)):
            rec["file"] = os.fspath(beam_arg)
        done[id(b)] = new
        recs.append(rec)
    out = [done[id(b)] for b in beams]
    return out, (recs[0] if len(recs) == 1 else {"per_beam": recs})


def apply_prior_mean(prior: Prior, note: str, prior_mean, prior_arg, freqs_hz, lmax: int) -> tuple[Prior, str, dict]:
    """``(prior, note, record)``: the prior with the mean ``prior_mean`` asks for, and ``checks["prior"]``.

    Args:
        prior: the resolved prior (Nf, n).
        note: its description.
        prior_mean: None / ``"zero"`` (as resolved) or ``"gsm"`` (the GSM's coefficients,
            l <= 16, at ``freqs_hz``).
        prior_arg: the ``prior`` argument as given (``"gsm"``, ``"flat"``, a file, ...).
        freqs_hz: (Nf,) the data's frequencies.
        lmax: degree of the coefficients.

    Raises:
        ValueError: an unknown ``prior_mean``; ``"gsm"`` with a flat prior or one whose
            mean comes from a file.
    """
    from ..model.skyprior import GSM_MEAN_LMAX, gsm_cl_range_hz, gsm_prior_mean

    if prior_mean not in (None,) + PRIOR_MEANS:
        raise ValueError(f"prior_mean must be one of {PRIOR_MEANS}, got {prior_mean!r}")
    f = np.asarray(freqs_hz, np.float64)
    rec = {"prior": note, "data_freq_range_hz": [float(f.min()), float(f.max())],
           "gsm_cl_table_range_hz": list(gsm_cl_range_hz()), "mean": "as the prior gives it"}
    if prior_mean != "gsm":
        rec["mean"] = "zero" if not np.any(np.asarray(prior.mean)) else "from the prior (a file or a given Prior)"
        return prior, note, rec
    if isinstance(prior_arg, str) and prior_arg == "flat":
        raise ValueError("prior_mean 'gsm' with a flat prior: a flat prior has no mean (use prior 'gsm')")
    if np.any(np.asarray(prior.mean)):
        raise ValueError("prior_mean 'gsm' with a prior that has its own mean (a map / alm file or a Prior): "
                         "give one of them")
    mean = gsm_prior_mean(f, lmax)
    note = f"{note.replace('zero mean', 'GSM mean')}; mean: the GSM's coefficients (l <= {min(lmax, GSM_MEAN_LMAX)})"
    rec.update(prior=note, mean=f"GSM coefficients at the data's frequencies, l <= {min(lmax, GSM_MEAN_LMAX)} "
               "(pyradiosky's map; per-pixel power laws outside 50-150 MHz), 0 above")
    return Prior(mean=mean, inv_var=prior.inv_var), note, rec


def with_checks(problem, sections: dict):
    """The Problem with ``sections`` added to its ``config.checks`` (existing sections kept)."""
    cfg = problem.config
    if cfg is None or not sections:
        return problem
    checks = {**getattr(cfg, "checks", {}), **sections}
    return dataclasses.replace(problem, config=dataclasses.replace(cfg, checks=checks))
