"""A wrapper that keeps any diffrax solver's state on the tangent bundle of (S^2)^n."""

from diffrax import AbstractSolver

from .._term import space_of
from .wrapped import AbstractTransparentSolver


class Projected(AbstractTransparentSolver):
    """Wraps any diffrax solver so that after every step each `q_i` is renormalized and
    the second state variable (velocity, angular velocity or momentum) has its normal
    part removed (on a mixed space, through its `MechanicsTerm` as `simulate` does: the
    sphere factors only). The projection moves the state by no more than the local
    error, so the order is kept (tests/test_solvers.py); error estimate, step-size
    control, interpolation (off the spheres by the local error: `simulate` retracts
    saved states), the FSAL reuse of the vector field and `isinstance` checks (adaptive,
    implicit) are the wrapped solver's.

    **Arguments:**
    - `solver`: any diffrax solver, e.g. `diffrax.Tsit5()` (the default of `simulate`),
      `diffrax.Dopri8()`, `diffrax.Kvaerno5()` or `sphere_mech.RK4()`.
    """

    solver: AbstractSolver

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        space = space_of(terms, y0, "Projected")
        y1, *rest = self.solver.step(terms, t0, t1, y0, args, solver_state, made_jump)
        return space.retract(*y1), *rest
