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
from ..model.gains import BASES
from ..parallel.channels import CHANNEL_KEY_SCHEME
from ..solvers import registry
from ..solvers.options import DEFAULT_TOL

__all__ = ["CHANNEL_MODES", "EXISTING", "FREQ_PRIORS", "METHODS", "Draws", "FrequencyModel", "GainSampling",
           "Output", "RunSpec", "Solver", "run_settings"]

#: The paths a run may ask for (``"auto"``: chosen by size, :func:`gcrsky.solvers.plan.choose_path`): the
#: registry's (:data:`gcrsky.solvers.registry.PATHS`, read again when a :class:`Solver` is checked).
METHODS = ("auto", *registry.METHODS)
#: What a run may do with a directory that already holds a run's files.
EXISTING = ("refuse", "overwrite", "resume")
#: The frequency models of a run: independent channels (each its own prior), or one prior over all of them
#: (:class:`FrequencyModel`, :mod:`gcrsky.run.frequency`).
FREQ_PRIORS = ("independent", "template", "basis", "kernel")
#: Independent-channel modes (:mod:`gcrsky.parallel.channels`); None is the joint run.
CHANNEL_MODES = ("loop", "devices", "processes")


def _integer(obj, name: str, where: str, lo: int, hi: int = 2**63 - 1) -> None:
    value = getattr(obj, name)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not lo <= value <= hi:
        raise ValueError(f"{where} must be an integer >= {lo} and <= {hi} (a signed 64-bit integer), got {value!r}")
    object.__setattr__(obj, name, int(value))


def _choice(where: str, value, allowed: tuple) -> None:
    if value not in allowed:
        raise ValueError(f"{where} must be one of {', '.join(map(repr, allowed))}, got {value!r}")


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
        _integer(self, "nsamples", "draws.nsamples", 1)
        _integer(self, "seed", "draws.seed", 0)
        _integer(self, "batch", "draws.batch", 1)

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
        _choice("solver.method", self.method, ("auto", *registry.PATHS))
        if isinstance(self.tol, bool) or not isinstance(self.tol, numbers.Real) or not (
                self.tol > 0 and math.isfinite(self.tol)):
            raise ValueError(f"solver.tol must be a positive finite number, got {self.tol!r}")
        object.__setattr__(self, "tol", float(self.tol))


@dataclasses.dataclass(frozen=True)
class Output:
    """Where the run writes (``out``, created if needed), what it does with a directory that
    holds a run's files (``existing``, :data:`EXISTING`), and whether report hooks draw figures."""

    out: Path
    existing: str = "refuse"
    plots: bool = True

    def __post_init__(self):
        if not isinstance(self.out, (str, os.PathLike)) or not os.fspath(self.out):
            raise ValueError(f"output.out must be a directory path, got {self.out!r}")
        object.__setattr__(self, "out", Path(self.out))
        _choice("output.existing", self.existing, EXISTING)
        if not isinstance(self.plots, bool):
            raise ValueError(f"output.plots must be True or False, got {self.plots!r}")


