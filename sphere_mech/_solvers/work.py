"""`WithWork`: any solver, plus the work of the system's forces accumulated over its steps."""

import jax
import jax.numpy as jnp
from diffrax import AbstractSolver

from .._misc import tree_dtype
from .._system import vector_field
from .._term import physical_time, system_of
from .wrapped import AbstractTransparentSolver, unwrapped


def power_and_rate(system, t, q, v, args):
    """`(P, dP/dt)`: the power `system.power` of the forces and its derivative along the
    flow (`jax.jvp` along `system.rates`)."""
    p = lambda s, y: system.power(s, y[0], y[1], args)
    tangent = (jnp.ones_like(t), vector_field(system, t, (q, v), args))
    return jax.jvp(p, (t, (q, v)), tangent)


def work_step(h, P0, dP0, P1, dP1):
    """`int P dt` over a step of length `h` by the end-corrected trapezoidal rule
    `h/2 (P0 + P1) + h^2/12 (P0' - P1')` (fourth order)."""
    return 0.5 * h * (P0 + P1) + h**2 / 12.0 * (dP0 - dP1)


class WithWork(AbstractTransparentSolver):
    """Wraps any solver of a `MechanicsTerm` (`wrapped`) and accumulates the work
    `W = int P dt` of the system's forces over the accepted steps (`work_step`, with `P`
    and `dP/dt` at both ends by autodiff) in its solver state: memory independent of the
    number of steps. Steps, states, error estimates and dense output are the wrapped
    solver's. `work_done(sol.solver_state)` (with `SaveAt(solver_state=True)`) reads the
    work since `t0`; `E(t1) - E(t0) - W` then measures the integrator alone."""

    wrapped: AbstractSolver

    @property
    def solver(self):
        """The solver inside `wrapped` (diffrax forwards `isinstance` checks one level only)."""
        return unwrapped(self.wrapped)

    def _power(self, terms, t, y, args):
        t = jnp.asarray(physical_time(terms, t), dtype=tree_dtype(y))
        return t, *power_and_rate(system_of(terms), t, *y, args)

    def init(self, terms, t0, t1, y0, args):
        _, P, dP = self._power(terms, t0, y0, args)
        return self.wrapped.init(terms, t0, t1, y0, args), jnp.zeros_like(P), P, dP

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        inner, W, P0, dP0 = solver_state
        y1, y_error, dense_info, inner, result = self.wrapped.step(
            terms, t0, t1, y0, args, inner, made_jump
        )
        s0 = jnp.asarray(physical_time(terms, t0), dtype=W.dtype)
        s1, P1, dP1 = self._power(terms, t1, y1, args)
        W = W + work_step(s1 - s0, P0, dP0, P1, dP1)
        return y1, y_error, dense_info, (inner, W, P1, dP1), result


def work_done(solver_state) -> jax.Array:
    """The work `WithWork` accumulated, from its solver state (`sol.solver_state`)."""
    return solver_state[1]
