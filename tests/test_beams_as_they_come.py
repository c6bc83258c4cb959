"""Beams as they come (gcrsky.instrument.beamprep, gcrsky.ingest.beamprior): normalisation, frequencies, images, feeds.

One small matvis simulation (4 antennas at HERA, 3 integrations, 100 and 101 MHz, a white
sky at lmax 4) made with matvis' HERA dipole E-field beam (peak-normalised) is read back
with that beam scaled to "physical" units (x sqrt(8243): the HERA CST beam's peak power):
peak-normalised by default it models the file as the original does; kept physical (the
negative control) the model is 8243 x the data.  The beam-image conversion is checked on a
synthetic SIN image whose off-centre blob lies east by the FITS convention (RA increases
to the east, CDELT1 < 0), and on HERABEAM.FITS (FWHM ~4.8 deg).
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

pytest.importorskip("matvis")

from gcrsky.checks.matvis import HERA_SITE, matvis_hera_beam_path, observing_times, random_sky, site  # noqa: E402
from gcrsky.checks.uvsim import simulate_uvdata  # noqa: E402
from gcrsky.ingest.beamprior import feed_pol_of  # noqa: E402
from gcrsky.ingest.uvdata import from_uvdata  # noqa: E402
from gcrsky.instrument.beamprep import (  # noqa: E402
    check_x_orientation,
    image_beam,
    prepare_beam,
    resample_beam,
)
from gcrsky.instrument.beams import beam_amplitude, beam_fwhm_rad  # noqa: E402
from gcrsky.io.visdata import feed_pol  # noqa: E402

LMAX, NSIDE = 4, 32  # nside 32: the quadrature resolves the fringes (from_uvdata refuses 16 here)
FREQS = np.array([100e6, 101e6])
PEAK = 8243.0  # the HERA CST E-field beam's peak power in physical (directivity) units
from conftest import REAL  # noqa: E402


def _hera():
    from pyuvdata import UVBeam

    return UVBeam.from_file(str(matvis_hera_beam_path()))


@pytest.fixture(scope="module")
def sim():
    """4 antennas (a 14.6 m rhombus), 3 integrations over 1 h, 2 channels, the HERA dipole beam; noiseless copy."""
    pos = np.array([[0.0, 0, 0], [14.6, 0, 0], [7.3, 12.64, 0], [21.9, 12.64, 0]])
    a = random_sky(LMAX, 3)
    out = simulate_uvdata(pos, site(*HERA_SITE), observing_times("2025-03-21T18:00:00", 1.0, 3), FREQS, _hera(), a,
                          LMAX, nside_matvis=NSIDE, dt_s=10.0, dnu_hz=1e5, noise_seed=0)
    noiseless = out.uvdata.copy()
    noiseless.data_array = out.model
    return noiseless, a


def _problem(uvd, beam, **kw):
    return from_uvdata(uvd, lmax=LMAX, nside=NSIDE, beam=beam, pol="xx", compress=False, **kw)


def _amplitude(prob, a):
    """Least-squares factor of the model X a on the data: 1 for a right model."""
    v = np.asarray(prob.visibilities(np.broadcast_to(a, (FREQS.size, a.size))))
    d = np.asarray(prob.data)
    return float(np.real(np.vdot(v, d)) / np.real(np.vdot(v, v)))


def test_physical_beam_is_peak_normalised_and_kept_physical_is_wrong_by_the_peak(sim, caplog):
    uvd, a = sim
    hera = _hera()
    phys = hera.copy()
    phys.data_array = phys.data_array * np.sqrt(PEAK)
    phys.data_normalization = "physical"
    ref = _problem(uvd, hera)
    with caplog.at_level(logging.INFO, logger="gcrsky.instrument.beamprep"):
        got = _problem(uvd, phys)
    assert "peak-normalised" in caplog.text
    rec = got.config.checks["beam"]
    assert rec["normalization_found"] == "physical" and rec["normalization_used"] == "peak"
    np.testing.assert_allclose(rec["peak_power_found"], PEAK * 1.0002, rtol=2e-4)  # the beam's own peak is 1.0002
    # normalised by its peak power (1.0002 x the file's "peak" beam): the model is the original's to that factor
    np.testing.assert_allclose(np.asarray(got.response), np.asarray(ref.response) / 1.0002, rtol=3e-4)
    assert abs(_amplitude(ref, a) - 1) < 0.03  # matvis vs gcrsky at nside 32, lmax 4: the dipole's ~1e-2 agreement
    assert abs(_amplitude(got, a) - 1) < 0.03
    kept = _problem(uvd, phys, beam_normalization="physical")  # negative control: the sky comes out 8243x too faint
    assert kept.config.checks["beam"]["normalization_used"] == "physical"
    assert abs(_amplitude(kept, a) * PEAK - 1) < 0.03


def test_solid_angle_beam_refused():
    b = _hera()
    b.data_normalization = "solid_angle"
    with pytest.raises(ValueError, match="solid-angle normalised"):
        prepare_beam(b, FREQS, x_orientation="east")


def _clipped_power_beam():
    """A chromatic Gaussian power beam on 4 channels 100-190 MHz, clipped to 0 below 0.1 (as beam images are)."""
    from pyuvdata.analytic_beam import GaussianBeam

    ch = np.array([100e6, 130e6, 160e6, 190e6])
    g = GaussianBeam(sigma=np.deg2rad(8.0), spectral_index=-2.0, reference_frequency=100e6)
    uvb = g.to_uvbeam(freq_array=ch, beam_type="power", axis1_array=np.deg2rad(np.arange(0, 360, 5.0)),
                      axis2_array=np.deg2rad(np.linspace(0, 90, 181)))
    uvb.data_array = np.where(uvb.data_array.real < 0.1, 0.0, uvb.data_array).astype(uvb.data_array.dtype)
    uvb.data_normalization = "peak"
    return uvb


def test_frequency_interpolation_keeps_power_non_negative():
    from pyuvdata import BeamInterface

    uvb = _clipped_power_beam()
    f = np.array([103e6, 112e6, 121e6])
    za = np.deg2rad(np.linspace(0, 30, 601))
    az = np.zeros_like(za)
    raw = np.real(BeamInterface(uvb).compute_response(az_array=az, za_array=za, freq_array=f, freq_interp_kind="cubic",
                                                      interpolation_function="az_za_map_coordinates"))
    assert raw.min() < -1e-3  # negative control: pyuvdata's cubic frequency interpolation of the clipped beam
    prep, rec = resample_beam(uvb, f)
    assert "linearly" in rec["frequency"] and np.all(np.asarray(prep.data_array) >= 0)
    amp = beam_amplitude(prep, az, za, f)  # spatial spline undershoot clipped: finite amplitudes, FWHM defined
    assert np.all(np.isfinite(amp)) and np.all(amp >= 0)
    w = [beam_fwhm_rad(prep, x) for x in f]
    assert np.all(np.isfinite(w)) and w[0] > w[1] > w[2]


def test_single_frequency_beam_needs_an_explicit_scaling():
    uvb = _clipped_power_beam().select(freq_chans=[0], inplace=False)
    f = np.array([100e6, 125e6])
    with pytest.raises(ValueError, match="freq_scaling='none'.*'lambda'.*--beam-freq-scaling"):
        resample_beam(uvb, f)
    same, _ = resample_beam(uvb, f, "none")
    scaled, rec = resample_beam(uvb, f, "lambda")
    w_same = [beam_fwhm_rad(same, x) for x in f]
    w_lam = [beam_fwhm_rad(scaled, x) for x in f]
    assert abs(w_same[1] / w_same[0] - 1) < 1e-9
    # size ~ 1/nu: sin(za_half) scales as nu0/nu (za_half ~ 9.4 deg: sin vs angle differs by 0.5 %)
    np.testing.assert_allclose(np.sin(w_lam[1] / 2) / np.sin(w_lam[0] / 2), 100 / 125, rtol=2e-3)
    assert rec["freq_scaling"] == "lambda"
    with pytest.raises(ValueError, match="freq_scaling must be one of"):
        resample_beam(uvb, f, "linear")


def _write_sin_image(path, img, *, ctype=("RA---SIN", "DEC--SIN"), freq=150e6, cdelt=0.25):
    from astropy.io import fits

    h = fits.Header()
    n = img.shape[0]
    for i, (ct, cd, cv) in enumerate(zip(ctype, (-cdelt, cdelt), (120.0, -30.7)), start=1):
        h[f"CTYPE{i}"], h[f"CDELT{i}"], h[f"CRPIX{i}"], h[f"CRVAL{i}"] = ct, cd, (n + 1) / 2, cv
    h["CTYPE3"], h["CRVAL3"], h["CDELT3"], h["CRPIX3"] = "FREQ", freq, 1e6, 1.0
    h["CTYPE4"], h["CRVAL4"], h["CDELT4"], h["CRPIX4"] = "STOKES", 1.0, 1.0, 1.0
    fits.PrimaryHDU(img[None, None].astype(np.float32), header=h).writeto(path)
    return path


def _image(n=121, blob_dx=0):
    """A Gaussian beam (sigma 3 deg at the centre) plus a 0.5 blob ``blob_dx`` pixels along the image's x axis."""
    y, x = np.mgrid[:n, :n] - (n - 1) / 2
    img = np.exp(-(x**2 + y**2) * 0.25**2 / (2 * 3.0**2))
    img += 0.5 * np.exp(-((x - blob_dx) ** 2 + y**2) * 0.25**2 / (2 * 1.0**2))
    return np.where(img < 1e-4, 0.0, img)


