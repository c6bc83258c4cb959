"""The one WARNING line of a rejected fit (``gcrsky.run.fit.fit_warning``): which channels, their chi2/dof, the tail.

The goodness-of-fit blocks are built here from chi-square values and scipy's tails (the
fields :func:`gcrsky.run.fit.goodness_of_fit` writes), so that the line is checked against
channels known to be rejected in the upper tail, the lower tail, or not at all.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from gcrsky.run.fit import FIT_ALPHA, MAX_NAMED_CHANNELS, fit_warning


def _gof(chi2_per_dof, dof=1000):
    chi2 = np.asarray(chi2_per_dof, float) * dof
    up, low = stats.chi2.sf(chi2, dof), stats.chi2.cdf(chi2, dof)
    thr = FIT_ALPHA / (2 * chi2.size)
    rejected = np.flatnonzero(np.minimum(up, low) < thr)
    return {"chi2": chi2.tolist(), "dof": [dof] * chi2.size, "chi2_per_dof": list(chi2_per_dof),
            "p_value": up.tolist(), "p_value_low": low.tolist(), "threshold_p": thr,
            "rejected_channels": rejected.tolist(), "rejected": bool(rejected.size)}


def test_one_line_names_each_rejected_channel_its_chi2_and_tail_the_worst_first():
    freqs = 100e6 + 1e6 * np.arange(6)
    gof = _gof([1.0, 1.5, 0.98, 0.6, 1.02, 3.0])  # 101 MHz upper, 103 lower, 105 upper (the worst)
    assert gof["rejected_channels"] == [1, 3, 5]
    line = fit_warning(gof, freqs)
    assert "\n" not in line and line.startswith("WARNING: the model does not fit the data in 3 of 6 channels")
    named = line.split("): ", 1)[1]
    assert named.index("105.000 MHz chi2/dof 3 (upper p") < named.index("103.000 MHz chi2/dof 0.6 (lower p") \
        < named.index("101.000 MHz chi2/dof 1.5 (upper p")
    for mhz in ("100.000", "102.000", "104.000"):
        assert mhz not in line
    assert "upper: the data vary more" in line and "lower: the data vary far less" in line


def test_many_rejected_channels_are_counted_and_a_passing_fit_has_no_line():
    n = MAX_NAMED_CHANNELS + 3
    line = fit_warning(_gof([2.0] * n), 100e6 + 1e6 * np.arange(n))
    assert line.count(" MHz chi2/dof ") == MAX_NAMED_CHANNELS and line.endswith(
        "see summary.json goodness_of_fit") and " and 3 more;" in line
    assert "lower:" not in line  # only the tail that rejects is explained
    assert fit_warning(_gof([1.0, 1.01, 0.99]), [1e8, 1.01e8, 1.02e8]) is None
