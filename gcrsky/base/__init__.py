"""Foundations every layer may use: the dtype policy, memory budgets, units, optional imports.

Nothing here imports any other part of gcrsky.
"""

from .dtypes import check_float64, require_x64
from .extras import require
from .memory import InsufficientMemoryError, available_memory_bytes, check_memory, format_bytes
from .units import BOLTZMANN, SPEED_OF_LIGHT, kelvin_sr_to_jy

__all__ = [
    "BOLTZMANN",
    "InsufficientMemoryError",
    "SPEED_OF_LIGHT",
    "available_memory_bytes",
    "check_float64",
    "check_memory",
    "format_bytes",
    "kelvin_sr_to_jy",
    "require",
    "require_x64",
]
