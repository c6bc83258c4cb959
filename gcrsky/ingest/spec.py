"""What to make of a visibility file: :class:`IngestSpec`, a frozen, validated set of settings.

One value replaces :func:`gcrsky.ingest.from_uvdata`'s keywords, grouped by stage (each
keyword is a field of one group, under its old name):

- :class:`Selection`: what is read (``pol``, channels, times, antennas, baselines);
- :class:`DataChecks`: calibration applied and the checks (``cal``, ``flag_outliers``, ``flux_scale``);
- :class:`BeamSpec`: the beams and how they are prepared;
- :class:`PriorSpec`: the prior, its scale and its mean;
- and on :class:`IngestSpec` itself the model: ``lmax``, ``nside``, ``band_limit``, ``frame_pad``,
  ``noise``, ``compress``, ``memory_budget``.

A bad value raises ``ValueError`` naming the field when the spec is built, before any file is
read.  :meth:`IngestSpec.from_keywords` builds one from the old keywords and
:meth:`IngestSpec.keywords` gives them back (the CLI records them in ``summary.json``).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any

from ..model.bandlimit import BAND_LIMIT_MODES
from .beamprior import PRIOR_MEANS
from .datachecks import AMPLITUDE_MODES, FLUX_SCALE_MODES

__all__ = ["BeamSpec", "DataChecks", "IngestSpec", "PriorSpec", "Selection"]

#: ``noise``'s named kinds (else a per-component sigma).
NOISE_KINDS = ("autos", "diff")


def _one_of(name: str, value, allowed) -> None:
    if not (isinstance(value, str) or value is None) or value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


def _flag(name: str, value) -> None:
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be True or False, got {value!r}")


def _positive(name: str, value, *, optional: bool = True) -> None:
    if value is None and optional:
        return
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value) and value > 0
    if not ok:
        raise ValueError(f"{name} must be a positive finite number{' or None' if optional else ''}, got {value!r}")


def _integer(name: str, value, low: int, *, optional: bool = True) -> None:
    if value is None and optional:
        return
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
        raise ValueError(f"{name} must be an integer >= {low}{' or None' if optional else ''}, got {value!r}")


def _pair(name: str, value) -> None:
    if value is None:
        return
    try:
        lo, hi = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (lo, hi) of numbers or None, got {value!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name} must be a pair of finite numbers, got {value!r}")


@dataclasses.dataclass(frozen=True)
class Selection:
    """What is read of the file (:func:`gcrsky.io.read_observation`'s selection).

    Attributes:
        pol: the modelled product(s): ``"pI"`` (``xx + yy``), ``"xx"``, ``"yy"``, ``("xx", "yy")`` /
            ``"xx,yy"``; compass names (``"ee"``, ``"nn"``) through the file's ``x_orientation``.
        freq_chans: channel indices, or None (all).
        freq_range_hz: ``(lo, hi)`` in Hz, or None.
        times_jd: times (JD) to keep, or None.
        lst_range_hours: ``(lo, hi)`` LST in hours (``(22, 2)`` wraps), or None.
        antennas: antenna numbers or names to keep (pairs among them), or None.
        bls: antenna pairs to keep, or None.
    """

    pol: Any = "pI"
    freq_chans: Any = None
    freq_range_hz: Any = None
    times_jd: Any = None
    lst_range_hours: Any = None
    antennas: Any = None
    bls: Any = None

    def __post_init__(self):
        if not isinstance(self.pol, (str, tuple, list)) or not self.pol:
            raise ValueError(f"pol must be a product name or a sequence of them, got {self.pol!r}")
        if not isinstance(self.pol, str) and not all(isinstance(p, str) for p in self.pol):
            raise ValueError(f"pol must name products by strings, got {self.pol!r}")
        _pair("freq_range_hz", self.freq_range_hz)
        if self.freq_range_hz is not None and not float(self.freq_range_hz[0]) < float(self.freq_range_hz[1]):
            raise ValueError(f"freq_range_hz must have lo < hi, got {self.freq_range_hz!r}")
        _pair("lst_range_hours", self.lst_range_hours)
        if isinstance(self.freq_chans, (str, bytes)):
            raise ValueError(f"freq_chans must be channel indices, got {self.freq_chans!r}")


@dataclasses.dataclass(frozen=True)
class DataChecks:
    """Calibration and the data checks (:mod:`gcrsky.ingest.datachecks`).

    Attributes:
        cal: a gain solutions file (calfits, calh5) applied first, a list of them (one per visibility file), or
            None.
        flag_outliers: flag the noise-excess outliers (:mod:`gcrsky.model.datachecks`).
        flux_scale: ``"accept"`` (the data / GSM autos ratio recorded, a warning outside the
            bounds; the library's default), ``"check"`` (refused outside them: the CLI's default)
            or ``"off"``; where the amplitude is inferred it never refuses (the ratio is a check).
        amplitude: ``"fixed"`` (the library's default: the data taken as calibrated, ``"uncalib"``
            refused), ``"auto"`` (the CLI's: inferred where the data are not absolutely calibrated,
            :func:`gcrsky.ingest.datachecks.amplitude_checks`) or ``"infer"``; a Problem whose amplitude
            is inferred is run by :class:`gcrsky.run.Amplitude` (``checks["amplitude"]`` says which).
    """

    cal: Any = None
    flag_outliers: bool = True
    flux_scale: str = "accept"
    amplitude: str = "fixed"

    def __post_init__(self):
        _flag("flag_outliers", self.flag_outliers)
        _one_of("flux_scale", self.flux_scale, FLUX_SCALE_MODES)
        _one_of("amplitude", self.amplitude, AMPLITUDE_MODES)


@dataclasses.dataclass(frozen=True)
class BeamSpec:
    """The antennas' beams and how they are prepared (:func:`gcrsky.instrument.beamprep.prepare_beam`).

    Attributes:
        beam: a pyuvdata beam object, a beam file's path, a dict antenna number / name -> beam,
            or a list in the file's ``antenna_numbers`` order; or None.
        dish_diameter_m: instead of ``beam``: a Gaussian beam with the Airy FWHM of that dish (m).
        beam_normalization: ``"peak"`` (a physical UVBeam peak-normalised) or ``"physical"``.
        beam_freq_scaling: a single-frequency beam's ``"none"`` or ``"lambda"`` scaling, or None.
        accept_x_orientation_mismatch: whether the beam's feed x may point elsewhere than the file's.

    A Problem needs one of ``beam`` and ``dish_diameter_m`` (``inspect`` neither); never both.
    """

    beam: Any = None
    dish_diameter_m: float | None = None
    beam_normalization: str = "peak"
    beam_freq_scaling: str | None = None
    accept_x_orientation_mismatch: bool = False

    def __post_init__(self):
        _positive("dish_diameter_m", self.dish_diameter_m)
        if self.beam is not None and self.dish_diameter_m is not None:
            raise ValueError("give beam or dish_diameter_m, not both")
        _one_of("beam_normalization", self.beam_normalization, ("peak", "physical"))
        _one_of("beam_freq_scaling", self.beam_freq_scaling, (None, "none", "lambda"))
        _flag("accept_x_orientation_mismatch", self.accept_x_orientation_mismatch)


@dataclasses.dataclass(frozen=True)
class PriorSpec:
    """The prior on the ICRS coefficients.

    Attributes:
        prior: None / ``"gsm"`` (isotropic, zero mean, the GSM's C_l), ``"flat"``, a
            :class:`~gcrsky.model.Prior`, a C_l array ((lmax+1,) or (Nf, lmax+1), K^2) or file
            (``.npy`` or text), or a HEALPix map / alm FITS file (the prior's mean, ICRS, K).
        prior_scale: factor on the prior variance (> 0).
        prior_mean: None / ``"zero"`` (the prior's own mean) or ``"gsm"`` (the GSM's coefficients).
    """

    prior: Any = None
    prior_scale: float = 1.0
    prior_mean: str | None = None

    def __post_init__(self):
        _positive("prior_scale", self.prior_scale, optional=False)
        _one_of("prior_mean", self.prior_mean, (None,) + PRIOR_MEANS)


#: The groups of :class:`IngestSpec` and their types, by field name.
GROUPS = {"selection": Selection, "checks": DataChecks, "beam": BeamSpec, "prior": PriorSpec}


@dataclasses.dataclass(frozen=True)
class IngestSpec:
    """How a visibility file becomes a :class:`~gcrsky.model.Problem` (module docstring).

    Attributes:
        nside: HEALPix nside of the response quadrature (a Problem needs it; ``inspect`` sizes
            the response with it if given).
        lmax: degree of the ICRS coefficients; None: every used baseline's reach at the highest
            frequency, capped by memory (:func:`gcrsky.model.bandlimit.observation_lmax`).
        band_limit: rows whose reach exceeds ``lmax``: ``"cut"`` (the CLI's default),
            ``"marginalise"`` (the sky above lmax as noise) or ``"truncate"`` (the library's default,
            with a warning: right for data simulated at lmax).
        frame_pad: degree margin of the ICRS -> of-date map (>= 0).
        noise: ``"autos"`` (radiometer equation), ``"diff"`` (time-adjacent differences), or each
            raw product's per-component sigma in the file's units (broadcastable to (Nf, Nt, Nbl)).
        compress: merge redundant baselines (identical responses only).
        memory_budget: bytes the read (and the band-limit cap) may use, or None (the free memory).
        selection, checks, beam, prior: the groups (:class:`Selection`, :class:`DataChecks`,
            :class:`BeamSpec`, :class:`PriorSpec`).
    """

    nside: int | None = None
    lmax: int | None = None
    band_limit: str = "truncate"
    frame_pad: int = 4
    noise: Any = "autos"
    compress: bool = True
    memory_budget: float | None = None
    selection: Selection = Selection()
    checks: DataChecks = DataChecks()
    beam: BeamSpec = BeamSpec()
    prior: PriorSpec = PriorSpec()

    def __post_init__(self):
        _integer("nside", self.nside, 1)
        _integer("lmax", self.lmax, 0)
        _one_of("band_limit", self.band_limit, BAND_LIMIT_MODES)
        _integer("frame_pad", self.frame_pad, 0, optional=False)
        if isinstance(self.noise, str) and self.noise not in NOISE_KINDS:
            raise ValueError(f"noise must be 'autos', 'diff' or a per-component sigma, got {self.noise!r}")
        _flag("compress", self.compress)
        _positive("memory_budget", self.memory_budget)
        for name, kind in GROUPS.items():
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name} must be a {kind.__name__}, got {type(getattr(self, name)).__name__}")

    @classmethod
    def from_keywords(cls, **keywords) -> IngestSpec:
        """The spec of :func:`gcrsky.ingest.from_uvdata`'s keywords (each the field of that name).

        Raises:
            TypeError: an unknown keyword (as a function would).
            ValueError: a bad value (naming the field).
        """
        groups: dict[str, dict] = {name: {} for name in GROUPS}
        top = {}
        owner = {f.name: name for name, kind in GROUPS.items() for f in dataclasses.fields(kind)}
        tops = {f.name for f in dataclasses.fields(cls)} - set(GROUPS)
        for key, value in keywords.items():
            if key in owner:
                groups[owner[key]][key] = value
            elif key in tops:
                top[key] = value
            else:
                raise TypeError(f"unknown ingest setting {key!r}")
        return cls(**top, **{name: GROUPS[name](**kw) for name, kw in groups.items()})

    def keywords(self) -> dict:
        """Every setting by its keyword name (the inverse of :meth:`from_keywords`), in field order."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in GROUPS}
        for name in GROUPS:
            group = getattr(self, name)
            out.update({f.name: getattr(group, f.name) for f in dataclasses.fields(group)})
        return out

    def replace(self, **keywords) -> IngestSpec:
        """A copy with some settings changed, by keyword name (validated again)."""
        return type(self).from_keywords(**{**self.keywords(), **keywords})
