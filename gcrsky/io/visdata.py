"""What a visibility file says: :class:`Observation`, a plain container of NumPy arrays.

An :class:`Observation` holds a file's visibilities, flags and nsamples on regular
(product, channel, time, baseline) grids in gcrsky's pinned conventions, with the
autocorrelations, antennas, times, site, frequencies and the file's own metadata (units,
``pol_convention``, ``x_orientation``, phase type, telescope, history).  It holds no
physics: nothing is converted to K sr, combined into modelled products or weighted.
:func:`gcrsky.io.read_observation` reads one from any file pyuvdata reads;
:func:`gcrsky.model.problem_from_observation` turns one (plus beams) into a
:class:`~gcrsky.model.Problem`.

Conventions (``docs/ingest.md``):

* Baselines: the pair ``(i, j)`` (indices into the antenna arrays, antennas ordered by
  increasing antenna number, ``i < j``) has baseline ``x_j - x_i`` and visibility
  ``V_ij = <V_i^* V_j>``: pyuvdata's ``ant2 - ant1``.  A row stored as ``(ant_2, ant_1)``
  was conjugated (and its feed product reversed, ``xy`` <-> ``yx``) when reading.
* Missing samples: a baseline or time absent from the file is ``present == False`` and
  flagged, with zero data and nsample.
* Phase: the data are drift-scan ("unprojected"); a projected file has been unprojected
  by pyuvdata (``phase_type == "projected"`` records that it was).
* Units: as in the file (``vis_units``: ``"Jy"``, ``"K str"`` or ``"uncalib"``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["COMPASS_POLS", "POLS", "Observation", "feed_pol", "parse_products"]

#: The products gcrsky models: name -> the feed products of the file it combines
#: (:mod:`gcrsky.model.observed`; :func:`gcrsky.io.read_observation` reads those).
POLS = {"pI": ("xx", "yy"), "xx": ("xx",), "yy": ("yy",)}

#: Products named by compass direction (pyuvdata's ``ee``, ``nn``, ``en``, ``ne``): which feed they are depends on the
#: file's ``x_orientation`` (:func:`feed_pol`).
COMPASS_POLS = ("ee", "nn", "en", "ne")

#: How the data's phase was found in the file (:attr:`Observation.phase_type`) -> description.
PHASE_TYPES = {
    "unprojected": "unprojected (drift scan)",
    "projected": "projected in the file; unprojected by pyuvdata (UVData.unproject_phase)",
}

#: Characters of a file's history kept in :attr:`Observation.history`.
HISTORY_CHARS = 2000

_ARRAYS = {  # field -> (dtype, shape in terms of the axis lengths)
    "vis": (np.complex128, ("Npols", "Nf", "Nt", "Nbl")),
    "flags": (np.bool_, ("Npols", "Nf", "Nt", "Nbl")),
    "nsamples": (np.float64, ("Npols", "Nf", "Nt", "Nbl")),
    "present": (np.bool_, ("Nt", "Nbl")),
    "integration_time_s": (np.float64, ("Nt", "Nbl")),
    "autos": (np.complex128, ("Npols", "Nf", "Nt", "Nant")),
    "auto_flags": (np.bool_, ("Npols", "Nf", "Nt", "Nant")),
    "auto_nsamples": (np.float64, ("Npols", "Nf", "Nt", "Nant")),
    "auto_present": (np.bool_, ("Nt", "Nant")),
    "antenna_numbers": (np.int64, ("Nant",)),
    "antenna_names": (np.str_, ("Nant",)),
    "antpos_enu_m": (np.float64, ("Nant", 3)),
    "antpairs": (np.int64, ("Nbl", 2)),
    "times_jd": (np.float64, ("Nt",)),
    "lsts_rad": (np.float64, ("Nt",)),
    "site_ecef_m": (np.float64, (3,)),
    "freqs_hz": (np.float64, ("Nf",)),
    "channel_width_hz": (np.float64, ("Nf",)),
    "polarizations": (np.int64, ("Npols",)),
    "telescope_antenna_numbers": (np.int64, ("Ntel",)),
    "telescope_antenna_names": (np.str_, ("Ntel",)),
}


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Observation:
    """A visibility file's contents on regular grids (module docstring).

    The arrays are NumPy, read-only views (not copies: arrays passed in stay the caller's).

    Axis lengths: ``Npols`` feed products read, ``Nf`` channels, ``Nt`` integrations
    (unique times), ``Nbl`` antenna pairs with cross-correlations, ``Nant`` antennas in
    them, ``Ntel`` antennas of the file's telescope.

    Attributes:
        vis: (Npols, Nf, Nt, Nbl) complex cross-correlations ``V_ij`` in ``vis_units``
            (0 where absent; anything, NaN included, where flagged).
        flags: (Npols, Nf, Nt, Nbl) bool, True = flagged or absent.
        nsamples: (Npols, Nf, Nt, Nbl) the file's nsample (0 where absent).
        present: (Nt, Nbl) bool, whether the file holds the pair at that time.
        integration_time_s: (Nt, Nbl) seconds (0 where absent).
        autos: (Npols, Nf, Nt, Nant) complex autocorrelations ``V_ii`` in ``vis_units``
            (real for ``xx``, ``yy``; 0 where absent).
        auto_flags: (Npols, Nf, Nt, Nant) bool, True = flagged or absent.
        auto_nsamples: (Npols, Nf, Nt, Nant) nsample of the autos (0 where absent).
        auto_present: (Nt, Nant) bool, whether the file holds ``V_ii`` at that time.
        antenna_numbers: (Nant,) the file's antenna numbers, increasing.
        antenna_names: (Nant,) their names.
        antpos_enu_m: (Nant, 3) East, North, Up metres about the site
            (``Telescope.get_enu_antpos``).
        antpairs: (Nbl, 2) indices ``(i, j)``, ``i < j``, into the antenna arrays; baseline
            ``x_j - x_i``.
        times_jd: (Nt,) UTC Julian dates, increasing.
        lsts_rad: (Nt,) the file's local apparent sidereal times, radians.
        site_ecef_m: (3,) the telescope location, Earth-centred Earth-fixed metres
            (``location``: an astropy ``EarthLocation``).
        freqs_hz: (Nf,) channel centres, Hz.
        channel_width_hz: (Nf,) channel widths, Hz.
        polarizations: (Npols,) pyuvdata polarisation numbers (-5 ``xx``, -6 ``yy``,
            -7 ``xy``, -8 ``yx``; ``pol_names``), in the file's order.
        x_orientation: ``"east"``, ``"north"`` or None: where feed x points
            (``Telescope.get_x_orientation_from_feeds``).
        vis_units: ``"Jy"``, ``"K str"`` or ``"uncalib"``.
        pol_convention: ``"sum"``, ``"avg"`` or None (absent in the file).
        phase_type: ``"unprojected"`` (drift scan in the file) or ``"projected"`` (phased
            in the file, unprojected by pyuvdata when reading).
        telescope_name: the file's telescope name.
        telescope_antenna_numbers, telescope_antenna_names: (Ntel,) every antenna the file's
            telescope lists, used or not (per-antenna beams are given by these).
        source: the file's path, or ``"<UVData object>"``.
        history: the first :data:`HISTORY_CHARS` characters of the file's history.
        selection: the selection applied when reading (pyuvdata ``select`` keywords,
            JSON-friendly).
        nblts_read: baseline-time rows read (autocorrelations included).
        notes: what reading did that a user should know (e.g. the unprojection).
        files: the files read when the observation joins several (``()`` for one file).
        time_file: (Nt,) with ``files``: the index into ``files`` of each integration's file.
    """

    vis: np.ndarray
    flags: np.ndarray
    nsamples: np.ndarray
    present: np.ndarray
    integration_time_s: np.ndarray
    autos: np.ndarray
    auto_flags: np.ndarray
    auto_nsamples: np.ndarray
    auto_present: np.ndarray
    antenna_numbers: np.ndarray
    antenna_names: np.ndarray
    antpos_enu_m: np.ndarray
    antpairs: np.ndarray
    times_jd: np.ndarray
    lsts_rad: np.ndarray
    site_ecef_m: np.ndarray
    freqs_hz: np.ndarray
    channel_width_hz: np.ndarray
    polarizations: np.ndarray
    x_orientation: str | None
    vis_units: str
    pol_convention: str | None
    phase_type: str
    telescope_name: str
    telescope_antenna_numbers: np.ndarray
    telescope_antenna_names: np.ndarray
    source: str
    history: str = ""
    selection: dict = dataclasses.field(default_factory=dict)
    nblts_read: int = 0
    notes: tuple = ()
    files: tuple = ()
    time_file: tuple = ()

    def __post_init__(self):
        sizes: dict = {}
        for name, (dtype, shape) in _ARRAYS.items():
            arr = np.asarray(getattr(self, name), dtype=dtype).view()  # no copy; read-only through this view
            if arr.ndim != len(shape):
                raise ValueError(f"Observation.{name} must have {len(shape)} axes {shape}, got shape {arr.shape}")
            for axis, (want, got) in enumerate(zip(shape, arr.shape)):
                want = sizes.setdefault(want, got) if isinstance(want, str) else want
                if got != want:
                    raise ValueError(f"Observation.{name} has shape {arr.shape}; axis {axis} ({shape[axis]}) "
                                     f"must be {want} as in the other fields")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        self._check_values()
        object.__setattr__(self, "notes", tuple(str(n) for n in self.notes))

    def _check_values(self):
        if self.phase_type not in PHASE_TYPES:
            raise ValueError(f"Observation.phase_type must be one of {sorted(PHASE_TYPES)}, got {self.phase_type!r}")
        if self.pol_convention not in (None, "sum", "avg"):
            raise ValueError(f"unknown pol_convention {self.pol_convention!r} (pyuvdata's are 'sum' and 'avg')")
        pairs = self.antpairs
        if pairs.size and (pairs.min() < 0 or pairs.max() >= self.n_antennas or np.any(pairs[:, 0] >= pairs[:, 1])):
            raise ValueError("Observation.antpairs must be antenna indices (i, j) with i < j")
        if np.any(np.diff(self.times_jd) <= 0) or np.any(np.diff(self.antenna_numbers) <= 0):
            raise ValueError("Observation.times_jd and antenna_numbers must be strictly increasing")

    def __repr__(self) -> str:
        return (f"Observation({self.source!r}: {self.n_antennas} antennas, {self.n_baselines} baselines, "
                f"{self.n_times} times, {self.n_freqs} channels, products {list(self.pol_names)}, "
                f"{self.vis_units}, flagged {self.flagged_fraction:.3g})")

    # ---------------------------------------------------------------- sizes and names

    @property
    def n_pols(self) -> int:
        return int(self.polarizations.size)

    @property
    def n_freqs(self) -> int:
        return int(self.freqs_hz.size)

    @property
    def n_times(self) -> int:
        return int(self.times_jd.size)

    @property
    def n_baselines(self) -> int:
        return int(self.antpairs.shape[0])

    @property
    def n_antennas(self) -> int:
        return int(self.antenna_numbers.size)

    @property
    def pol_names(self) -> tuple[str, ...]:
        """The products' names in feed terms (``"xx"``, ``"yy"``, ``"xy"``, ``"yx"``, ...)."""
        from pyuvdata.utils.pol import polnum2str

        return tuple(str(polnum2str(int(p))) for p in self.polarizations)

    @property
    def file_pol_names(self) -> tuple[str, ...]:
        """The products' names as pyuvdata's ``get_pols`` gives them (``"ee"``, ``"nn"`` where x points east)."""
        from pyuvdata.utils.pol import polnum2str

        return tuple(str(polnum2str(int(p), x_orientation=self.x_orientation)) for p in self.polarizations)

    def pol_index(self, name: str) -> int:
        """Index on the product axis of the product ``name`` (``"xx"``, ...); an error naming what is there."""
        names = self.pol_names
        if name not in names:
            raise ValueError(f"the observation holds products {list(names)}, not {name!r}")
        return names.index(name)

    # ---------------------------------------------------------------- derived

    @property
    def baseline_antnums(self) -> np.ndarray:
        """(Nbl, 2) the antenna numbers of each pair."""
        return self.antenna_numbers[self.antpairs]

    @property
    def baselines_enu_m(self) -> np.ndarray:
        """(Nbl, 3) baseline vectors ``x_j - x_i``, ENU metres."""
        return self.antpos_enu_m[self.antpairs[:, 1]] - self.antpos_enu_m[self.antpairs[:, 0]]

    @property
    def baseline_lengths_m(self) -> np.ndarray:
        """(Nbl,) baseline lengths, metres."""
        return np.linalg.norm(self.baselines_enu_m, axis=1)

    @property
    def usable(self) -> np.ndarray:
        """(Npols, Nf, Nt, Nbl) bool: unflagged with a positive nsample."""
        return ~self.flags & (self.nsamples > 0)

    @property
    def flagged_fraction(self) -> float:
        """Fraction of the cross-correlation samples flagged, absent or with nsample <= 0 (mean over products)."""
        if self.vis.size == 0:
            return 1.0
        return float(np.mean([np.mean(self.flags[k] | (self.nsamples[k] <= 0)) for k in range(self.n_pols)]))

    @property
    def has_autos(self) -> bool:
        """Whether the file holds any autocorrelation of the observation's antennas."""
        return bool(np.any(self.auto_present))

    @property
    def location(self):
        """The site as an astropy ``EarthLocation`` (from :attr:`site_ecef_m`, exactly)."""
        from astropy.coordinates import EarthLocation

        return EarthLocation.from_geocentric(*self.site_ecef_m, unit="m")

    @property
    def site_lat_lon_alt(self) -> tuple[float, float, float]:
        """(latitude deg, longitude deg, altitude m) of the site (WGS84)."""
        loc = self.location
        return float(loc.lat.deg), float(loc.lon.deg), float(loc.height.to_value("m"))

    @property
    def lst_hours(self) -> np.ndarray:
        """(Nt,) the file's LSTs in hours, [0, 24)."""
        return np.mod(np.rad2deg(self.lsts_rad) / 15.0, 24.0)

    @property
    def phase_description(self) -> str:
        """How the data's phase was found and treated (``Problem.config.conventions["phase"]``)."""
        return PHASE_TYPES[self.phase_type]


def parse_products(pol) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(modelled products, feed products they need) for ``pol``: ``"pI"``, ``"xx"``, ``"yy"``, a tuple, ``"xx,yy"``."""
    if isinstance(pol, str):
        prods = tuple(p.strip() for p in pol.split(",")) if "," in pol else (pol,)
    else:
        prods = tuple(pol)
    bad = [p for p in prods if p not in POLS]
    if not prods or bad:
        raise ValueError(f"pol must be one of {sorted(POLS)} or a tuple of them (e.g. ('xx', 'yy')), got {pol!r}")
    if len(set(prods)) != len(prods):
        raise ValueError(f"pol names a product twice: {pol!r}")
    raw = tuple(dict.fromkeys(r for p in prods for r in POLS[p]))
    return prods, raw


def _product_names(pol) -> tuple[str, ...]:
    if isinstance(pol, str):
        return tuple(p.strip() for p in pol.split(",")) if "," in pol else (pol,)
    return tuple(pol)


def feed_pol(pol, x_orientation: str | None):
    """``pol`` with compass names (``ee``, ``nn``, ``en``, ``ne``) as feed names, through ``x_orientation``.

    Feed x points ``x_orientation``: east: ``ee`` = ``xx``, ``nn`` = ``yy``, ``en`` = ``xy``;
    north: ``nn`` = ``xx``, ``ee`` = ``yy``, ``ne`` = ``xy`` (pyuvdata's ``polstr2num``).
    Other names are returned unchanged, in ``pol``'s form (a string, ``"a,b"`` or a tuple).

    Raises:
        ValueError: compass names with an unknown ``x_orientation``.
    """
    names = _product_names(pol)
    if not any(n.lower() in COMPASS_POLS for n in names):
        return pol
    if x_orientation not in ("east", "north"):
        raise ValueError(f"pol {pol!r} names products by compass direction, but the file does not say where feed x "
                         f"points (x_orientation {x_orientation!r}): name them xx / yy")
    x, y = ("e", "n") if x_orientation == "east" else ("n", "e")
    table = {x: "x", y: "y"}
    out = tuple("".join(table[c] for c in n.lower()) if n.lower() in COMPASS_POLS else n for n in names)
    if isinstance(pol, str):
        return ",".join(out) if "," in pol else out[0]
    return out
