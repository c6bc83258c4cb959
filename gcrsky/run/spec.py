"""What one run is asked to do: :class:`RunSpec`, typed, frozen and validated on construction.

A run draws ``draws.nsamples`` posterior samples of a :class:`~gcrsky.model.Problem` in
batches (:class:`Draws`: key ``PRNGKey(seed)``, :mod:`gcrsky.inference.batches`), by an
exact path (:class:`Solver`), and writes its files into a directory (:class:`Output`).
A bad value raises ``ValueError`` naming the field (``draws.nsamples``, ``solver.tol``, ...).

:meth:`RunSpec.settings` is what identifies the run's draws: it is recorded in
``results.h5`` and must be equal for ``existing="resume"`` to continue a run.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import os
from pathlib import Path
from typing import Any, Mapping

from ..inference.batches import KEY_SCHEME
from ..io.results import clean_json, json_default
from ..solvers import registry
from ..solvers.options import DEFAULT_TOL
from .output import EXISTING
from .sampling import (
    CHANNEL_MODES,
    FREQ_PRIORS,
    Amplitude,
    AmplitudeSampling,
    Beams,
    BeamSampling,
    DrawStage,
    FrequencyModel,
    Gains,
    GainSampling,
    Independent,
    Joint,
    JointFrequency,
    check_choice,
    check_integer,
)

__all__ = ["Amplitude", "AmplitudeSampling", "BeamSampling", "Beams", "CHANNEL_MODES", "EXISTING", "FREQ_PRIORS", "METHODS", "DrawStage", "Draws", "FrequencyModel", "GainSampling",
           "Gains", "Independent", "Joint", "JointFrequency", "Output", "RunSpec", "Solver", "run_settings", "sampling_of"]

#: The paths a run may ask for (``"auto"``: chosen by size, :func:`gcrsky.solvers.plan.choose_path`): the
#: registry's (:data:`gcrsky.solvers.registry.PATHS`, read again when a :class:`Solver` is checked).
METHODS = ("auto", *registry.METHODS)


@dataclasses.dataclass(frozen=True)
class Draws:
    """The posterior draws: ``nsamples`` in batches of ``batch``, key ``jax.random.PRNGKey(seed)``.

    Batch ``b`` uses ``fold_in(key, b)`` and is always drawn whole (the last one is
    truncated), so draw ``i`` depends only on ``seed`` and ``batch``.
    """

    nsamples: int
    seed: int = 0
    batch: int = 50

    def __post_init__(self):
        check_integer(self, "nsamples", "draws.nsamples", 1)
        check_integer(self, "seed", "draws.seed", 0)
        check_integer(self, "batch", "draws.batch", 1)

    @property
    def n_batches(self) -> int:
        """Batches in all, ``ceil(nsamples / batch)``."""
        return -(-self.nsamples // self.batch)


@dataclasses.dataclass(frozen=True)
class Solver:
    """The exact path (``method``, :data:`METHODS`) and the CG tolerance ``tol`` in posterior sigma."""

    method: str = "auto"
    tol: float = DEFAULT_TOL

    def __post_init__(self):
        check_choice("solver.method", self.method, ("auto", *registry.PATHS))
        if isinstance(self.tol, bool) or not isinstance(self.tol, numbers.Real) or not (
                self.tol > 0 and math.isfinite(self.tol)):
            raise ValueError(f"solver.tol must be a positive finite number, got {self.tol!r}")
        object.__setattr__(self, "tol", float(self.tol))


@dataclasses.dataclass(frozen=True)
class Output:
    """Where the run writes (``out``, created if needed), what it does with a directory that
    holds a run's files (``existing``, :data:`EXISTING`), and whether report hooks draw figures.
    ``trust_recorded`` (with ``existing="resume"`` only): continue from the inputs recorded in
    ``results.h5`` even where the rebuilt ones differ by more than rounding
    (:func:`gcrsky.run.resume.resumed_problem`)."""

    out: Path
    existing: str = "refuse"
    plots: bool = True
    trust_recorded: bool = False

    def __post_init__(self):
        if not isinstance(self.out, (str, os.PathLike)) or not os.fspath(self.out):
            raise ValueError(f"output.out must be a directory path, got {self.out!r}")
        object.__setattr__(self, "out", Path(self.out))
        check_choice("output.existing", self.existing, EXISTING)
        if not isinstance(self.plots, bool):
            raise ValueError(f"output.plots must be True or False, got {self.plots!r}")
        if not isinstance(self.trust_recorded, bool):
            raise ValueError(f"output.trust_recorded must be True or False, got {self.trust_recorded!r}")
        if self.trust_recorded and self.existing != "resume":
            raise ValueError("output.trust_recorded continues a recorded run: it needs existing='resume' (--resume)")


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One run: draws, solver, output, what it samples, and what else identifies it.

    Attributes:
        draws: :class:`Draws`.
        output: :class:`Output`.
        solver: :class:`Solver` (default: ``auto``, tol 1e-6).
        sampling: what the run samples, one draw stage (:mod:`gcrsky.run.sampling`):
            :class:`Joint` (default: one joint system over the channels),
            :class:`Independent` (the channels solved independently, ``Independent("loop")``,
            ``"devices"`` or ``"processes"``), :class:`JointFrequency` (one frequency-coupled
            prior, :class:`FrequencyModel`) or :class:`Gains` (gains sampled with the sky,
            :class:`GainSampling`).  Its settings block is recorded with the run's settings.
        scenario: the paper scenario of the run, if any (recorded).
        argv: the command line (recorded in ``summary.json``), or None.
        extra: further settings that identify the run (e.g. the input file of a run on a
            file); JSON-able, no key of the standard settings.
    """

    draws: Draws
    output: Output
    solver: Solver = Solver()
    sampling: DrawStage = Joint()
    scenario: str | None = None
    argv: tuple[str, ...] | None = None
    extra: Mapping[str, Any] | None = None

    def __post_init__(self):
        for name, kind in (("draws", Draws), ("output", Output), ("solver", Solver), ("sampling", DrawStage)):
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name} must be a {kind.__name__}, got {getattr(self, name)!r}")
        if self.scenario is not None and not isinstance(self.scenario, str):
            raise ValueError(f"scenario must be a name or None, got {self.scenario!r}")
        if self.argv is not None:
            if isinstance(self.argv, str) or not all(isinstance(a, str) for a in self.argv):
                raise ValueError(f"argv must be a sequence of strings or None, got {self.argv!r}")
            object.__setattr__(self, "argv", tuple(self.argv))
        if self.extra is not None:
            object.__setattr__(self, "extra", dict(self.extra))
        self.settings(None)  # the extra settings must not clash and must be JSON-able

    @property
    def channels(self) -> str | None:
        """The independent-channel mode (:class:`Independent`), or None for any other run."""
        return self.sampling.channels if isinstance(self.sampling, Independent) else None

    @property
    def gains(self) -> GainSampling | None:
        """The gain sampling (:class:`Gains`), or None for any other run."""
        return self.sampling.gains if isinstance(self.sampling, Gains) else None

    @property
    def frequency(self) -> FrequencyModel | None:
        """The frequency prior (:class:`JointFrequency`), or None for any other run."""
        return self.sampling.model if isinstance(self.sampling, JointFrequency) else None

    def all_extra(self) -> dict:
        """``extra`` and the sampling's settings block (:meth:`DrawStage.settings_block`)."""
        extra = dict(self.extra or {})
        extra.update(self.sampling.settings_block())
        return extra

    def settings(self, config) -> dict:
        """The run's settings (:func:`run_settings`) with the problem's ``config`` (or None)."""
        d, s = self.draws, self.solver
        return run_settings(config, nsamples=d.nsamples, seed=d.seed, batch=d.batch, method=s.method, tol=s.tol,
                            scenario=self.scenario, extra=self.all_extra())


