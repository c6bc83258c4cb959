"""Pre-fit data checks (:mod:`gcrsky.model.datachecks`) on small synthetic Observations and the H1C file.

The synthetic Observation is built here independently of the checks: a constant sky per
(channel, baseline) plus complex white noise whose per-component variance is the radiometer
equation's ``A_i A_j / (2 dt dnu N)`` for the autos ``A`` written into the file.  So the
noise excess has expectation exactly 1 on clean data, and injected RFI (a time-varying
signal of known power) has a known excess.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import H1C  # noqa: E402

from gcrsky.io.visdata import Observation
from gcrsky.model.datachecks import (
    MAX_DRIFT_RAD,
    dead_channels,
    drift_phase_rad,
    find_outliers,
    flag_outliers,
    flagged_antennas,
    noise_excess,
    outlier_rule,
    refuse_empty,
)

if not H1C.exists():
    H1C = Path("/work/shared/data/real/zen.2458098.45361.HH_downselected.uvh5")


def synthetic(seed=0, nf=24, nt=8, nant=5, dt=10.0, dnu=1e5, nsamples=1.0):
    """A clean Observation (module docstring): 2 products xx, yy; autos 100 +- 20 % per antenna and channel."""
    rng = np.random.default_rng(seed)
    pairs = np.array([(i, j) for i in range(nant) for j in range(i + 1, nant)])
    nbl = len(pairs)
    autos = 100.0 * (1 + 0.2 * rng.uniform(-1, 1, (2, nf, 1, nant))) * np.ones((1, 1, nt, 1))
    var = autos[:, :, :, pairs[:, 0]] * autos[:, :, :, pairs[:, 1]] / (2 * dt * dnu * nsamples)
    sky = rng.normal(size=(2, nf, 1, nbl)) + 1j * rng.normal(size=(2, nf, 1, nbl))
    noise = np.sqrt(var) * (rng.normal(size=var.shape) + 1j * rng.normal(size=var.shape))
    shape = (2, nf, nt, nbl)
    return Observation(
        vis=sky + noise, flags=np.zeros(shape, bool), nsamples=np.full(shape, nsamples),
        present=np.ones((nt, nbl), bool), integration_time_s=np.full((nt, nbl), dt),
        autos=autos.astype(complex), auto_flags=np.zeros(autos.shape, bool), auto_nsamples=np.ones(autos.shape),
        auto_present=np.ones((nt, nant), bool), antenna_numbers=np.arange(nant) * 10,
        antenna_names=np.array([f"A{i}" for i in range(nant)]), antpos_enu_m=rng.normal(size=(nant, 3)) * 30,
        antpairs=pairs, times_jd=2460000.0 + np.arange(nt) * dt / 86400, lsts_rad=np.linspace(1, 1.01, nt),
        site_ecef_m=np.array([5109342.8, 2005241.9, -3239939.4]), freqs_hz=100e6 + dnu * np.arange(nf),
        channel_width_hz=np.full(nf, dnu), polarizations=np.array([-5, -6]), x_orientation="east",
        vis_units="Jy", pol_convention=None, phase_type="unprojected", telescope_name="TEST",
        telescope_antenna_numbers=np.arange(nant) * 10,
        telescope_antenna_names=np.array([f"A{i}" for i in range(nant)]),
        source="synthetic")


def with_rfi(obs, *, channels=(), baselines=(), times=(), power=1e3, seed=1):
    """``obs`` plus a random (white in time) signal of ``power`` x the radiometer variance at those places."""
    rng = np.random.default_rng(seed)
    vis = np.array(obs.vis)
    sig = np.sqrt(power * 100.0 ** 2 / (2 * 10.0 * 1e5))
    add = np.zeros(vis.shape, bool)
    for c in channels:
        add[:, c] = True
    for b in baselines:
        add[..., b] = True
    for t in times:
        add[:, :, t] = True
    vis[add] += sig * (rng.normal(size=add.sum()) + 1j * rng.normal(size=add.sum()))
    return dataclasses.replace(obs, vis=vis)


def test_clean_noise_excess_is_one():
    """Mean of z is 1 for radiometer noise; the channel medians lie within 4 of their scatter of 1.

    Each excess is a mean of 7 adjacent-pair terms (neighbours share a sample: sd ~0.45); a
    median of 20 (2 products x 10 baselines) has sd ~0.13, so 4 sd is 0.5.
    """
    ex = noise_excess(synthetic(seed=3))
    assert ex.excess.shape == (2, 24, 10) and ex.pol_names == ("xx", "yy")
    # each excess is the mean of 7 correlated Exp(1) pairs; the mean over 2 x 24 x 10 items: sd < 0.03
    assert abs(np.mean(ex.excess) - 1.0) < 0.06
    assert np.all(np.abs(ex.per_channel() - 1.0) < 0.5)


def test_false_alarm_rate_on_clean_data():
    """20 clean files of 24 channels, 10 baselines, 8 times (4800 cells): nothing flagged (k = 5, factor 2)."""
    found = [find_outliers(synthetic(seed=s)) for s in range(20)]
    assert not any(o.any for o in found)


def test_injected_rfi_channels_baselines_and_times_are_flagged_and_reported(caplog):
    obs = with_rfi(synthetic(seed=5), channels=(4, 17), power=1e3)
    obs = with_rfi(obs, baselines=(6,), power=30, seed=2)
    obs = with_rfi(obs, times=(5,), power=50, seed=3)
    flagged, out = flag_outliers(obs)
    assert out.channels == (4, 17) and out.baselines == (6,) and out.times == (5,) and out.cells == ()
    assert min(out.channel_excess) > 300  # ~ 1 + 1e3 / 2 x (A^2 / 100^2) per channel
    assert np.all(flagged.flags[:, [4, 17]]) and np.all(flagged.flags[..., 6]) and np.all(flagged.flags[:, :, 5])
    assert not np.any(obs.flags)  # the input is not changed
    assert flagged.usable.sum() == obs.usable[:, [c for c in range(24) if c not in (4, 17)]][..., :].sum() - (
        2 * 22 * 8 * 1 + 2 * 22 * 1 * 9)  # the baseline's and the time's samples on the kept channels
    assert "channels [4, 17]" in caplog.text
    rep = out.to_dict(obs)
    assert rep["baselines"] == [[int(a) for a in obs.baseline_antnums[6]]] and rep["channels"] == [4, 17]


def test_a_weak_excess_is_not_flagged_a_strong_one_is():
    """The factor-2 floor: 1.5 x the noise variance (sky drift scale) stays, 10 x goes."""
    weak = with_rfi(synthetic(seed=7), channels=(9,), power=0.5)
    assert find_outliers(weak).channels == ()
    strong = with_rfi(synthetic(seed=7), channels=(9,), power=9.0)
    assert find_outliers(strong).channels == (9,)


def test_outlier_rule_is_robust_and_floored():
    rng = np.random.default_rng(0)
    s = np.exp(0.05 * rng.normal(size=100))
    s[[3, 50]] = [5.0, 40.0]
    bad, cut = outlier_rule(s, np.full(100, 1e4))
    assert list(np.flatnonzero(bad)) == [3, 50] and 1.9 < cut < 2.2
    bad, cut = outlier_rule(np.ones(10), np.full(10, 5))  # MAD 0: the estimator's own scatter sets the scale
    assert not bad.any() and cut > 2.0


def test_dead_channels_and_fully_flagged_antennas():
    obs = synthetic(seed=2)
    vis = np.array(obs.vis)
    vis[:, 0] = 0.0
    flags = np.array(obs.flags)
    flags[..., [b for b, (i, j) in enumerate(obs.antpairs) if 3 in (i, j)]] = True
    obs = dataclasses.replace(obs, vis=vis, flags=flags)
    assert dead_channels(obs) == [0]
    assert flagged_antennas(obs) == [30]
    flagged, out = flag_outliers(obs)
    assert out.dead_channels == (0,) and np.all(flagged.flags[:, 0])


def test_all_flagged_and_zero_nsample_are_refused():
    obs = synthetic()
    refuse_empty(obs)
    with pytest.raises(ValueError, match="every cross-correlation sample of the selection is flagged"):
        refuse_empty(dataclasses.replace(obs, flags=np.ones(obs.flags.shape, bool)))
    with pytest.raises(ValueError, match="nsample of every unflagged sample is zero"):
        refuse_empty(dataclasses.replace(obs, nsamples=np.zeros(obs.nsamples.shape)))


def test_h1c_rfi_channels():
    """The real file: dead edge channels 0-2, FM (104.7, 106.3 MHz; 105.3 weaker) and ORBCOMM (137.5 MHz)."""
    from gcrsky.io.observation import read_observation

    obs = read_observation(H1C)
    ex = noise_excess(obs)
    pc = ex.per_channel()
    out = find_outliers(obs, ex)
    assert out.dead_channels == (0, 1, 2) and out.channels == (3, 4, 5, 24)
    assert out.cells == ((63, 9),) and out.cell_excess[0] > 50  # 198.4 MHz on baseline 1-13 only
    assert list(obs.baseline_antnums[9]) == [1, 13]
    clean = np.delete(pc, [0, 1, 2, 3, 4, 5, 24])
    assert 0.8 < clean.min() and clean.max() < 1.4  # medians over baselines; per baseline up to ~1.6
    assert pc[24] > 1e4 and pc[4] > 1e3
    assert abs(obs.freqs_hz[24] / 1e6 - 137.5) < 0.8
    assert flagged_antennas(obs) == []


def test_a_single_bad_cell_is_flagged_alone():
    obs = synthetic(seed=11)
    vis = np.array(obs.vis)
    rng = np.random.default_rng(4)
    vis[:, 8, :, 3] += 0.5 * (rng.normal(size=(2, 8)) + 1j * rng.normal(size=(2, 8)))  # ~50 x the noise variance
    flagged, out = flag_outliers(dataclasses.replace(obs, vis=vis))
    assert out.cells == ((8, 3),) and out.channels == () and out.baselines == ()
    assert np.all(flagged.flags[:, 8, :, 3]) and flagged.flags.sum() == 2 * 8


def test_sky_drift_over_long_steps_is_not_flagged_as_a_bad_baseline():
    """30-minute steps: a bright baseline's fringe turns ~radians per step, its excess is sky, not RFI.

    Negative control: with the drift gate off (max_drift_rad=inf) the same baseline is flagged.
    """
    obs = synthetic(seed=9)
    nt = obs.n_times
    times = 2460000.0 + np.arange(nt) * 1800.0 / 86400
    vis = np.array(obs.vis)
    vis[..., 6] += 0.5 * np.exp(1j * 1.0 * np.arange(nt))[None, None, :]  # a bright source drifting 1 rad per step
    drifting = dataclasses.replace(obs, vis=vis, times_jd=times)
    out = find_outliers(drifting)
    assert out.baselines == () and out.cells == () and len(out.not_judged_baselines) == obs.n_baselines
    assert find_outliers(drifting, max_drift_rad=np.inf).baselines == (6,)
    assert find_outliers(obs).not_judged_baselines == ()  # 10 s steps: every baseline judged


def test_the_sky_s_drift_and_slow_gains_are_not_taken_for_noise():
    """Issue 39: on a clean twin the first differences read the sky's drift between integrations (the fringe
    turning by up to 0.1 rad per step, signal to noise ~150) and a slow gain drift as noise: excess 1.7-2.2 in
    every channel and 18-65 on the shortest east-west baselines, which were flagged.  The second differences
    cancel what changes linearly: no false flag; RFI on top of it is still found.  Control: the first
    differences of the same data (the old statistic) put baselines far above twice the median."""
    base = synthetic(seed=7, nt=10)
    phi = drift_phase_rad(base)  # (Nbl,) the fringe's turn per step, as the check bounds it
    assert 0.02 < phi.max() <= MAX_DRIFT_RAD
    t = np.arange(base.n_times)
    sigma = np.sqrt(100.0**2 / (2 * 10.0 * 1e5))
    rng = np.random.default_rng(11)
    amp = 150 * sigma * np.exp(2j * np.pi * rng.uniform(size=(2, base.n_freqs, 1, base.n_baselines)))
    gain = (1 + 0.003 * t) * np.exp(0.003j * t)  # a slow drift of the gains: 0.3 % and 0.17 deg per step
    sky = amp * np.exp(1j * phi[None, None, None, :] * t[None, None, :, None]) * gain[None, None, :, None]
    obs = dataclasses.replace(base, vis=np.asarray(base.vis) + sky)  # its own constant sky cancels in differences
    ex = noise_excess(obs)
    out = find_outliers(obs, ex)
    assert not out.any, out
    # medians over 48 cells of means of 8 correlated unit exponentials: ~1 +- 0.1 (the drift's residue is
    # second order: (0.1 rad)^2 x 150 sigma ~ 1.5 sigma at most, on the longest baseline)
    assert np.all(np.abs(ex.per_baseline() - 1.0) < 0.5) and np.all(np.abs(ex.per_channel() - 1.0) < 0.5)
    first = np.nanmean(ex.z, axis=2)  # (Npols, Nf, Nbl): the first-difference excess of the same data
    per_bl = np.nanmedian(first.reshape(-1, first.shape[-1]), axis=0)
    assert np.max(per_bl) > 2 * np.median(per_bl) and np.max(per_bl) > 5  # would have been flagged
    rfi = with_rfi(obs, channels=(4,), power=1e3)
    assert find_outliers(rfi).channels == (4,)