def test_image_beam_is_converted_with_east_at_az_zero(tmp_path):
    # x pixel index decreasing = RA increasing (CDELT1 < 0) = east for a zenith image: blob 40 px (10 deg) to the east
    path = _write_sin_image(tmp_path / "b.fits", _image(blob_dx=-40))
    uvb = image_beam(path)
    za = np.deg2rad([0.0, 10.0])
    east = beam_amplitude(uvb, np.array([0.0, 0.0]), za, np.array([150e6]))[0] ** 2
    west = beam_amplitude(uvb, np.array([np.pi, np.pi]), za, np.array([150e6]))[0] ** 2
    north = beam_amplitude(uvb, np.array([np.pi / 2] * 2), za, np.array([150e6]))[0] ** 2
    assert abs(east[0] - 1) < 1e-3  # peak-normalised at the zenith
    # the blob: l = sin(10 deg) east, so 0.5 plus the main lobe exp(-(sin 10 / sin 3 ...)) there
    assert east[1] > 0.45 and west[1] < 0.05 and north[1] < 0.05
    assert uvb.get_x_orientation_from_feeds() == "east"


def test_image_beams_refused_with_what_is_needed(tmp_path):
    with pytest.raises(ValueError, match="orthographic \\(SIN\\).*az/za beam file"):
        image_beam(_write_sin_image(tmp_path / "car.fits", _image(), ctype=("RA---CAR", "DEC--CAR")))
    big = _image(n=41)  # 10 deg across: the beam is not mapped until it falls to 0
    with pytest.raises(ValueError, match="border.*falls to 0"):
        image_beam(_write_sin_image(tmp_path / "cut.fits", big))


