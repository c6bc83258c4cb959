"""The ingest's settings (:class:`gcrsky.ingest.IngestSpec`): validation, the old keywords, one builder for the CLI.

* every bad value is refused when the spec is built, naming the field;
* the defaults are ``from_uvdata``'s keyword defaults before the spec existed (written out here);
* ``from_uvdata(file, **kw)`` and ``ingest(file, IngestSpec(...))`` give the same Problem bit for bit on
  the real HERA file (calibrated, a band-limit marginalised);
* ``gcrsky run --data`` and ``gcrsky inspect`` build their spec with the same builder.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from conftest import H1C  # noqa: E402
from conftest import H1C_CAL as CAL  # noqa: E402

from gcrsky.ingest import BeamSpec, DataChecks, IngestSpec, PriorSpec, Selection, from_uvdata, ingest  # noqa: E402

#: ``from_uvdata``'s keyword defaults as they were (gcrsky.io.uvdata before the spec; nside had none).
OLD_DEFAULTS = {
    "lmax": None, "beam": None, "dish_diameter_m": None, "pol": "pI", "prior": None, "prior_scale": 1.0,
    "noise": "autos", "freq_chans": None, "freq_range_hz": None, "times_jd": None, "lst_range_hours": None,
    "antennas": None, "bls": None, "compress": True, "frame_pad": 4, "memory_budget": None,
    "beam_normalization": "peak", "beam_freq_scaling": None, "accept_x_orientation_mismatch": False,
    "prior_mean": None, "band_limit": "truncate", "cal": None, "flag_outliers": True, "flux_scale": "accept",
    "amplitude": "fixed",  # issue 38's keyword: the library keeps the old behaviour (the CLI's default is auto)
}


def test_defaults_are_the_old_keyword_defaults():
    kw = IngestSpec().keywords()
    assert kw.pop("nside") is None
    assert kw == OLD_DEFAULTS
    assert IngestSpec.from_keywords(nside=32) == IngestSpec(nside=32)


def test_keywords_round_trip_and_groups():
    spec = IngestSpec.from_keywords(nside=16, lmax=4, pol=("xx", "yy"), freq_chans=[1, 2], cal="c.calfits",
                                    flux_scale="check", beam="b.fits", beam_freq_scaling="lambda", prior="flat",
                                    prior_scale=2.0, band_limit="cut")
    assert spec.selection == Selection(pol=("xx", "yy"), freq_chans=[1, 2])
    assert spec.checks == DataChecks(cal="c.calfits", flux_scale="check")
    assert spec.beam == BeamSpec(beam="b.fits", beam_freq_scaling="lambda")
    assert spec.prior == PriorSpec(prior="flat", prior_scale=2.0)
    assert IngestSpec.from_keywords(**spec.keywords()) == spec
    assert spec.replace(lmax=6).lmax == 6 and spec.replace(lmax=6).selection == spec.selection
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.lmax = 3


BAD = [
    ("nside", 0), ("nside", 16.0), ("lmax", -1), ("lmax", True), ("band_limit", "clip"), ("frame_pad", -1),
    ("noise", "radiometer"), ("compress", 1), ("memory_budget", 0), ("memory_budget", float("inf")),
    ("pol", ""), ("pol", 3), ("freq_range_hz", (2e8, 1e8)), ("freq_range_hz", (1e8,)), ("lst_range_hours", "22-2"),
    ("freq_chans", "1,2"), ("flag_outliers", "yes"), ("flux_scale", "refuse"), ("dish_diameter_m", -14.0),
    ("beam_normalization", "area"), ("beam_freq_scaling", "nu"), ("accept_x_orientation_mismatch", None),
    ("prior_scale", 0.0), ("prior_scale", float("nan")), ("prior_mean", "map"),
]


@pytest.mark.parametrize("field,value", BAD, ids=[f"{f}={v!r}" for f, v in BAD])
def test_each_bad_value_is_refused_naming_its_field(field, value):
    with pytest.raises(ValueError, match=field):
        IngestSpec.from_keywords(**{field: value})


def test_refusals_of_the_whole():
    with pytest.raises(ValueError, match="give beam or dish_diameter_m, not both"):
        IngestSpec.from_keywords(beam="b.fits", dish_diameter_m=14.0)
    with pytest.raises(ValueError, match="selection must be a Selection"):
        IngestSpec(selection={"pol": "xx"})
    with pytest.raises(TypeError, match="unknown ingest setting 'dish_diameter'"):
        IngestSpec.from_keywords(dish_diameter=14.0)
    with pytest.raises(TypeError, match="not both"):
        from_uvdata("x.uvh5", IngestSpec(nside=16), lmax=4)
    with pytest.raises(ValueError, match="nside must be given"):
        ingest("x.uvh5", IngestSpec())
    with pytest.raises(TypeError, match="spec must be an IngestSpec"):
        ingest("x.uvh5", {"nside": 16})


def _leaves(prob):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(
        {f.name: getattr(prob, f.name) for f in dataclasses.fields(prob) if f.name != "config"})]


@pytest.mark.skipif(not H1C.exists(), reason="the real HERA files are not there")
def test_keywords_and_spec_give_the_same_problem_bit_for_bit():
    """H1C, its omnical solutions applied, one channel, lmax 4 with the sky above it marginalised."""
    kw = dict(lmax=4, nside=64, dish_diameter_m=14.0, freq_chans=[20], cal=CAL, band_limit="marginalise")
    a = from_uvdata(H1C, **kw)
    spec = IngestSpec(nside=64, lmax=4, band_limit="marginalise", selection=Selection(freq_chans=[20]),
                      checks=DataChecks(cal=CAL), beam=BeamSpec(dish_diameter_m=14.0))
    b = ingest(H1C, spec)
    la, lb = _leaves(a), _leaves(b)
    assert len(la) == len(lb) > 5
    assert all(x.dtype == y.dtype and np.array_equal(x, y, equal_nan=x.dtype.kind in "fc") for x, y in zip(la, lb))
    assert json.dumps(a.config.checks, sort_keys=True, default=str) == json.dumps(b.config.checks, sort_keys=True,
                                                                                  default=str)
    assert a.config.checks["flux_scale"]["mode"] == "accept" and "band_limit" in a.config.checks


def test_the_cli_builds_one_spec_for_run_and_inspect():
    from gcrsky.cli.parser import build_parser

    parser = build_parser()
    run = parser.parse_args(["run", "--data", "f.uvh5", "--dish-diameter", "14", "--chans", "1,2", "--lmax", "5",
                             "--pol", "xx,yy", "--freq-range", "100", "120", "--no-compress", "--prior", "flat"])
    ins = parser.parse_args(["inspect", "f.uvh5", "--dish-diameter", "14", "--chans", "1,2", "--lmax", "5",
                             "--pol", "xx,yy", "--freq-range", "100", "120"])
    from gcrsky.cli.options import ingest_spec

    r, i = ingest_spec(run, run=True), ingest_spec(ins, run=False)
    assert r.selection == i.selection == Selection(pol=("xx", "yy"), freq_chans=[1, 2], freq_range_hz=(1e8, 1.2e8))
    assert r.checks == i.checks == DataChecks(flux_scale="check")  # the CLI refuses an off flux scale by default
    assert r.beam == i.beam == BeamSpec(dish_diameter_m=14.0)
    # prior_mean None: the prior's own mean, or the GSM's where the amplitude is inferred (issue 38)
    assert (r.lmax, r.band_limit, r.compress, r.prior.prior, r.prior.prior_mean) == (5, "cut", False, "flat", None)
    assert (i.lmax, i.band_limit, i.compress, i.prior) == (5, "truncate", True, PriorSpec())
