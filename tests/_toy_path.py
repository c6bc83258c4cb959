"""A toy solver path for the registry tests (tests/test_registry.py): its own name ``"toy"``, options and
state types, wrapping the dense Cholesky math (:mod:`gcrsky.solvers.dense`) and, for a frequency-coupled
run, the dense joint Cholesky math (:mod:`gcrsky.solvers.joint`).  Added to
:data:`gcrsky.solvers.registry.PATHS` by one ``monkeypatch.setitem``: nothing else names it.

(Its Gibbs step: tests/test_registry.py::test_a_toy_path_in_the_registry_is_a_gibbs_step.)
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax

from gcrsky.model import LinearSystem
from gcrsky.solvers import CholeskyOptions, SolveInfo, SolverPath
from gcrsky.solvers.dense import CholeskyState, draw_cholesky, prepare_cholesky
from gcrsky.solvers.joint import JointCholeskyPath
from gcrsky.solvers.options import DEFAULT_TOL

NAME = "toy"


@dataclasses.dataclass(frozen=True)
class ToyOptions:
    """The toy path's options (the dense Cholesky path's ``throw`` and ``tol``)."""

    throw: bool = False
    tol: float = DEFAULT_TOL
    method = NAME

    def cholesky(self) -> CholeskyOptions:
        return CholeskyOptions(throw=self.throw, tol=self.tol)


class ToyState(eqx.Module):
    """The toy path's state: the Cholesky state it wraps, and the fields every state has."""

    system: LinearSystem
    a_wf: jax.Array
    wiener: SolveInfo
    inner: CholeskyState
    method = NAME


def _wrap(inner: CholeskyState) -> ToyState:
    return ToyState(inner.system, inner.a_wf, inner.wiener, inner)


_CHOLESKY = JointCholeskyPath()


class ToyPath(SolverPath):
    """Dense Cholesky of P under another name (per channel and, through the joint hooks, all channels)."""

    name = NAME
    options_type = ToyOptions
    state_type = ToyState
    joint = True

    def memory_bytes(self, system, options, ndraws=1):
        return _CHOLESKY.memory_bytes(system, options.cholesky(), ndraws)

    def cost_flop(self, system, options, ndraws):
        return 2.0 * _CHOLESKY.cost_flop(system, options.cholesky(), ndraws)  # never preferred by auto

    def auto_limits(self, system, options, budget, ndraws):
        return "the toy path is only run by name"

    def prepare(self, system, options):
        return _wrap(prepare_cholesky(system, options.cholesky()))

    def draw(self, key, state, ndraws):
        return draw_cholesky(key, state.inner, ndraws)

    def condition(self, state, data):
        return _wrap(_CHOLESKY.condition(state.inner, data))

    def joint_variants(self, joint, full_day, requested):
        return _CHOLESKY.joint_variants(joint, full_day, True) if requested else []

    def joint_prepare(self, joint, tol, variant):
        return _CHOLESKY.joint_prepare(joint, tol, variant)._replace(method=NAME)

    def joint_draw(self, key, state, ndraws):
        return _CHOLESKY.joint_draw(key, state, ndraws)
