"""What a run samples: one draw-stage object per kind of run (:class:`DrawStage`), held by
:attr:`gcrsky.run.RunSpec.sampling`.

* :class:`Joint`: one joint system over all channels (the default);
* :class:`Independent`: the channels solved independently (``"loop"``, ``"devices"`` or
  ``"processes"``, :mod:`gcrsky.run.channels`);
* :class:`JointFrequency`: one frequency-coupled prior over all channels (:class:`FrequencyModel`,
  :mod:`gcrsky.run.frequency`);
* :class:`Gains`: per-antenna gains sampled with the sky (:class:`GainSampling`, :mod:`gcrsky.run.gains`);
* :class:`Amplitude`: the overall amplitude per channel (bandpass) inferred with the sky, anchored by a
  sky model, with or without per-antenna gains (:class:`AmplitudeSampling`, :mod:`gcrsky.run.amplitude`);
* :class:`Beams`: every antenna's beam perturbation sampled with the sky (:class:`BeamSampling`,
  :mod:`gcrsky.run.beams`).

Each stage declares what the runner needs of it, so that :func:`gcrsky.run.execute` has no
test of the kind of run: its settings block (:meth:`DrawStage.settings_block`, recorded in the
run's settings and compared on resume), the files it writes besides the standard ones
(:attr:`DrawStage.files`), the function that draws (:meth:`DrawStage.run_draws`), the
summary's ``channels`` block (:meth:`DrawStage.channels_block`) and, after the draws, its own
summary block and files (:meth:`DrawStage.finish`).  A new kind of run (e.g. sampled beams) is
a new subclass.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import ClassVar

import jax

from ..model.gains import BASES
from ..parallel.channels import CHANNEL_KEY_SCHEME
from .amplitude import amplitude_draws, amplitude_summary
from .amplitude import fit_problem as amplitude_fit_problem
from .beams import beam_draws, beam_fit_problem, beam_summary, fit_without_gains, write_beam_products
from .channels import channel_draws, worker_channels
from .draws import joint_draws
from .frequency import channels_block, frequency_draws
from .gains import (
    beam_gain_summary,
    gain_draws,
    gain_summary,
    gained_problem,
    stored_gain_factor,
    write_gain_products,
)
from .output import BEAM_DIR, GAIN_FILE

__all__ = ["AMPLITUDE_MODEL_SD", "Amplitude", "AmplitudeSampling", "BeamSampling", "Beams", "CHANNEL_MODES", "FIXED_SCALE_SD", "DEFAULT_NUGGET", "FREQ_PRIORS", "DrawStage", "FrequencyModel", "GainSampling", "Gains",
           "Independent", "Joint", "JointFrequency", "STAGES", "check_choice", "check_integer", "check_positive"]

#: The frequency models of a run: independent channels (each its own prior), or one prior over all of them
#: (:class:`FrequencyModel`, :mod:`gcrsky.run.frequency`).
FREQ_PRIORS = ("independent", "template", "basis", "kernel")
#: Independent-channel modes (:mod:`gcrsky.parallel.channels`; :class:`Independent`).
CHANNEL_MODES = ("loop", "devices", "processes")


def check_integer(obj, name: str, where: str, lo: int, hi: int = 2**63 - 1) -> None:
    """Set ``obj.name`` to its int value if an integer in ``[lo, hi]``, else raise ``ValueError`` naming ``where``."""
    value = getattr(obj, name)
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not lo <= value <= hi:
        raise ValueError(f"{where} must be an integer >= {lo} and <= {hi} (a signed 64-bit integer), got {value!r}")
    object.__setattr__(obj, name, int(value))


def check_choice(where: str, value, allowed: tuple) -> None:
    """Raise ``ValueError`` naming ``where`` unless ``value`` is one of ``allowed``."""
    if value not in allowed:
        raise ValueError(f"{where} must be one of {', '.join(map(repr, allowed))}, got {value!r}")


#: ``GainSampling.scale_sd`` of a run whose amplitude is fixed (``--amplitude fixed --gains sample``): ``q``
#: held at 1 to 1e-6, far below any posterior spread the data give it.
FIXED_SCALE_SD = 1e-6


@dataclasses.dataclass(frozen=True)
class GainSampling:
    """Per-antenna gains sampled with the sky (:mod:`gcrsky.run.gains`; the model of :mod:`gcrsky.model.gains`).

    The run's draws are then the states of a Markov chain over (sky, gains, overall amplitude)
    (:func:`gcrsky.inference.joint_gain_step`), not independent draws: ``burn`` sweeps of burn-in
    (re-centred on the current gains after each half), then one kept state every ``thin`` sweeps.

    Attributes:
        modes: ``(Kf, Kt)`` smooth modes per gain in frequency (delay) and time (fringe rate);
            ``(1, 1)``: one complex gain per antenna (or feed) over the selection.
        basis: ``"dpss"``, ``"fourier"`` or ``"legendre"`` (:func:`gcrsky.model.gains.mode_basis`).
        sigma: prior standard deviation of each mode's coefficient (rms fractional gain error).
        burn: burn-in sweeps (>= 2: the linearisation point moves after each half).
        thin: sweeps per kept draw.
        gauge_moves: Metropolis moves along the amplitude-sky gauge orbit per sweep
            (:func:`gcrsky.inference.gauge_step`; 0 is plain Gibbs, which barely moves along it).
        applied: the overall amplitude ``gbar`` the gains start from (e.g. the square root of
            the autocorrelations' flux-scale ratio); the sampled amplitude is relative to it.
        scale_sd: prior sd of the amplitude ``q`` about 1 (relative to ``applied^2``): ``inf`` (the
            library's default) flat, the amplitude sampled; :data:`FIXED_SCALE_SD` (the command line's
            ``--amplitude fixed``, calibrated data) holds it at 1.
    """

    modes: tuple = (1, 1)
    basis: str = "dpss"
    sigma: float = 0.05
    burn: int = 200
    thin: int = 1
    gauge_moves: int = 4
    applied: float = 1.0
    scale_sd: float = math.inf

    def __post_init__(self):
        modes = tuple(self.modes)
        if len(modes) != 2 or any(isinstance(k, bool) or not isinstance(k, numbers.Integral) or k < 1 for k in modes):
            raise ValueError(f"gains.modes must be two integers >= 1 (Kf, Kt), got {self.modes!r}")
        object.__setattr__(self, "modes", tuple(int(k) for k in modes))
        check_choice("gains.basis", self.basis, BASES)
        for name in ("sigma", "applied"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, numbers.Real) or not (v > 0 and math.isfinite(v)):
                raise ValueError(f"gains.{name} must be a positive finite number, got {v!r}")
            object.__setattr__(self, name, float(v))
        v = self.scale_sd
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not v > 0:
            raise ValueError(f"gains.scale_sd must be a positive number (inf: flat), got {v!r}")
        object.__setattr__(self, "scale_sd", float(v))
        check_integer(self, "burn", "gains.burn", 2)
        check_integer(self, "thin", "gains.thin", 1)
        check_integer(self, "gauge_moves", "gains.gauge_moves", 0)

    def to_dict(self) -> dict:
        """The settings as a JSON-able dict (recorded with the run's settings).  ``scale_sd`` only where finite: the
        flat default records what runs recorded before it existed, so that they still resume."""
        d = {**dataclasses.asdict(self), "modes": list(self.modes)}
        if math.isinf(self.scale_sd):
            del d["scale_sd"]
        return d


#: Default fractional uncertainty of the sky model's overall scale (``AmplitudeSampling.model_sd``): the GSM's
#: stated accuracy, ~10 % (de Oliveira-Costa et al. 2008, MNRAS 388, 247: the model reproduces the input
#: surveys to ~10 %); absolute comparisons at 50-200 MHz (LWA1 LFSS, Dowell et al. 2017; EDGES, Monsalve et al.
#: 2021) find the GSM's scale off by 5-20 %: give 0.2 for that view.
AMPLITUDE_MODEL_SD = 0.1


@dataclasses.dataclass(frozen=True)
class AmplitudeSampling:
    """The overall amplitude per channel inferred with the sky (:mod:`gcrsky.run.amplitude`, DESIGN section 14).

    The data are ``q_f x`` the visibilities of the sky in K (``q`` multiplies a calibrated visibility);
    the sky is ``c (a0 + delta)`` with ``a0`` the prior's mean (a sky model: the GSM) and ``c ~ N(1,
    model_sd^2)`` its overall scale.  ``q`` per channel is drawn from its exact marginal, the sky given it
    exactly; with ``gains`` the per-antenna gains are a Gibbs block (a Markov chain).

    Attributes:
        model_sd: fractional uncertainty of the sky model's overall scale (:data:`AMPLITUDE_MODEL_SD`).
        gains: the per-antenna gains (:class:`GainSampling`: modes, basis, prior sd, burn-in, thinning;
            ``applied`` and ``gauge_moves`` are not used), or None (the amplitude alone: independent draws).
    """

    model_sd: float = AMPLITUDE_MODEL_SD
    gains: GainSampling | None = None

    def __post_init__(self):
        check_positive(self, "model_sd", "amplitude.model_sd")
        if self.gains is not None and not isinstance(self.gains, GainSampling):
            raise ValueError(f"amplitude.gains must be a GainSampling or None, got {self.gains!r}")

    def to_dict(self) -> dict:
        """The settings as a JSON-able dict (recorded with the run's settings as ``amplitude``)."""
        return {"model_sd": self.model_sd, "gains": None if self.gains is None else self.gains.to_dict()}


def check_positive(obj, name: str, where: str, *, zero: bool = False) -> None:
    """Set ``obj.name`` to its float value if positive (``zero``: or 0) and finite, else raise ``ValueError``
    naming ``where``."""
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
        check_choice("frequency.prior", self.prior, FREQ_PRIORS[1:])
        if self.beta is not None:
            if isinstance(self.beta, bool) or not isinstance(self.beta, numbers.Real) or not math.isfinite(self.beta):
                raise ValueError(f"frequency.beta must be a finite number or None, got {self.beta!r}")
            object.__setattr__(self, "beta", float(self.beta))
        check_positive(self, "xi", "frequency.xi")
        check_integer(self, "nbasis", "frequency.nbasis", 1, 8)
        check_positive(self, "basis_sigma", "frequency.basis_sigma")
        if self.nugget is None:
            object.__setattr__(self, "nugget", DEFAULT_NUGGET[self.prior])
        check_positive(self, "nugget", "frequency.nugget", zero=True)
        if not isinstance(self.fit, bool):
            raise ValueError(f"frequency.fit must be True or False, got {self.fit!r}")
        if self.fit and self.prior != "kernel":
            raise ValueError(f"frequency.fit fits the kernel's hyperparameters: it needs prior 'kernel', not "
                             f"{self.prior!r}")

    def to_dict(self) -> dict:
        """The settings as a JSON-able dict (recorded with the run's settings as ``frequency``)."""
        return dataclasses.asdict(self)


class DrawStage:
    """What a run samples and how (module doc); subclasses are frozen dataclasses.

    Attributes:
        name: the kind of run (``"joint"``, ``"independent"``, ``"frequency"``, ``"gains"``).
        files: the files this stage writes into the run's directory besides the standard
            ones (each also in :data:`gcrsky.run.output.RUN_FILES`, so refused, overwritten
            and resumed with the run).
    """

    name: ClassVar[str] = ""
    files: ClassVar[tuple[str, ...]] = ()

    def settings_block(self) -> dict:
        """The settings this stage adds to the run's (:meth:`gcrsky.run.RunSpec.settings`): JSON-able."""
        return {}

    def run_draws(self, prob, spec, run, st, watch) -> str:
        """The ``wiener`` stage and the draws into ``run.h5`` from batch ``run.start``; returns the path that
        ran and leaves the ``draws`` stage of ``st`` running."""
        raise NotImplementedError

    def elsewhere(self) -> bool:
        """True in a process that computes a share of the draws and writes nothing (see :meth:`run_share`)."""
        return False

    def run_share(self, prob, spec, watch) -> None:
        """This process's share of the draws, where :meth:`elsewhere` is True."""
        raise NotImplementedError

    def channels_block(self, prob, h5, warnings: list) -> dict:
        """The summary's ``channels`` block (:func:`gcrsky.run.frequency.channels_block`), channels independent."""
        return channels_block(prob, None, h5, warnings)

    def fit_problem(self, prob, h5):
        """The problem whose data the goodness of fit checks the Wiener filter against."""
        return prob

    def finish(self, prob, out, h5) -> dict:
        """After the draws of a run not yet summarised: this stage's top-level ``summary.json`` blocks
        (``{name: block}``, names among :class:`gcrsky.run.summary.RunSummary`'s fields) and its files
        (:attr:`files`) written into ``out``."""
        return {}


@dataclasses.dataclass(frozen=True)
class Joint(DrawStage):
    """One joint system over all channels (:func:`gcrsky.run.draws.joint_draws`): the default run."""

    name: ClassVar[str] = "joint"

    def run_draws(self, prob, spec, run, st, watch) -> str:
        """:func:`gcrsky.run.draws.joint_draws`."""
        return joint_draws(prob, spec, run, st, watch)


@dataclasses.dataclass(frozen=True)
class Independent(DrawStage):
    """The channels solved independently (:mod:`gcrsky.run.channels`; key scheme
    :data:`~gcrsky.parallel.channels.CHANNEL_KEY_SCHEME`: other, equally exact draws than a joint run's).

    Attributes:
        channels: ``"loop"`` one at a time, ``"devices"`` over this process's devices,
            ``"processes"`` over ``jax.distributed`` processes (only process 0 writes).
    """

    name: ClassVar[str] = "independent"
    channels: str = "loop"

    def __post_init__(self):
        check_choice("sampling.channels", self.channels, CHANNEL_MODES)

    def settings_block(self) -> dict:
        """``channels`` (the mode) and ``channel_key_scheme``."""
        return {"channels": self.channels, "channel_key_scheme": CHANNEL_KEY_SCHEME}

    def run_draws(self, prob, spec, run, st, watch) -> str:
        """:func:`gcrsky.run.channels.channel_draws`."""
        return channel_draws(prob, spec, run, st, watch)

    def elsewhere(self) -> bool:
        """A ``jax.distributed`` process other than 0 of a ``"processes"`` run."""
        return self.channels == "processes" and jax.process_index() != 0

    def run_share(self, prob, spec, watch) -> None:
        """:func:`gcrsky.run.channels.worker_channels`."""
        worker_channels(prob, spec, watch)


@dataclasses.dataclass(frozen=True)
class JointFrequency(DrawStage):
    """All channels sampled jointly under one frequency-coupled prior (:mod:`gcrsky.run.frequency`).

    Attributes:
        model: the :class:`FrequencyModel` (recorded in the settings as ``frequency``).
    """

    name: ClassVar[str] = "frequency"
    model: FrequencyModel = FrequencyModel()

    def __post_init__(self):
        if not isinstance(self.model, FrequencyModel):
            raise ValueError(f"sampling.model must be a FrequencyModel, got {self.model!r}")

    def settings_block(self) -> dict:
        """``frequency``: the model's settings."""
        return {"frequency": self.model.to_dict()}

    def run_draws(self, prob, spec, run, st, watch) -> str:
        """:func:`gcrsky.run.frequency.frequency_draws`."""
        return frequency_draws(prob, spec, run, st, watch)

    def channels_block(self, prob, h5, warnings: list) -> dict:
        """The ``channels`` block of a frequency-coupled run (flagged channels inpainted)."""
        return channels_block(prob, self.model, h5, warnings)


@dataclasses.dataclass(frozen=True)
class Gains(DrawStage):
    """Per-antenna gains sampled with the sky (:mod:`gcrsky.run.gains`): a chain over (sky, gains, amplitude).

    Attributes:
        gains: the :class:`GainSampling` (recorded in the settings as ``gains``).
    """

    name: ClassVar[str] = "gains"
    files: ClassVar[tuple[str, ...]] = (GAIN_FILE,)
    gains: GainSampling = GainSampling()

    def __post_init__(self):
        if not isinstance(self.gains, GainSampling):
            raise ValueError(f"sampling.gains must be a GainSampling, got {self.gains!r}")

    def settings_block(self) -> dict:
        """``gains``: the gain sampling's settings."""
        return {"gains": self.gains.to_dict()}

    def run_draws(self, prob, spec, run, st, watch) -> str:
        """:func:`gcrsky.run.gains.gain_draws`."""
        return gain_draws(prob, spec, run, st, watch)

    def fit_problem(self, prob, h5):
        """The problem with the gains of the Wiener filter's set-up applied (:func:`gcrsky.run.gains.gained_problem`)."""
        return gained_problem(prob, stored_gain_factor(h5))

    def finish(self, prob, out, h5) -> dict:
        """``{"gains": block}``: the ``gains`` block (:func:`gcrsky.run.gains.gain_summary`) with ``calibration_file``, the calh5 written
        (:func:`gcrsky.run.gains.write_gain_products`; None if the problem cannot say where its antennas are)."""
        block = gain_summary(prob, self.gains, h5)
        block["calibration_file"] = write_gain_products(prob, self.gains, out, h5)
        return {"gains": block}


@dataclasses.dataclass(frozen=True)
class Amplitude(DrawStage):
    """The amplitude per channel inferred with the sky (:mod:`gcrsky.run.amplitude`), gains optional.

    Attributes:
        amplitude: the :class:`AmplitudeSampling` (recorded in the settings as ``amplitude``).
    """

    name: ClassVar[str] = "amplitude"
    files: ClassVar[tuple[str, ...]] = ()
    amplitude: AmplitudeSampling = AmplitudeSampling()

    def __post_init__(self):
        if not isinstance(self.amplitude, AmplitudeSampling):
            raise ValueError(f"sampling.amplitude must be an AmplitudeSampling, got {self.amplitude!r}")

    def settings_block(self) -> dict:
        """``amplitude``: the amplitude sampling's settings."""
        return {"amplitude": self.amplitude.to_dict()}

    def run_draws(self, prob, spec, run, st, watch) -> str:
        """:func:`gcrsky.run.amplitude.amplitude_draws`."""
        return amplitude_draws(prob, spec, run, st, watch)

    def fit_problem(self, prob, h5):
        """The problem with the set-up's amplitude and gains divided out (:func:`gcrsky.run.amplitude.fit_problem`)."""
        return amplitude_fit_problem(prob, h5)

    def finish(self, prob, out, h5) -> dict:
        """The ``flux_scale`` and ``amplitude`` blocks (:func:`gcrsky.run.amplitude.amplitude_summary`)."""
        return amplitude_summary(prob, self.amplitude, h5)


@dataclasses.dataclass(frozen=True)
class BeamSampling:
    """Every antenna's beam perturbation sampled with the sky (:mod:`gcrsky.run.beams`; the model:
    :mod:`gcrsky.instrument.beammodes`, :mod:`gcrsky.inference.beams`, ``docs/beams.md``).

    Antenna ``i``'s voltage beam is ``A_0 (1 + sum_k c_ik(nu) f_k)``, ``f_k`` the Zernike modes of radial
    order 1 to ``nmax`` on a disc of 1.5 power FWHM (tilts: pointing; defocus: width; astigmatisms:
    ellipticity), ``c_ik(nu)`` ``freq_modes`` Legendre modes across the band.

    Attributes:
        nmax: the highest Zernike radial order (2: tilts, defocus, astigmatisms, 5 modes; 1: tilts only).
        piston: include the piston (an antenna's gain: leave it to the gains).
        sigma: prior sd of each coefficient (fractional voltage change at the disc's edge).
        mean_sigma: prior sd of the array's mean coefficient (a change common to every dish is nearly
            degenerate with the sky: small, so that the nominal beam is the array's mean), or None.
        freq_modes: Legendre modes per coefficient across the band (1: constant).
        burn: warm-up steps of the chain (discarded).
        thin: steps per kept draw.
        amplitude: the overall amplitude per channel inferred with the beams and the sky
            (:class:`AmplitudeSampling`, its ``gains`` None: the data as given are ``u X(theta) a`` with the sky
            model's scale ``c``: DESIGN section 14), or None (the data are calibrated: ``u = 1``).
        gains: per-antenna gains sampled with the beams and the sky, in the same collapsed move
            (:mod:`gcrsky.inference.beam_gains`; :class:`GainSampling`: its ``modes``, ``basis``, ``sigma`` and
            ``thin``, the steps per kept draw, which replaces ``thin`` above).  The gains are fitted with the beams
            (Newton, the linearisation point moved to the maximum) rather than burnt in, so ``burn`` does not apply
            (``burn`` above does); the overall amplitude is ``amplitude``'s, so ``applied`` must be 1 and
            ``scale_sd`` and ``gauge_moves`` do not apply.  None: the gains are the file's.
    """

    nmax: int = 2
    piston: bool = False
    sigma: float = 0.2
    mean_sigma: float | None = 0.02
    freq_modes: int = 1
    burn: int = 20
    thin: int = 1
    amplitude: AmplitudeSampling | None = None
    gains: GainSampling | None = None

    def __post_init__(self):
        check_integer(self, "nmax", "beams.nmax", 1, 4)
        if not isinstance(self.piston, bool):
            raise ValueError(f"beams.piston must be True or False, got {self.piston!r}")
        check_positive(self, "sigma", "beams.sigma")
        if self.mean_sigma is not None:
            check_positive(self, "mean_sigma", "beams.mean_sigma")
        check_integer(self, "freq_modes", "beams.freq_modes", 1, 8)
        check_integer(self, "burn", "beams.burn", 0)
        check_integer(self, "thin", "beams.thin", 1)
        if self.amplitude is not None and not isinstance(self.amplitude, AmplitudeSampling):
            raise ValueError(f"beams.amplitude must be an AmplitudeSampling or None, got {self.amplitude!r}")
        if self.amplitude is not None and self.amplitude.gains is not None:
            raise ValueError("beams.amplitude.gains: give the gains as beams.gains (the beams' own gain block), and "
                             "AmplitudeSampling(gains=None)")
        if self.gains is not None and not isinstance(self.gains, GainSampling):
            raise ValueError(f"beams.gains must be a GainSampling or None, got {self.gains!r}")
        if self.gains is not None and self.gains.applied != 1.0:
            raise ValueError(f"beams.gains.applied is {self.gains.applied:g}: with the beams the gains start at the "
                             "file's (1) and the overall amplitude is beams.amplitude's (give applied=1)")

    def to_dict(self) -> dict:
        """The settings as a JSON-able dict (recorded with the run's settings as ``beams``)."""
        out = dataclasses.asdict(self)
        out["amplitude"] = None if self.amplitude is None else self.amplitude.to_dict()
        if self.gains is None:  # what runs recorded before the gains could be sampled with the beams: they resume
            del out["gains"]
        else:
            out["gains"] = self.gains.to_dict()
        return out


@dataclasses.dataclass(frozen=True)
class Beams(DrawStage):
    """Every antenna's beam sampled with the sky (:mod:`gcrsky.run.beams`): a chain over (sky, beams).

    Attributes:
        beams: the :class:`BeamSampling` (recorded in the settings as ``beams``).
        nominal: the nominal beams, one pyuvdata beam per antenna of the problem (what it was built with:
            :func:`gcrsky.ingest.ingest_with_beams`); not a setting (the problem's ``config`` records them).
    """

    name: ClassVar[str] = "beams"
    files: ClassVar[tuple[str, ...]] = (BEAM_DIR, GAIN_FILE)
    beams: BeamSampling = BeamSampling()
    nominal: tuple = dataclasses.field(default=(), compare=False, repr=False)

    def __post_init__(self):
        if not isinstance(self.beams, BeamSampling):
            raise ValueError(f"sampling.beams must be a BeamSampling, got {self.beams!r}")
        object.__setattr__(self, "nominal", tuple(self.nominal))
        if not self.nominal:
            raise ValueError("sampling.nominal: give the nominal beams, one per antenna (gcrsky.ingest.ingest_with_beams)")

    def settings_block(self) -> dict:
        """``beams``: the beam sampling's settings."""
        return {"beams": self.beams.to_dict()}

    def run_draws(self, prob, spec, run, st, watch) -> str:
        """:func:`gcrsky.run.beams.beam_draws`."""
        return beam_draws(prob, self.nominal, spec, run, st, watch)

    def fit_problem(self, prob, h5):
        """The problem with the beams (and amplitude) of the Wiener filter's set-up
        (:func:`gcrsky.run.beams.beam_fit_problem`)."""
        return beam_fit_problem(prob, h5)

    def finish(self, prob, out, h5) -> dict:
        """``{"beams": block}`` (:func:`gcrsky.run.beams.beam_summary`) with ``beam_files``, the directory of
        per-antenna UVBeam files written (:func:`gcrsky.run.beams.write_beam_products`); with the amplitude
        inferred also the ``flux_scale`` and ``amplitude`` blocks (:func:`gcrsky.run.amplitude.amplitude_summary`);
        with gains the ``gains`` block (:func:`gcrsky.run.gains.beam_gain_summary`) and its calh5."""
        block = beam_summary(prob, self.beams, h5)
        block["beam_files"] = write_beam_products(prob, self.nominal, self.beams, out, h5)
        amp = {} if self.beams.amplitude is None else amplitude_summary(prob, self.beams.amplitude, h5, markov=True,
                                                                        gain_theta=False)
        if self.beams.gains is None:
            return {"beams": block, **amp}
        gains = beam_gain_summary(prob, self.beams.gains, h5)
        gains["fit_file_gains"] = fit_without_gains(prob, h5)
        gains["calibration_file"] = write_gain_products(prob, self.beams.gains, out, h5)
        return {"beams": block, **amp, "gains": gains}


#: The draw stages a run may hold (:attr:`gcrsky.run.RunSpec.sampling`).
STAGES = (Joint, Independent, JointFrequency, Gains, Amplitude, Beams)