def test_herabeam_fits_is_converted():
    path = REAL / "HERABEAM.FITS"
    if not path.exists():
        pytest.skip("the real HERA files are not here")
    with pytest.raises(ValueError, match="--beam-freq-scaling"):
        prepare_beam(str(path), [140e6, 150e6], x_orientation="east")
    b, rec = prepare_beam(str(path), [140e6, 149.951177498e6, 160e6], freq_scaling="lambda", x_orientation="east")
    assert "SIN" in rec["kind"] and rec["x_orientation"]["check"].startswith("not needed")
    # a Stokes-I image has no feed orientation: a north-x file takes it too (issue 39: it was refused)
    _, north = prepare_beam(str(path), [150e6], freq_scaling="lambda", x_orientation="north")
    assert north["x_orientation"]["check"].startswith("not needed") and north["x_orientation"]["file"] == "north"
    w = np.rad2deg([beam_fwhm_rad(b, f) for f in (140e6, 149.951177498e6, 160e6)])
    assert abs(w[1] - 4.8) < 0.1  # the README's FWHM ~4.8 deg
    np.testing.assert_allclose(w[[0, 2]] / w[1], [149.951 / 140, 149.951 / 160], rtol=5e-3)


def test_x_orientation_mismatch_caught(sim):
    uvd, _ = sim
    north = _hera()
    north.set_feeds_from_x_orientation("north")
    with pytest.raises(ValueError, match="feed x points east.*north.*--accept-x-orientation-mismatch"):
        _problem(uvd, north)
    ok = _problem(uvd, north, accept_x_orientation_mismatch=True)
    assert ok.config.checks["beam"]["x_orientation"]["check"] == "MISMATCH accepted"
    assert _problem(uvd, _hera()).config.checks["beam"]["x_orientation"] == {"file": "east", "beam": "east",
                                                                             "check": "agree"}
    from pyuvdata.analytic_beam import GaussianBeam

    assert "not needed" in check_x_orientation(GaussianBeam(diameter=14.0), "north")["x_orientation"]["check"]