def sampling_of(channels: str | None = None, gains: GainSampling | None = None,
                frequency: FrequencyModel | None = None, amplitude: AmplitudeSampling | None = None) -> DrawStage:
    """The draw stage of at most one of an independent-channel mode, a gain sampling and a frequency prior;
    with ``amplitude`` (the amplitude inferred, :class:`Amplitude`) the gains, if any, are its own.

    Raises:
        ValueError: more than one is given (the message names them and what to drop).
    """
    if amplitude is not None:
        if channels is not None or frequency is not None:
            raise ValueError("the amplitude is inferred jointly over the channels of a run (one sky model scale): "
                             "drop " + ("channels (--by-channel, --devices, --num-processes)" if channels is not None
                                        else "the frequency prior") + ", or fix the amplitude (--amplitude fixed)")
        return Amplitude(amplitude if gains is None else dataclasses.replace(amplitude, gains=gains))
    given = [name for name, v in (("channels", channels), ("gains", gains), ("frequency", frequency)) if v is not None]
    if len(given) > 1:
        raise ValueError(f"a run samples one way: {' and '.join(given)} were both given. "
                         + ("gains are sampled jointly over the channels (the amplitude's modes span them): drop "
                            "channels (--by-channel, --devices, --num-processes)" if given == ["channels", "gains"]
                            else "a frequency prior couples the channels, so they are sampled together: drop "
                            + ("channels (--by-channel, --devices, --num-processes)" if "channels" in given
                               else "--gains sample (not combined with a frequency prior yet)")))
    if channels is not None:
        return Independent(channels)
    if gains is not None:
        return Gains(gains)
    if frequency is not None:
        return JointFrequency(frequency)
    return Joint()


def run_settings(config, *, nsamples: int, seed: int, batch: int, method: str, tol: float,
                 scenario: str | None = None, extra: dict | None = None) -> dict:
    """What identifies a run's draws: recorded in ``results.h5`` and compared on resume.

    Args:
        config: the problem's configuration (an object with ``to_dict()``, or a dict), or
            None for a problem that has none (then ``extra`` should identify the inputs).
        nsamples, seed, batch: the draws (key scheme :data:`gcrsky.inference.batches.KEY_SCHEME`).
        method: the path asked for (``"auto"`` included; a resumed run uses the path
            the recorded run chose); tol: CG tolerance, posterior sigma.
        scenario: the paper scenario, if any.
        extra: further settings (e.g. the input file of a run on real data).

    Returns:
        a JSON-able dict (``config``, ``nsamples``, ``seed``, ``batch``, ``method``,
        ``tol``, ``scenario``, ``key_scheme`` and ``extra``'s keys).

    Raises:
        ValueError: an ``extra`` key clashes with a standard one.
    """
    if config is not None and not isinstance(config, dict):
        config = config.to_dict()
    out = {
        "config": config, "nsamples": int(nsamples), "seed": int(seed), "batch": int(batch), "method": str(method),
        "tol": float(tol), "scenario": scenario, "key_scheme": KEY_SCHEME,
    }
    for k, v in (extra or {}).items():
        if k in out:
            raise ValueError(f"extra setting {k!r} clashes with a standard one")
        out[k] = v
    return json.loads(json.dumps(clean_json(out), default=json_default))  # canonical: lists, plain numbers
