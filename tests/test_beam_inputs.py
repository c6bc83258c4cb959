"""Beam files as users give them, valid and hostile (issue 26): interpolated power never negative, unusable
beams refused when read (naming the file and the problem), and a run that fails after its draws finished by
``--resume``.

matvis' HERA dipole E-field beam (2-degree az/za grid, channels 100 and 101 MHz) is a valid beam whose
power, interpolated with pyuvdata's cubic ``az_za_map_coordinates`` spline (what the response uses), rings
below 0 next to a null: at 100.9 MHz (between its channels), az 90 deg, za ~17.4 deg, down to -5.4e-6 of the
peak.  Its power version is made with ``UVBeam.efield_to_power`` (matvis ships only the E-field); on disk
with the cross polarisations (pyuvdata 3.2.8's ``write_beamfits`` writes a real-valued power beam with two
polarisations in a layout its own reader refuses, "spectral window axis larger than one").
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

pytest.importorskip("matvis")

from gcrsky import cli  # noqa: E402
from gcrsky.checks.matvis import HERA_SITE, matvis_hera_beam_path, observing_times, random_sky, site  # noqa: E402
from gcrsky.cli.runs import EXIT_AFTER_DRAWS  # noqa: E402
from gcrsky.instrument.beamfiles import read_beam  # noqa: E402
from gcrsky.instrument.beamprep import prepare_beam  # noqa: E402
from gcrsky.instrument.beams import beam_amplitude, beam_fwhm_rad  # noqa: E402
from gcrsky.instrument.polarization import cross_power_kernel  # noqa: E402

F_MID = np.array([100.9e6])  # between the dipole's channels (100, 101 MHz)
LMAX, NSIDE = 4, 32  # nside 32: the quadrature resolves the fringes (reach ~80 <= 3 nside - 1)


def _dipole():
    from pyuvdata import UVBeam

    return UVBeam.from_file(str(matvis_hera_beam_path()))


def _power(cross=False):
    return _dipole().efield_to_power(calc_cross_pols=cross, inplace=False)


def _patch():
    """Directions around the ringing: az 80-100 deg, za 10-25 deg, 0.1 x 0.05 deg."""
    az, za = np.meshgrid(np.deg2rad(np.linspace(80, 100, 201)), np.deg2rad(np.linspace(10, 25, 301)))
    return az.ravel(), za.ravel()


def _spline(power_beam, az, za, freqs):
    """pyuvdata's interpolant of a power beam as the response calls it, unclipped: (Npols, Nf, Npix)."""
    from pyuvdata import BeamInterface

    return np.real(BeamInterface(power_beam).compute_response(
        az_array=az, za_array=za, freq_array=freqs, freq_interp_kind="linear",
        interpolation_function="az_za_map_coordinates", check_azza_domain=False))[0]


@pytest.mark.parametrize("kind", ["efield", "power"])
def test_hera_dipole_power_between_channels_is_non_negative(kind, caplog):
    az, za = _patch()
    beam = _dipole() if kind == "efield" else _power()
    prep, rec = prepare_beam(beam, F_MID, x_orientation="east")
    # the old interpolation, computed directly: the same spline of the same power, not clipped
    raw = _spline(prep.efield_to_power(calc_cross_pols=False, inplace=False) if kind == "efield" else prep,
                  az, za, F_MID)[0, 0]  # xx
    assert raw.min() < -1e-6  # negative control: the spline rings below 0 here (-5.4e-6 of the peak)
    with caplog.at_level(logging.WARNING, logger="gcrsky.instrument.beams"):
        amp2 = beam_amplitude(prep, az, za, F_MID)[0] ** 2  # the unpolarised response's power
        kern = cross_power_kernel(prep, prep, "xx", az, za, F_MID)[0].real  # the polarised response's
    for got in (amp2, kern):
        assert np.all(got >= 0) and np.all(np.isfinite(got))
        pos = raw >= 0
        np.testing.assert_allclose(got[pos], raw[pos], rtol=1e-12, atol=1e-15)  # the spline wherever it was >= 0
        assert np.all(got[~pos] == 0)
    assert "clipped to 0" in caplog.text or kind == "power"  # first clipping of a beam: a warning (once per name)
    fwhm = np.rad2deg(beam_fwhm_rad(prep, F_MID[0]))
    assert 13 < fwhm < 15.5  # the dipole's ~14.3 deg