def test_compass_pol_names(sim):
    uvd, _ = sim
    assert feed_pol("ee", "east") == "xx" and feed_pol("nn", "east") == "yy"
    assert feed_pol("nn", "north") == "xx" and feed_pol("ee,nn", "north") == "yy,xx"
    assert feed_pol(("en", "ne"), "east") == ("xy", "yx") and feed_pol("pI", None) == "pI"
    with pytest.raises(ValueError, match="x_orientation"):
        feed_pol("ee", None)
    ee = from_uvdata(uvd, lmax=LMAX, nside=NSIDE, beam=_hera(), pol="ee", compress=False)
    xx = _problem(uvd, _hera())
    np.testing.assert_array_equal(np.asarray(ee.data), np.asarray(xx.data))
    assert ee.config.checks["pol"] == {"given": "ee", "as": "xx", "x_orientation": "east"}
    with pytest.raises(ValueError, match="pol 'en' is 'xy' where feed x points east"):  # cross products: not modelled
        feed_pol_of(uvd, "en")
    real = REAL / "zen.2458098.45361.HH_downselected.uvh5"
    if real.exists():  # the H1C file: pols ee/nn, x_orientation east
        assert feed_pol_of(str(real), "nn,ee")[0] == "yy,xx"


def test_response_kernel_of_a_clipped_power_beam_is_non_negative():
    """The response's kernel of a power beam (pyuvdata's cubic spatial spline) is clipped at 0: measured undershoot
    of the clipped beam ~1e-3 of the peak before clipping (the negative control: pyuvdata's own evaluation)."""
    from pyuvdata import BeamInterface

    from gcrsky.instrument.polarization import cross_power_kernel

    uvb, _ = resample_beam(_clipped_power_beam(), np.array([130e6]))
    za = np.deg2rad(np.linspace(0, 40, 2001))
    az = np.full_like(za, 0.3)
    raw = np.real(BeamInterface(uvb).compute_response(az_array=az, za_array=za, freq_array=np.array([130e6]),
                                                      interpolation_function="az_za_map_coordinates"))
    assert raw.min() < 0
    k = cross_power_kernel(uvb, uvb, "xx", az, za, np.array([130e6]))
    assert np.all(k.real >= 0) and np.all(np.isfinite(k))
    np.testing.assert_allclose(k.real, np.clip(raw[0, 0], 0, None), atol=1e-12)


def test_prior_mean_gsm_through_from_uvdata(sim):
    from gcrsky.model.skyprior import gsm_cl, gsm_prior_mean

    uvd, _ = sim
    p = _problem(uvd, _hera(), prior_mean="gsm")
    np.testing.assert_allclose(np.asarray(p.prior.mean), gsm_prior_mean(FREQS, LMAX), rtol=1e-12)
    np.testing.assert_allclose(1 / np.asarray(p.prior.inv_var)[:, 0], gsm_cl(FREQS, LMAX)[:, 0], rtol=1e-12)
    rec = p.config.checks["prior"]
    assert rec["mean"].startswith("GSM coefficients") and rec["gsm_cl_table_range_hz"] == [30e6, 250e6]
    assert "GSM mean" in p.config.prior
    zero = _problem(uvd, _hera())
    assert zero.config.checks["prior"]["mean"] == "zero" and not np.any(np.asarray(zero.prior.mean))
    with pytest.raises(ValueError, match="flat prior has no mean"):
        _problem(uvd, _hera(), prior="flat", prior_mean="gsm")
    with pytest.raises(ValueError, match="prior_mean must be one of"):
        _problem(uvd, _hera(), prior_mean="map")


