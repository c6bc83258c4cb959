"""Continuing a run: what must equal the recorded one, and the solver options it recorded.

A run is resumed only when its settings (:meth:`gcrsky.run.RunSpec.settings`) equal
those in ``results.h5`` (:func:`settings_differences` names the ones that differ) and the
problem's inputs are the same bit for bit (:func:`check_resumable`); the resumed run then
uses the exact solver options the first one chose (:func:`options_from_json`), so that it
ends with exactly the draws of an uninterrupted run.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path

from ..io.results import inputs_fingerprint, json_default
from ..solvers.registry import method_of, options_for

__all__ = ["ResumeError", "check_resumable", "options_from_json", "options_json", "settings_differences"]

log = logging.getLogger(__name__)


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


def check_resumable(out, state, prob, version: str) -> None:
    """Raise :class:`ResumeError` unless the recorded run (``state``) can be continued with ``prob``.

    The file must record its solver options, and ``prob``'s inputs must equal the
    recorded ones bit for bit (:func:`gcrsky.io.inputs_fingerprint`); another gcrsky
    ``version`` than the recorded one is only logged.
    """
    if "solver_options_json" not in state.attrs:
        raise ResumeError(out, f"cannot resume: {state.path} does not record its solver options (not written by "
                               "gcrsky.run)")
    if state.attrs.get("inputs_sha256") != inputs_fingerprint(prob):
        raise ResumeError(out, f"cannot resume the run in {out}: the problem's inputs (data, noise, prior, "
                               "times or frequencies) differ bit for bit from those recorded, e.g. another "
                               "sky model is on disk now, or another machine or software version")
    if state.attrs.get("gcrsky_version") != version:
        log.warning("resuming a run of gcrsky %s with gcrsky %s", state.attrs.get("gcrsky_version"), version)