# ---------------------------------------------------------------- unusable beams, refused when read


def _write(uvb, path):
    uvb.write_beamfits(str(path), clobber=True, run_check=False)
    return path


def _hostile(kind):
    """A beam that cannot be used and the words its refusal must contain."""
    p = _power(cross=True)
    d = np.array(p.data_array)
    if kind == "nan":
        d[0, 0, 1, 40, 7] = np.nan
        return p, d, "NaN or infinite"
    if kind == "zero":
        return p, d * 0, "zero everywhere"
    if kind == "sign":  # the whole power negative: a sign error
        return p, -d, "nowhere positive"
    if kind == "deep_negative":  # sidelobes at -5 % of the peak
        d[0, :2, :, 50:60, :] = -0.05
        return p, d, "negative, down to -0.05"
    if kind == "widespread_negative":  # every sidelobe beyond za 60 deg negated: shallow but everywhere
        d[0, :2, :, 30:, :] *= -1
        return p, d, "of its power values are negative"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["nan", "zero", "sign", "deep_negative", "widespread_negative"])
def test_unusable_beam_refused_at_read_time(kind, tmp_path):
    p, d, words = _hostile(kind)
    p.data_array = d
    path = _write(p, tmp_path / f"{kind}.beamfits")
    with pytest.raises(ValueError, match=f"beam file {path}") as err:
        read_beam(path)
    assert words in str(err.value)
    with pytest.raises(ValueError, match=words.replace("-", r"\-").replace("(", r"\(")):
        prepare_beam(str(path), F_MID, x_orientation="east")


def test_nan_efield_beam_and_other_files_refused(tmp_path):
    e = _dipole()
    e.data_array = e.data_array * np.nan
    path = _write(e, tmp_path / "nan_efield.beamfits")
    with pytest.raises(ValueError, match=r"131040 of 131040 beam values are NaN or infinite, on 2 channels"):
        read_beam(path)
    text = tmp_path / "notes.beamfits"
    text.write_text("not a beam")
    with pytest.raises(ValueError, match=f"beam file {text}: pyuvdata cannot read it as a beam \\(OSError"):
        read_beam(text)
    with pytest.raises(FileNotFoundError, match="no such file"):
        read_beam(tmp_path / "missing.beamfits")


def test_shallow_negative_power_in_a_file_is_clipped_and_said(tmp_path, caplog):
    p = _power(cross=True)
    d = np.array(p.data_array)
    d[0, 0, :, 45, :3] = -1e-3  # a few values ringing at 1e-3 of the peak: an interpolant's, clipped
    p.data_array = d
    path = _write(p, tmp_path / "ringing.beamfits")
    with caplog.at_level(logging.WARNING, logger="gcrsky.instrument.beamfiles"):
        beam, rec = read_beam(path)
    assert "6 tabulated power values below 0" in caplog.text and str(path) in caplog.text
    clip = rec["negative_power_clipped"]
    assert clip["count"] == 6 and clip["min_relative_to_peak"] == pytest.approx(-1e-3, rel=1e-3)
    assert np.real(beam.data_array[0, :2]).min() >= 0


def test_fwhm_of_a_beam_dark_at_the_zenith_is_an_error():
    p = _power()
    d = np.array(p.data_array)
    d[..., :3, :] = 0.0  # zero power within 4 deg of the zenith
    p.data_array = d
    with pytest.raises(ValueError, match="power at the zenith is 0"):
        beam_fwhm_rad(p, 100e6)


# ---------------------------------------------------------------- runs


@pytest.fixture(scope="module")
def uvh5(tmp_path_factory):
    """4 antennas, 3 integrations, the dipole's 101 MHz channel relabelled 100.9 MHz (between its channels)."""
    from gcrsky.checks.uvsim import simulate_uvdata

    pos = np.array([[0.0, 0, 0], [14.6, 0, 0], [7.3, 12.64, 0], [21.9, 12.64, 0]])
    out = simulate_uvdata(pos, site(*HERA_SITE), observing_times("2025-03-21T18:00:00", 1.0, 3),
                          np.array([100e6, 101e6]), _dipole(), random_sky(LMAX, 3), LMAX, nside_matvis=NSIDE,
                          dt_s=10.0, dnu_hz=1e5, noise_seed=0)
    uvd = out.uvdata.select(freq_chans=[1], inplace=False)
    uvd.freq_array = F_MID.copy()
    path = tmp_path_factory.mktemp("beam_inputs") / "obs.uvh5"
    uvd.write_uvh5(str(path))
    return path