def test_out_of_band_prior_refused_before_the_beam_is_read(sim):
    uvd, _ = sim
    high = uvd.copy()
    high.freq_array = high.freq_array + 160e6  # 260-261 MHz: beyond the GSM C_l table
    with pytest.raises(ValueError, match="GSM C_l table covers 30-250 MHz"):
        from_uvdata(high, lmax=LMAX, nside=NSIDE, beam="/nonexistent/beam.fits", pol="xx")


@pytest.fixture(scope="module")
def uvh5(sim, tmp_path_factory):
    path = tmp_path_factory.mktemp("beams") / "obs.uvh5"
    sim[0].write_uvh5(str(path))
    return path


def test_cli_beam_options(uvh5, tmp_path, capsys):
    import json

    from gcrsky import cli

    image = REAL / "HERABEAM.FITS"
    if image.exists():
        rc = cli.main(["run", "--data", str(uvh5), "--beam", str(image), "--out", str(tmp_path / "a"), "--no-progress",
                       "--lmax", str(LMAX), "--band-limit", "truncate", "--flux-scale", "accept"])
        assert rc == 2 and "--beam-freq-scaling" in capsys.readouterr().err
    assert cli.main(["inspect", str(uvh5), "--json", "--pol", "nn"]) == 0
    assert json.loads(capsys.readouterr().out)["modelled_products"] == ["yy"]
    hera = tmp_path / "hera_physical.beamfits"
    phys = _hera()
    phys.data_array = phys.data_array * np.sqrt(PEAK)
    phys.data_normalization = "physical"
    phys.write_beamfits(str(hera))
    out = tmp_path / "run"
    rc = cli.main(["run", "--data", str(uvh5), "--beam", str(hera), "--pol", "ee", "--prior-mean", "gsm", "--lmax",
                   str(LMAX), "--band-limit", "truncate", "--flux-scale", "accept", "--nside", str(NSIDE), "--nsamples", "4", "--batch", "4",
                   "--no-progress", "--no-plots", "--out", str(out)])
    assert rc == 0
    checks = json.loads((out / "summary.json").read_text())["data_checks"]
    assert checks["beam"]["file"] == str(hera) and checks["beam"]["normalization_used"] == "peak"
    assert checks["pol"]["as"] == "xx" and checks["prior"]["mean"].startswith("GSM")


def test_efield_beam_power_between_channels_is_non_negative():
    """A clipped E-field beam on 4 channels keeps its channels; the power the response interpolates cubically between
    them (pyuvdata's, after efield_to_power) undershoots 0 (the negative control) and is clipped where evaluated."""
    from pyuvdata import BeamInterface
    from pyuvdata.analytic_beam import GaussianBeam

    from gcrsky.instrument.polarization import cross_power_kernel

    ch = np.array([100e6, 130e6, 160e6, 190e6])
    g = GaussianBeam(sigma=np.deg2rad(8.0), spectral_index=-2.0, reference_frequency=100e6)
    uvb = g.to_uvbeam(freq_array=ch, beam_type="efield", axis1_array=np.deg2rad(np.arange(0, 360, 5.0)),
                      axis2_array=np.deg2rad(np.linspace(0, 90, 181)))
    uvb.data_array = np.where(np.abs(uvb.data_array) ** 2 < 0.1, 0.0, uvb.data_array)
    uvb.data_normalization = "peak"
    prep, rec = prepare_beam(uvb, np.array([112e6]), x_orientation="east")
    assert prep is uvb and "cubically" in rec["frequency"]
    za = np.deg2rad(np.linspace(0, 30, 601))
    az = np.zeros_like(za)
    pw = uvb.efield_to_power(calc_cross_pols=False, inplace=False)
    raw = np.real(BeamInterface(pw).compute_response(az_array=az, za_array=za, freq_array=np.array([112e6]),
                                                     freq_interp_kind="cubic",
                                                     interpolation_function="az_za_map_coordinates"))
    assert raw.min() < -1e-3
    k = cross_power_kernel(prep, prep, "xx", az, za, np.array([112e6]))
    assert np.all(k.real >= 0)
