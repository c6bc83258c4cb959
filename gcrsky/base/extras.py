"""Optional dependencies: import one, or fail with a message naming the extra that installs it.

The core needs only jax, numpy, scipy, healpy, astropy, pyuvdata, equinox and h5py;
the applications need extras: ``[sim]`` (pyradiosky, pygdsm: truth skies),
``[plots]`` (matplotlib: figures), ``[validate]`` (matvis: forward-model checks),
``[cli]`` (tqdm, plus sim and plots: the ``gcrsky`` command); one core feature needs
one: ``[nuts]`` (blackjax: collapsed NUTS over hyperparameters,
:mod:`gcrsky.inference.collapsed`); ``[all]`` has every one.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["require"]


def require(module: str, extra: str, what: str) -> ModuleType:
    """Import ``module`` or raise ``ImportError`` saying ``what`` needs it and how to install it.

    Args:
        module: the import name, e.g. ``"matplotlib.pyplot"``.
        extra: the gcrsky extra that provides it, e.g. ``"plots"``.
        what: the feature that needs it, e.g. ``"the paper's figures"``.
    """
    try:
        return importlib.import_module(module)
    except ImportError as e:
        top = module.split(".")[0]
        raise ImportError(
            f"{what} needs {top}, which is not installed: pip install 'gcrsky[{extra}]' (or 'gcrsky[all]')"
        ) from e
