"""A wrapper that keeps any diffrax solver's state on the tangent bundle of (S^2)^n."""

from diffrax import AbstractSolver

from .._term import space_of
from .wrapped import AbstractTransparentSolver


class Projected(AbstractTransparentSolver):
    """Wraps any diffrax solver (explicit or implicit, adaptive or fixed-step) so that
    after every step each `q_i` is renormalized and the second state variable (velocity,
    angular velocity or momentum) has its normal part removed.

    The projection moves the state by no more than the step's own local error, so the
    order of the wrapped solver is kept (measured in tests/test_solvers.py); its error
    estimate, step-size control, interpolation and `isinstance` checks (adaptive,
    implicit) pass through unchanged. Dense output is the wrapped solver's polynomial,
    which leaves the spheres by the local error (`simulate` retracts saved states).
    First-same-as-last solvers (Tsit5, Dopri5, Dopri8, Kvaerno5) reuse the vector field
    at the unprojected end point; it differs from the one at the projected point by the
    local error times a Lipschitz constant, which does not change the order.

    The state must be the pair `(q, v)` of `(n, 3)` arrays used throughout sphere_mech,
    or, for a system on a mixed space (integrated through its `MechanicsTerm`, as
    `simulate` does), the pair of dicts of its factors: only the sphere factors are
    retracted; Euclidean factors are left as the wrapped solver stepped them.

    **Arguments:**
    - `solver`: any diffrax solver, e.g. `diffrax.Tsit5()` (the default of `simulate`),
      `diffrax.Dopri8()`, `diffrax.Kvaerno5()` or `sphere_mech.RK4()`.
    """

    solver: AbstractSolver

    def init(self, terms, t0, t1, y0, args):
        return self.solver.init(terms, t0, t1, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        space = space_of(terms, y0, "Projected")
        y1, y_error, dense_info, solver_state, result = self.solver.step(
            terms, t0, t1, y0, args, solver_state, made_jump
        )
        return space.retract(*y1), y_error, dense_info, solver_state, result
