"""Continuing a run: what must equal the recorded one, and the solver options it recorded.

A run is resumed only when its settings (:meth:`gcrsky.run.RunSpec.settings`) equal
those in ``results.h5`` (:func:`settings_differences` names the ones that differ) and the
problem's inputs are the same (:func:`check_resumable`): bit for bit, or, where a rebuilt
input differs by floating-point rounding (a simulation rebuilt in another process differs by
~1 ulp; so does one with and without the compile cache), within :data:`RESUME_RTOL` of each
recorded array's largest magnitude (a warning names the largest difference).  The resumed
run then continues from the inputs *recorded* in ``results.h5`` (:func:`resumed_problem`:
the data, noise, weights, prior, frequencies and LSTs the first batches were drawn with, not
the rebuilt ones) with the exact solver options the first one chose
(:func:`options_from_json`), so that it ends with the draws of an uninterrupted run, bit for
bit.  Inputs that differ by more than rounding (another sky model on disk, another
simulator version) are refused unless ``trust_recorded`` (``--resume --trust-recorded``)
says to continue from the recorded ones anyway; the geometry (pairs, shapes) must match
either way, since the response is rebuilt from the settings.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

import numpy as np

from ..io.results import inputs_fingerprint, json_default
from ..solvers.registry import method_of, options_for

__all__ = ["RESUME_RTOL", "ResumeError", "input_differences", "options_from_json", "options_json",
           "recorded_inputs", "resumed_problem", "settings_differences"]

log = logging.getLogger(__name__)


#: Recorded and rebuilt inputs that differ by at most this, relative to each array's largest magnitude, are the
#: same inputs rounded differently (measured: ~1 ulp, 2e-16, between processes rebuilding a simulation).
RESUME_RTOL = 1e-12

#: The inputs ``results.h5`` stores (dataset name, how to get it from a Problem), those of the fingerprint.
_STORED = (("freqs_hz", lambda p: p.freqs_hz), ("lsts_rad", lambda p: p.lsts_rad), ("antpairs", lambda p: p.antpairs),
           ("data", lambda p: p.data), ("sigma", lambda p: p.sigma), ("weights", lambda p: p.weights),
           ("prior_mean", lambda p: p.prior.mean), ("prior_inv_var", lambda p: p.prior.inv_var))


def input_differences(h5_path, prob) -> dict:
    """``{input: largest |recorded - rebuilt| / largest |recorded|}`` for the inputs ``results.h5`` stores.

    ``inf`` where an input is missing from the file, has another shape, or is non-finite in one and not
    the other; 0 where equal (NaNs in the same places count as equal).
    """
    import h5py

    out = {}
    with h5py.File(h5_path, "r") as h:
        for name, get in _STORED:
            if name not in h:
                out[name] = float("inf")
                continue
            a, b = np.asarray(h[name][()]), np.asarray(get(prob))
            if a.shape != b.shape:
                out[name] = float("inf")
                continue
            fa, fb = np.isfinite(a), np.isfinite(b)
            if np.any(fa != fb) or np.any(~fa & (a != b) & ~(np.isnan(a) & np.isnan(b))):
                out[name] = float("inf")
                continue
            scale = float(np.max(np.abs(a[fa]))) if np.any(fa) else 0.0
            diff = float(np.max(np.abs(a[fa] - b[fa]))) if np.any(fa) else 0.0
            out[name] = 0.0 if diff == 0 else (diff / scale if scale > 0 else float("inf"))
    return out


class ResumeError(ValueError):
    """The run in the output directory cannot be resumed by this one.

    Attributes:
        out: the directory.
        differences: ``[(setting, recorded, requested)]`` where the settings differ
            (:func:`settings_differences`; empty when the reason is another one).
    """

    def __init__(self, out, message: str, differences=()):
        self.out, self.differences = Path(out), list(differences)
        super().__init__(message)


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def settings_differences(recorded: dict, requested: dict) -> list[tuple[str, object, object]]:
    """``[(setting, recorded value, requested value)]`` where two runs' settings differ.

    Nested settings are named with dots (``config.lmax``); a setting missing on one
    side is reported with the value ``None`` there.
    """
    a = _flatten(json.loads(json.dumps(recorded, default=json_default)))
    b = _flatten(json.loads(json.dumps(requested, default=json_default)))
    return [(k, a.get(k), b.get(k)) for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


def options_json(options) -> str:
    """The resolved options of a solver path as JSON (``results.h5``'s ``solver_options_json``)."""
    return json.dumps({"method": method_of(options), "fields": dataclasses.asdict(options)}, default=json_default)


def options_from_json(text: str):
    """The options object :func:`options_json` wrote."""
    d = json.loads(text)
    return type(options_for(d["method"]))(**d["fields"])


#: The stored inputs that fix the operator's geometry: they may differ by rounding only, even with ``trust_recorded``.
_GEOMETRY = ("freqs_hz", "lsts_rad", "antpairs")


def recorded_inputs(h5_path, prob):
    """``prob`` with the inputs recorded in ``results.h5`` in place of its own (each cast to ``prob``'s dtype).

    The frequencies, LSTs, data, noise, weights and prior mean and inverse variance are replaced; the
    response, frame and everything else are ``prob``'s.  The shapes must agree (:func:`input_differences`
    is not inf for shape reasons; checked by the caller).
    """
    import h5py
    import jax.numpy as jnp

    with h5py.File(h5_path, "r") as h:
        rec = {name: np.asarray(h[name][()]) for name, _ in _STORED}

    def like(name, current):
        return jnp.asarray(rec[name], dtype=jnp.asarray(current).dtype)

    prior = prob.prior._replace(mean=like("prior_mean", prob.prior.mean),
                                inv_var=like("prior_inv_var", prob.prior.inv_var))
    return dataclasses.replace(prob, freqs_hz=like("freqs_hz", prob.freqs_hz), lsts_rad=like("lsts_rad", prob.lsts_rad),
                               data=like("data", prob.data), sigma=like("sigma", prob.sigma),
                               weights=like("weights", prob.weights), prior=prior)


def _described(off: dict) -> str:
    return ", ".join(f"{k} by {v:.3g}" if np.isfinite(v) else f"{k} (other shape or non-finite values)"
                     for k, v in off.items())


def resumed_problem(out, state, prob, version: str, *, trust_recorded: bool = False):
    """The problem a resumed run continues with: ``prob`` with the recorded inputs (:func:`recorded_inputs`).

    Raises :class:`ResumeError` unless the recorded run (``state``) can be continued: the file must record
    its solver options and its inputs; ``prob``'s inputs must equal the recorded ones bit for bit
    (:func:`gcrsky.io.inputs_fingerprint`) or within :data:`RESUME_RTOL` (:func:`input_differences`:
    rounding; logged), or, with ``trust_recorded``, differ only in values (data, noise, weights, prior:
    logged as a warning), never in geometry (:data:`_GEOMETRY`, shapes).  Another gcrsky ``version`` than
    the recorded one is only logged.  Where the fingerprints agree, ``prob`` itself is returned.
    """
    if "solver_options_json" not in state.attrs:
        raise ResumeError(out, f"cannot resume: {state.path} does not record its solver options (not written by "
                               "gcrsky.run)")
    if state.attrs.get("gcrsky_version") != version:
        log.warning("resuming a run of gcrsky %s with gcrsky %s", state.attrs.get("gcrsky_version"), version)
    if state.attrs.get("inputs_sha256") == inputs_fingerprint(prob):
        return prob
    diffs = input_differences(state.path, prob)
    off = {k: v for k, v in diffs.items() if v > RESUME_RTOL}
    geometry = {k: v for k, v in off.items() if k in _GEOMETRY or not np.isfinite(v)}
    if geometry or (off and not trust_recorded):
        keep = ("" if geometry else "; --resume --trust-recorded continues from the recorded inputs (the draws "
                "kept, the rebuilt inputs ignored)")
        raise ResumeError(out, f"cannot resume the run in {out}: the problem's inputs differ from those recorded "
                               f"({_described(off)}, relative to their largest magnitude; more than rounding, "
                               f"{RESUME_RTOL:g}), e.g. another sky model is on disk now, or another file{keep}")
    if off:
        log.warning("resuming %s from its recorded inputs (--trust-recorded): the rebuilt ones differ (%s); the "
                    "remaining draws are of the recorded problem", out, _described(off))
    else:
        worst = max(diffs, key=diffs.get)
        log.info("resuming %s from its recorded inputs: the rebuilt ones differ by floating-point rounding only "
                 "(at most %.2g of %s's largest magnitude; tolerance %g)", out, diffs[worst], worst, RESUME_RTOL)
    return recorded_inputs(state.path, prob)

