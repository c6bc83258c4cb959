"""What an exact solver path is: one object per path, with everything the rest of gcrsky asks of it.

A path (Cholesky, eigen, m-mode, data space, CG, ...) is a :class:`SolverPath`: a
stateless object that knows its options type and its state type, and answers

* **applicability**: :meth:`~SolverPath.check` (``""`` or the reason it does not apply,
  on concrete arrays) and :meth:`~SolverPath.resolve` (the options made concrete for a
  system, or a ``ValueError`` naming the reason);
* **planning**: :meth:`~SolverPath.memory_bytes`, :meth:`~SolverPath.cost_flop` and
  :meth:`~SolverPath.auto_limits` (what keeps ``method="auto"`` from choosing it);
* **sampling**: :meth:`~SolverPath.prepare` (factor / precondition once, Wiener filter),
  :meth:`~SolverPath.draw`, :meth:`~SolverPath.condition` (the same factor for a new
  data vector) and :meth:`~SolverPath.wiener`;
* **joint frequency sampling** (a path with a joint flavour, ``joint = True``):
  :meth:`~SolverPath.joint_variants` (its forms for a :class:`~gcrsky.solvers.joint.JointSystem`
  and their memory), :meth:`~SolverPath.joint_check`, :meth:`~SolverPath.joint_prepare` and
  :meth:`~SolverPath.joint_draw`; :func:`gcrsky.solvers.plan.choose_joint_path` plans between them;
* **evidence**: :meth:`~SolverPath.evidence_parts` (the solve and log-determinant
  pieces of ``log p(d)``, from a system) and :meth:`~SolverPath.state_evidence_parts`
  (the same from a prepared state, without refactorising).

:mod:`gcrsky.solvers.registry` holds one instance of each; the planner, the posterior,
the evidence, the Gibbs kernels and the channel code look paths up there
(:func:`gcrsky.solvers.registry.path_of`) instead of testing names.  A new path is one
module defining its options, state and :class:`SolverPath` subclass, plus one line in
the registry.

The state of every path is an equinox Module with at least ``system``, ``a_wf`` (Nf, n)
and ``wiener`` (:class:`~gcrsky.solvers.SolveInfo`, (Nf,) fields), and a class attribute
``method`` (the path's name).
"""

from __future__ import annotations

import abc
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..model.system import LinearSystem
from .info import DrawInfo, SolveInfo

__all__ = ["AUTO_MEMORY_FRACTION", "EvidenceParts", "JointVariant", "SolverPath", "has_flat_prior", "is_traced",
           "quadratic_from_state"]

#: Fraction of the available memory a direct path's set-up peak may take under ``method="auto"``.
AUTO_MEMORY_FRACTION = 0.75


def is_traced(tree) -> bool:
    """True if any leaf of ``tree`` is a JAX tracer (inside ``jit``, ``vmap``, ``grad``)."""
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def has_flat_prior(system: LinearSystem) -> bool:
    """True if some prior direction is flat or non-positive (``inv_var <= 0``; host-side, concrete)."""
    return bool(np.any(np.asarray(system.prior.inv_var) <= 0))


class EvidenceParts(NamedTuple):
    """A path's part of the log evidence, per channel (Nf,) each (:mod:`gcrsky.inference.evidence`).

    ``log p(d) = -1/2 [chi2 + logdet_whitened + log det N + N_d log 2 pi]``.

    Attributes:
        chi2: ``r^T C^-1 r`` with ``r = d - X a0`` and ``C = N + X S X^T``: exactly
            chi-square with ``N_d`` degrees of freedom under the model.  The primal paths
            form it as ``r^T W r - b'^T P^-1 b'`` (``b' = X^T W r``), the data-space path
            as ``r~^T D^-1 r~`` directly.
        logdet_whitened: ``log det(I + H) = log det S + log det P``.
        stderr: the standard error of ``log p(d)`` from this part (0 on exact paths).
        solve: :class:`~gcrsky.solvers.SolveInfo` of the solve or factorisation behind it.
    """

    chi2: jax.Array
    logdet_whitened: jax.Array
    stderr: jax.Array
    solve: SolveInfo


class JointVariant(NamedTuple):
    """One form of a path's joint flavour for one joint system (:meth:`SolverPath.joint_variants`).

    Attributes:
        variant: the form's name (recorded beside the path's name, e.g. ``"dense"``, ``"mmode"``).
        memory: estimated peak bytes of its factor and working set (float64).
        width: the width of its factor (the planner prefers the narrower).
    """

    variant: str
    memory: float
    width: float


