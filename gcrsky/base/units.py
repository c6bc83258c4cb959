"""Physical constants and unit conversions (SI).

Visibilities of a sky in kelvin come out in K sr; :func:`kelvin_sr_to_jy` converts
them to Jy by Rayleigh-Jeans, ``2 k nu^2 / c^2``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SPEED_OF_LIGHT", "BOLTZMANN", "kelvin_sr_to_jy"]

#: Speed of light in vacuum, m/s.
SPEED_OF_LIGHT = 299792458.0
#: Boltzmann's constant, J/K.
BOLTZMANN = 1.380649e-23


def kelvin_sr_to_jy(freqs_hz) -> np.ndarray:
    """Factor ``2 k nu^2 / c^2 * 1e26`` converting K sr to Jy, per frequency (Hz)."""
    f = np.asarray(freqs_hz, np.float64)
    return 2 * BOLTZMANN * f**2 / SPEED_OF_LIGHT**2 * 1e26