@dataclasses.dataclass(frozen=True)
class GainSampling:
    """Per-antenna gains sampled with the sky (:mod:`gcrsky.run.gains`; the model of :mod:`gcrsky.model.gains`).

    The run's draws are then the states of a Markov chain over (sky, gains, overall amplitude)
    (:func:`gcrsky.inference.joint_gain_step`), not independent draws: ``burn`` sweeps of burn-in
    (re-centred on the current gains after each half), then one kept state every ``thin`` sweeps.

    Attributes:
        modes: ``(Kf, Kt)`` smooth modes per gain in frequency (delay) and time (fringe rate);
            ``(1, 1)``: one complex gain per antenna (or feed) over the selection.
        basis: ``"dpss"``, ``"fourier"`` or ``"legendre"`` (:func:`gcrsky.model.mode_basis`).
        sigma: prior standard deviation of each mode's coefficient (rms fractional gain error).
        burn: burn-in sweeps (>= 2: the linearisation point moves after each half).
        thin: sweeps per kept draw.
        gauge_moves: Metropolis moves along the amplitude-sky gauge orbit per sweep
            (:func:`gcrsky.inference.gauge_step`; 0 is plain Gibbs, which barely moves along it).
        applied: the overall amplitude ``gbar`` the gains start from (e.g. the square root of
            the autocorrelations' flux-scale ratio); the sampled amplitude is relative to it.
    """

    modes: tuple = (1, 1)
    basis: str = "dpss"
    sigma: float = 0.05
    burn: int = 200
    thin: int = 1
    gauge_moves: int = 4
    applied: float = 1.0

    def __post_init__(self):
        modes = tuple(self.modes)
        if len(modes) != 2 or any(isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 1 for k in modes):
            raise ValueError(f"gains.modes must be two integers >= 1 (Kf, Kt), got {self.modes!r}")
        object.__setattr__(self, "modes", tuple(int(k) for k in modes))
        _choice("gains.basis", self.basis, BASES)
        for name in ("sigma", "applied"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not (v > 0 and math.isfinite(v)):
                raise ValueError(f"gains.{name} must be a positive finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        _integer(self, "burn", "gains.burn", 2)
        _integer(self, "thin", "gains.thin", 1)
        _integer(self, "gauge_moves", "gains.gauge_moves", 0)

    def to_dict(self) -> dict:
        """The settings as a JSON-able dict (recorded with the run's settings)."""
        return {**dataclasses.asdict(self), "modes": list(self.modes)}


def _positive(obj, name: str, where: str, *, zero: bool = False) -> None:
    v = getattr(obj, name)
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v) or v < 0 or (v == 0 and not zero):
        raise ValueError(f"{where} must be a {'non-negative' if zero else 'positive'} finite number, got {v!r}")
    object.__setattr__(obj, name, float(v))


#: Default relative nugget per frequency prior (:mod:`gcrsky.model.spectral`): the template and the kernel only
#: need ``R`` numerically positive definite; a rank-K basis needs a proper prior beyond its K functions.
DEFAULT_NUGGET = {"template": 1e-6, "basis": 1e-3, "kernel": 1e-6}


@dataclasses.dataclass(frozen=True)
class FrequencyModel:
    """One prior over all channels, coupling them (:mod:`gcrsky.run.frequency`; DESIGN section 13).

    The prior is separable, ``Cov(a_k(nu), a_k(nu')) = c_k R(nu, nu')``, with ``c_k`` the problem's
    own (independent) prior variance at the reference channel (the middle one) and ``R`` from
    :mod:`gcrsky.model.spectral`:

    * ``"template"``: the paper's power law ``(nu/nu0)^beta`` shared by all channels (a one-function
      spectral basis), plus the nugget;
    * ``"basis"``: ``nbasis`` log-polynomial functions ``(nu/nu0)^beta log(nu/nu0)^k``, the k-th with
      prior variance ``basis_sigma^(2k)`` (relative to the power law's), plus the nugget;
    * ``"kernel"``: ``(nu nu'/nu0^2)^beta exp(-(log nu - log nu')^2 / (2 xi^2))``, plus the nugget.

    Attributes:
        prior: ``"template"``, ``"basis"`` or ``"kernel"``.
        beta: spectral index of the prior's standard deviation, or None: fitted (least squares
            in log-log) to the ratio of each channel's prior variance to the reference channel's.
        xi: the kernel's correlation length in ``log nu`` (natural log).
        nbasis: the basis' number of functions K (>= 1).
        basis_sigma: the basis' relative prior standard deviation per order.
        nugget: relative jitter (:mod:`gcrsky.model.spectral`); None: :data:`DEFAULT_NUGGET`.
        fit: fit the kernel's hyperparameters (amplitude, beta, xi) by maximum joint evidence
            before sampling (``"kernel"`` only).
    """

    prior: str = "kernel"
    beta: float | None = None
    xi: float = 0.1
    nbasis: int = 3
    basis_sigma: float = 0.1
    nugget: float | None = None
    fit: bool = False

    def __post_init__(self):
        _choice("frequency.prior", self.prior, FREQ_PRIORS[1:])
        if self.beta is not None:
            if isinstance(self.beta, bool) or not isinstance(self.beta, numbers.Real) or not math.isfinite(self.beta):
                raise ValueError(f"frequency.beta must be a finite number or None, got {self.beta!r}")
            object.__setattr__(self, "beta", float(self.beta))
        _positive(self, "xi", "frequency.xi")
        _integer(self, "nbasis", "frequency.nbasis", 1, 8)
        _positive(self, "basis_sigma", "frequency.basis_sigma")
        if self.nugget is None:
            object.__setattr__(self, "nugget", DEFAULT_NUGGET[self.prior])
        _positive(self, "nugget", "frequency.nugget", zero=True)
        if not isinstance(self.fit, bool):
            raise ValueError(f"frequency.fit must be True or False, got {self.fit!r}")
        if self.fit and self.prior != "kernel":
            raise ValueError(f"frequency.fit fits the kernel's hyperparameters: it needs prior 'kernel', not "
                             f"{self.prior!r}")

    def to_dict(self) -> dict:
        """The settings as a JSON-able dict (recorded with the run's settings as ``frequency``)."""
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class RunSpec:
    """One run: draws, solver, output, and what else identifies it.

    Attributes:
        draws: :class:`Draws`.
        output: :class:`Output`.
        solver: :class:`Solver` (default: ``auto``, tol 1e-6).
        channels: None (one joint system) or a mode of :data:`CHANNEL_MODES`: the channels
            solved independently (key scheme
            :data:`~gcrsky.parallel.channels.CHANNEL_KEY_SCHEME`, other, equally exact draws):
            ``"loop"`` one at a time, ``"devices"`` over this process's devices,
            ``"processes"`` over ``jax.distributed`` processes (only process 0 writes).
        scenario: the paper scenario of the run, if any (recorded).
        argv: the command line (recorded in ``summary.json``), or None.
        extra: further settings that identify the run (e.g. the input file of a run on a
            file); JSON-able, no key of the standard settings.
        gains: None (the data taken as calibrated) or :class:`GainSampling`: gains sampled
            with the sky (a joint run only; recorded in the settings as ``gains``).
        frequency: None (independent channels, each its own prior) or :class:`FrequencyModel`:
            one prior over all channels, sampled jointly (:mod:`gcrsky.run.frequency`; recorded
            in the settings as ``frequency``).
    """

    draws: Draws
    output: Output
    solver: Solver = Solver()
    channels: str | None = None
    scenario: str | None = None
    argv: tuple[str, ...] | None = None
    extra: Mapping[str, Any] | None = None
    gains: GainSampling | None = None
    frequency: FrequencyModel | None = None

    def __post_init__(self):
        for name, kind in (("draws", Draws), ("output", Output), ("solver", Solver)):
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name} must be a {kind.__name__}, got {getattr(self, name)!r}")
        if self.channels is not None:
            _choice("channels", self.channels, CHANNEL_MODES)
        if self.scenario is not None and not isinstance(self.scenario, str):
            raise ValueError(f"scenario must be a name or None, got {self.scenario!r}")
        if self.argv is not None:
            if isinstance(self.argv, str) or not all(isinstance(a, str) for a in self.argv):
                raise ValueError(f"argv must be a sequence of strings or None, got {self.argv!r}")
            object.__setattr__(self, "argv", tuple(self.argv))
        if self.extra is not None:
            object.__setattr__(self, "extra", dict(self.extra))
        if self.gains is not None:
            if not isinstance(self.gains, GainSampling):
                raise ValueError(f"gains must be a GainSampling or None, got {self.gains!r}")
            if self.channels is not None:
                raise ValueError("gains are sampled jointly over the channels (the amplitude's modes span them): "
                                 "drop channels (--by-channel, --devices, --num-processes)")
        if self.frequency is not None:
            if not isinstance(self.frequency, FrequencyModel):
                raise ValueError(f"frequency must be a FrequencyModel or None, got {self.frequency!r}")
            if self.channels is not None or self.gains is not None:
                raise ValueError("a frequency prior couples the channels, so they are sampled together: drop "
                                 + ("channels (--by-channel, --devices, --num-processes)" if self.channels is not None
                                    else "--gains sample (not combined with a frequency prior yet)"))
        self.settings(None)  # the extra settings must not clash and must be JSON-able

    def all_extra(self) -> dict:
        """``extra`` and, for an independent-channel run, its mode and key scheme; the gain sampling, if any."""
        extra = dict(self.extra or {})
        if self.gains is not None:
            extra["gains"] = self.gains.to_dict()
        if self.frequency is not None:
            extra["frequency"] = self.frequency.to_dict()
        if self.channels is not None:
            extra.update(channels=self.channels, channel_key_scheme=CHANNEL_KEY_SCHEME)
        return extra

    def settings(self, config) -> dict:
        """The run's settings (:func:`run_settings`) with the problem's ``config`` (or None)."""
        d, s = self.draws, self.solver
        return run_settings(config, nsamples=d.nsamples, seed=d.seed, batch=d.batch, method=s.method, tol=s.tol,
                            scenario=self.scenario, extra=self.all_extra())


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