class SolverPath(abc.ABC):
    """One exact path (subclass per path; the registry keeps one instance of each).

    Class attributes:
        name: the path's name (``method=`` in the user tier).
        options_type: its frozen options dataclass.
        state_type: its prepared-state Module.
        direct: True for a factorisation (the planner compares their costs), False for the
            iterative fallback (chosen only when no direct path applies and fits).
        joint: True if the path also samples a frequency-coupled joint system
            (:class:`~gcrsky.solvers.joint.JointSystem`, the ``joint_*`` hooks).
    """

    name: ClassVar[str]
    options_type: ClassVar[type]
    state_type: ClassVar[type]
    direct: ClassVar[bool] = True
    joint: ClassVar[bool] = False

    # ------------------------------------------------------------ applicability

    def check(self, system: LinearSystem, options) -> str:
        """``""`` if the path is exact for ``system`` (concrete arrays), else the reason it is not."""
        return ""

    def resolve(self, system: LinearSystem, options):
        """``options`` made concrete for ``system`` (host-side); ``ValueError`` naming the reason if
        the path does not apply.  Under a trace only what can be decided from shapes is checked."""
        if not is_traced(system):
            why = self.check(system, options)
            if why:
                raise ValueError(f"method={self.name!r} does not apply: {why}")
        return options

    def resolve_channels(self, system: LinearSystem, options, requested):
        """Options chosen on one channel (:func:`gcrsky.parallel.channels.resolve_channel_path`) made right for
        every channel of ``system``; ``requested``: what the user passed (or None)."""
        return self.resolve(system, options)

    # ------------------------------------------------------------ planning

    @abc.abstractmethod
    def memory_bytes(self, system: LinearSystem, options, ndraws: int = 1) -> float:
        """Estimated peak bytes of the path's large arrays (float64), beyond the system."""

    def cost_flop(self, system: LinearSystem, options, ndraws: int) -> float:
        """Estimated flop of the set-up plus ``ndraws`` draws, all channels (direct paths; the
        planner compares them).  The iterative path has none (its iterations are unknown)."""
        raise ValueError(f"method={self.name!r} has no cost model (the planner only compares direct paths)")

    def auto_limits(self, system: LinearSystem, options, budget: float, ndraws: int) -> str:
        """``""`` if ``method="auto"`` may choose this path for ``system`` within ``budget`` bytes,
        else why not (sizes, memory, the prior): limits of the planner, beyond :meth:`check`."""
        return ""

    def describe(self, system: LinearSystem, options, memory: float) -> str:
        """One line for the planner's reason when this path is chosen."""
        return self.name

    # ------------------------------------------------------------ sampling

    @abc.abstractmethod
    def prepare(self, system: LinearSystem, options):
        """Set the path up once (factor / preconditioner, Wiener filter): its state."""

    @abc.abstractmethod
    def draw(self, key: jax.Array, state, ndraws: int) -> tuple[jax.Array, DrawInfo]:
        """``ndraws`` exact posterior draws (Nf, ndraws, n) and their :class:`DrawInfo`."""

    @abc.abstractmethod
    def condition(self, state, data: jax.Array):
        """The state for new visibilities ``data`` (Nf, Nt, Nbl), same noise and prior: the Wiener
        filter re-solved with the existing factor or preconditioner (nothing refactorised)."""

    def wiener(self, system: LinearSystem, options) -> tuple[jax.Array, SolveInfo]:
        """The Wiener filter (Nf, n) and its :class:`SolveInfo`; by default through :meth:`prepare`."""
        state = self.prepare(system, options)
        return state.a_wf, state.wiener

    # ------------------------------------------------------------ joint frequency sampling

    def joint_check(self, joint, mmode) -> str:
        """``""`` if the joint flavour applies to ``joint`` (a :class:`~gcrsky.solvers.joint.JointSystem`,
        concrete arrays), else why not; ``mmode``: :func:`gcrsky.solvers.mmode_check` of its data."""
        return "" if self.joint else f"method={self.name!r} has no joint (frequency-coupled) flavour"

    def joint_variants(self, joint, full_day: bool, requested: bool) -> list[JointVariant]:
        """The forms of the joint flavour a direct path offers for ``joint`` (:class:`JointVariant`).

        Args:
            joint: the :class:`~gcrsky.solvers.joint.JointSystem` (shapes only).
            full_day: whether the coverage is uniform full day (the per-order forms apply).
            requested: True when the user asked for this path by name (``method="auto"`` otherwise).
        """
        return []

    def joint_prepare(self, joint, tol: float, variant: str):
        """Set the joint flavour's form ``variant`` up once for ``joint``: a
        :class:`~gcrsky.solvers.joint.JointState` (its Wiener filter (Nf, n) and measured
        :class:`SolveInfo` (Nf,) fields); ``tol``: the solve's tolerance in posterior sigma."""
        raise ValueError(f"method={self.name!r} has no joint (frequency-coupled) flavour")

    def joint_draw(self, key: jax.Array, state, ndraws: int) -> tuple[np.ndarray, DrawInfo]:
        """``ndraws`` joint posterior draws (Nf, ndraws, n) over all channels and their
        :class:`DrawInfo` ((Nf, ndraws) fields), host arrays, from :meth:`joint_prepare`'s state."""
        raise ValueError(f"method={self.name!r} has no joint (frequency-coupled) flavour")

    # ------------------------------------------------------------ evidence

    def evidence_parts(self, system: LinearSystem, options, terms, *, slq=None, key=None) -> EvidenceParts:
        """The path's pieces of ``log p(d)`` (:class:`EvidenceParts`), differentiable in ``system``.

        ``terms``: :func:`gcrsky.inference.evidence.evidence_terms` of the system (``rWr``, ``b_res`` =
        ``X^T W (d - X a0)`` (Nf, n), ...); ``slq``, ``key``: stochastic Lanczos settings of the
        iterative path.
        """
        raise ValueError(f"method={self.name!r} has no evidence")

    def state_evidence_parts(self, state, terms, *, slq=None, key=None) -> EvidenceParts:
        """:meth:`evidence_parts` from a prepared ``state`` (its factor reused: no refactorisation)."""
        raise ValueError(f"method={self.name!r} has no evidence from a prepared state")


def quadratic_from_state(state, b_res: jax.Array) -> jax.Array:
    """``b'^T P^-1 b' = b'^T (a_wf - a0)`` (Nf,) from a prepared state's Wiener filter."""
    return jnp.sum(b_res * (state.a_wf - state.system.prior.mean), axis=-1)