def _run_args(uvh5, beam, out, *more):
    return ["run", "--data", str(uvh5), "--beam", str(beam), "--lmax", str(LMAX), "--nside", str(NSIDE),
            "--band-limit", "truncate", "--flux-scale", "accept", "--nsamples", "4", "--batch", "2",
            "--no-progress", "--out", str(out), *more]


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["efield", "power"])
def test_run_with_the_hera_dipole_between_its_channels(uvh5, kind, tmp_path, capsys):
    import json

    beam = matvis_hera_beam_path() if kind == "efield" else _write(_power(cross=True), tmp_path / "power.beamfits")
    out = tmp_path / "run"
    assert cli.main(_run_args(uvh5, beam, out)) == 0
    s = json.loads((out / "summary.json").read_text())
    fwhm = s["per_frequency"][0]["fwhm_deg"]
    assert 13 < fwhm < 15.5 and s["draws_finite"]
    assert (out / "posterior_mean.fits").exists() and (out / "fig4_sky_maps.png").exists()


@pytest.mark.slow
def test_unusable_beam_is_a_message_before_any_draw(uvh5, tmp_path, capsys):
    p, d, words = _hostile("nan")
    p.data_array = d
    path = _write(p, tmp_path / "nan.beamfits")
    out = tmp_path / "run"
    assert cli.main(_run_args(uvh5, path, out)) == 2
    err = capsys.readouterr().err
    assert f"beam file {path}" in err and words in err and "Traceback" not in err
    assert not (out / "results.h5").exists()


@pytest.mark.slow
def test_failure_after_the_draws_then_resume_finishes(uvh5, tmp_path, capsys, monkeypatch):
    """A failure in the last stage (the products): exit 4 with what to do; --resume, without the set-up or a
    draw, writes the products, maps and summary from the kept draws (bit for bit the same draws)."""
    import gcrsky.run.draws as D
    import gcrsky.run.runner as R
    from gcrsky.io import read_draws, read_results_state

    out = tmp_path / "run"
    args = _run_args(uvh5, matvis_hera_beam_path(), out, "--no-plots")

    def boom(*a, **k):
        raise OSError("disk full (injected)")

    with monkeypatch.context() as m:
        m.setattr(R, "write_products", boom)
        assert cli.main(args) == EXIT_AFTER_DRAWS
    err = capsys.readouterr().err
    assert "failed after its draws, in stage 'write'" in err and "disk full (injected)" in err
    assert "--resume" in err and "--overwrite" in err and "Traceback" not in err
    state = read_results_state(out / "results.h5")
    assert state.draws_done and not state.complete and not (out / "summary.json").exists()
    kept = read_draws(out / "results.h5").draws.tobytes()

    def no_setup(*a, **k):
        raise AssertionError("a resumed run whose draws are complete must not set up again")

    with monkeypatch.context() as m:
        m.setattr(D, "_setup", no_setup)
        assert cli.main(args + ["--resume"]) == 0
    assert read_results_state(out / "results.h5").complete
    assert read_draws(out / "results.h5").draws.tobytes() == kept
    for f in ("summary.json", "posterior_mean.fits", "posterior_std.fits", "posterior_mean_alm.fits"):
        assert (out / f).exists(), f


@pytest.mark.slow
def test_run_with_a_beam_that_never_falls_to_half_finishes(uvh5, tmp_path, capsys):
    """A flat (uniform) power beam is valid but has no FWHM: the run finishes without beam-region metrics."""
    import json

    p = _power(cross=True)
    d = np.zeros_like(p.data_array)
    d[0, :2] = 1.0  # xx, yy uniform; cross polarisations 0
    p.data_array = d
    out = tmp_path / "run"
    assert cli.main(_run_args(uvh5, _write(p, tmp_path / "flat.beamfits"), out)) == 0
    m = json.loads((out / "summary.json").read_text())["per_frequency"][0]
    assert m["fwhm_deg"] is None and "no beam-region metrics" in m["fwhm_note"] and "std_fwhm_median" not in m
    assert (out / "fig4_sky_maps.png").exists()
