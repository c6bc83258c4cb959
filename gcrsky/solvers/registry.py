"""The exact solver paths by name: the one place that lists them.

``PATHS`` maps each path's name to its :class:`~gcrsky.solvers.path.SolverPath`; the planner,
the posterior, the evidence, the Gibbs kernels and the channel code find a path here, by
name, options or prepared state (:func:`path_of`), and ask it what they need.  The order is
the planner's order of preference between direct paths of equal estimated cost.

The paths with a joint (frequency-coupled) flavour are the subclasses of
:mod:`gcrsky.solvers.joint`, :mod:`~gcrsky.solvers.joint_dataspace` and :mod:`~gcrsky.solvers.joint_cg`
(:class:`~gcrsky.solvers.joint.JointCholeskyPath`, ...): the same path, same name, with the ``joint_*``
hooks of :class:`~gcrsky.solvers.path.SolverPath` (the joint modules build on the per-channel ones).

Adding a path: a module with its options (a frozen dataclass with a ``method`` class
attribute), its state (an equinox Module with ``system``, ``a_wf``, ``wiener`` and a
``method`` class attribute) and a :class:`~gcrsky.solvers.path.SolverPath` subclass; then one
line below.
"""

from __future__ import annotations

import dataclasses
from typing import Union

from .dense import EighPath
from .joint import JointCholeskyPath, JointMModePath
from .joint_cg import JointCGPath
from .joint_dataspace import JointDataSpacePath
from .path import SolverPath

__all__ = ["LEGACY_JOINT_NAMES", "METHODS", "PATHS", "SolverOptions", "joint_methods", "method_of", "options_for",
           "path_of"]

#: Every exact path, by name (direct paths first, in order of preference).
PATHS: dict[str, SolverPath] = {p.name: p for p in (
    JointMModePath(),
    JointCholeskyPath(),
    JointDataSpacePath(),
    EighPath(),
    JointCGPath(),
)}


def path_of(what) -> SolverPath:
    """The :class:`~gcrsky.solvers.path.SolverPath` of a name, an options object or a prepared state.

    Raises:
        ValueError: an unknown name; TypeError: an object that is neither.
    """
    if isinstance(what, str):
        if what not in PATHS:
            raise ValueError(f"method must be one of {', '.join(map(repr, PATHS))}, got {what!r}")
        return PATHS[what]
    for p in PATHS.values():
        if isinstance(what, (p.options_type, p.state_type)):
            return p
    names = ", ".join(p.options_type.__name__ for p in PATHS.values())
    raise TypeError(f"expected a path name, options ({names}) or a prepared state "
                    f"(gcrsky.prepare), got {type(what).__name__}")


#: The exact paths' names (at import; code that must see a path added later reads :data:`PATHS`).
METHODS = tuple(PATHS)

#: What runs before the joint paths joined the registry recorded as ``method`` in ``results.h5``:
#: ``{old name: (path name, joint variant)}`` (read on resume, never written).
LEGACY_JOINT_NAMES = {
    "joint-cholesky": ("cholesky", "dense"),
    "joint-mmode": ("mmode", "mmode"),
    "joint-dataspace": ("dataspace", "dense"),
    "joint-dataspace-mmode": ("dataspace", "mmode"),
    "joint-cg": ("cg", "cg"),
}


def joint_methods() -> tuple[str, ...]:
    """The names of the paths with a joint (frequency-coupled) flavour, in registry order (read now)."""
    return tuple(name for name, p in PATHS.items() if p.joint)

#: The options of any path (a type for annotations).
SolverOptions = Union[tuple(p.options_type for p in PATHS.values())]


def method_of(options) -> str:
    """The path name of an options object (``"cg"``, ``"cholesky"``, ...)."""
    if isinstance(options, str):
        raise TypeError(f"method_of takes an options object, got the string {options!r}")
    return path_of(options).name


def options_for(method: str, options=None, *, tol: float | None = None):
    """The options of path ``method``: ``options`` checked against it, or the path's defaults.

    Args:
        method: a path name (:data:`METHODS`).
        options: options for that path, or None for its defaults.
        tol: if given, the CG tolerance (replaces ``options.tol`` of the iterative path); the
            direct paths keep their own ``tol`` (the accuracy their factor must reach).

    Raises:
        ValueError: unknown method, or options of another path.
    """
    path = path_of(method)
    if options is None:
        options = path.options_type()
    elif path_of(options) is not path:
        raise ValueError(f"method={method!r} was given {type(options).__name__} (options of "
                         f"method={method_of(options)!r})")
    if tol is not None and not path.direct and tol != options.tol:
        options = dataclasses.replace(options, tol=float(tol))
    return options
