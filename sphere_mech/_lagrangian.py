"""Lagrangian systems: form 1 in `(q, qdot)` (Proposition 1) and form 2 in `(q, omega)`
(Proposition 2), derived from the user's `L` by autodiff."""

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ._checks import check_function, check_scalar, check_time
from ._custom_types import Args, ForceFn, Points, Tangents
from ._linalg import dense_solve
from ._misc import as_python, check_bool, tree_add, tree_dtype, tree_sub, tree_zeros_like
from ._momentum import check_inverse_options, invert_momentum, newton_tolerance
from ._spaces import AbstractSpace, Spheres, as_space
from ._system import SINGULAR_MESSAGE, AbstractLagrangianSystem, as_time, check_rates


def _lagrangian_terms(L, t, q, v, args, direction):
    """For `L(t, q, v)`: `dL/dv`, `dL/dq`, the mixed derivative
    `d/deps dL/dv (t + eps, q + eps * direction, v)`, and a linear map applying
    `d^2 L / dv^2`. One function for forms 1 and 2."""
    t = as_time(t, q)

    def scalar_L(t_, q_, v_):
        return check_scalar(L(t_, q_, v_, args), "L(t, q, v, args)")

    dL_dv = lambda t_, q_, v_: jax.grad(scalar_L, argnums=2)(t_, q_, v_)
    dL_dq = jax.grad(scalar_L, argnums=1)(t, q, v)
    p, mixed = jax.jvp(lambda t_, q_: dL_dv(t_, q_, v), (t, q), (jnp.ones_like(t), direction))
    _, hvp = jax.linearize(lambda v_: dL_dv(t, q, v_), v)
    return p, dL_dq, mixed, hvp


SINGULAR_RCOND = 4.0
"""A reduced mass matrix whose smallest LU pivot is below `SINGULAR_RCOND n eps` times its
largest is singular to rounding (condition number above about `1 / (4 n eps)`: 5.6e14 at
`n = 2` in float64, 1e6 in float32): its accelerations would be rounding errors."""


def _tangent_solve(space, hvp, q, rhs):
    """The tangent `x` with `P H x = P rhs`, solved as `(T^T H T) a = T^T rhs` (`T` the
    space's tangent basis: `blockdiag(I_m, T_S)` on a mixed space); NaN where the reduced
    mass matrix `T^T H T` is singular to rounding (a pivot below `SINGULAR_RCOND`)."""
    T = space.tangent_basis(q)
    K = space.reduced_matrix(hvp, T)
    rcond = SINGULAR_RCOND * K.shape[0] * jnp.finfo(K.dtype).eps
    a = dense_solve(K, space.to_tangent(T, rhs), rcond)
    return space.from_tangent(T, a)


def _space_field():
    return eqx.field(default_factory=Spheres, converter=as_space)


class _AbstractAutodiffLagrangian(AbstractLagrangianSystem):
    """A Lagrangian system given by the user's function `L` (forms 1 and 2)."""

    L: eqx.AbstractVar[Callable]

    def __check_init__(self):
        check_function(self.L, "L", f"L(t, q, {self.state_name}, args)", 4)
        check_bool(self.quadratic_in_velocity, "quadratic_in_velocity")

    def lagrangian(self, t, q, v, args):
        return self.L(t, q, v, args)

    def velocity_from_momentum(
        self, t, q, p, args=None, *, guess=None, quadratic=None, tol=None, max_steps=32
    ):
        """The inverse Legendre map: the tangent `v` with `P dL/dv = p`, by one linear solve
        around `guess` (default zero) when `quadratic` (default `quadratic_in_velocity`),
        otherwise refined by Newton's method to `tol` (default `eps ** 0.75`) in at most
        `max_steps` (globalized by a line search when needed). Returns `(v, result)`, the
        `RESULTS` code never raised here. A bad option raises `ValueError`."""
        options = dict(guess=guess, quadratic=quadratic, tol=tol, max_steps=max_steps)
        check_inverse_options(p, **options)
        guess = tree_zeros_like(p) if guess is None else guess
        quadratic = self.quadratic_in_velocity if quadratic is None else quadratic
        tol = newton_tolerance(tree_dtype(q)) if tol is None else tol
        options = dict(guess=guess, quadratic=quadratic, tol=tol, max_steps=max_steps)
        return invert_momentum(self.lagrangian, self.state_space, t, q, p, args, **options)


class Lagrangian(_AbstractAutodiffLagrangian):
    """A system given by any Lagrangian `L(t, q, qdot, args) -> scalar` on (S^2)^n
    (form 1); state `(q, qdot)`.

    **Arguments:**
    - `L`: the Lagrangian, a JAX function of time, `q` (`(n, 3)` unit vectors), `qdot`
      (`(n, 3)` tangent) and `args`. Only its values on the tangent bundle matter.
    - `forces`: optional `forces(t, q, qdot, args) -> (n, 3)`, generalized forces with
      virtual work `sum_i f_i . delta q_i`.
    - `quadratic_in_velocity`: declare that `L` is (at most) quadratic in `qdot`; then
      `legendre` inverts the momentum map by one linear solve instead of Newton.
    - `space`: the configuration space: `Spheres()` (default: `q` a plain `(n, 3)`
      array, any `n`) or a dict of factors, e.g. `{"cart": sm.Euclidean(1), "pendulum":
      sm.Spheres(1)}`; then `q`, `qdot` and the forces are dicts with its keys (one
      array per factor) and the virtual work is `f_x . delta x + sum_i f_i . delta q_i`.

    Accelerations solve `(P H_vv + Q) qddot = P b - c` in tangent coordinates (2n x 2n),
    with `H_vv = d^2L/dqdot^2` applied by forward-over-reverse autodiff.
    """

    L: Callable
    forces: ForceFn | None = None
    quadratic_in_velocity: bool = eqx.field(default=False, static=True, converter=as_python)
    space: AbstractSpace = _space_field()
    state_name: ClassVar[str] = "qdot"
    angular: ClassVar[bool] = False

    def _vdot(self, t, q, qdot, args):
        _, dL_dq, mixed, hvp = _lagrangian_terms(self.L, t, q, qdot, args, qdot)
        c = self.space.normal_acceleration(q, qdot)  # keeps q_i . qddot_i = -|qdot_i|^2
        f = self.generalized_force(t, q, qdot, args)
        b = tree_sub(dL_dq, mixed) if f is None else tree_add(tree_sub(dL_dq, mixed), f)
        return tree_sub(_tangent_solve(self.space, hvp, q, tree_add(b, hvp(c))), c)


class AngularLagrangian(_AbstractAutodiffLagrangian):
    """A system given by a Lagrangian `L(t, q, omega, args) -> scalar` in the angular
    velocities `omega_i = q_i x qdot_i` (form 2, Proposition 2); state `(q, omega)`.

    `sphere_mech.angular(Lagrangian(...))` builds one from a form-1 system.

    **Arguments:**
    - `L`: the Lagrangian, a JAX function of time, `q` (`(n, 3)` unit vectors), `omega`
      (`(n, 3)` tangent) and `args`.
    - `forces`: optional `forces(t, q, omega, args) -> (n, 3)`, generalized forces with
      virtual work `sum_i f_i . delta q_i` (the same convention as everywhere).
    - `quadratic_in_velocity`: declare that `L` is (at most) quadratic in `omega`; then
      `legendre` inverts the momentum map by one linear solve instead of Newton.
    - `space`: the configuration space, as in `Lagrangian`; only the sphere factors have
      angular velocities, Euclidean factors keep `xdot`.
    """

    L: Callable
    forces: ForceFn | None = None
    quadratic_in_velocity: bool = eqx.field(default=False, static=True, converter=as_python)
    space: AbstractSpace = _space_field()
    state_name: ClassVar[str] = "omega"
    angular: ClassVar[bool] = True

    def _vdot(self, t, q, omega, args):
        space = self.space
        qdot = space.to_linear(q, omega)
        p, dL_dq, mixed, hvp = _lagrangian_terms(self.L, t, q, omega, args, qdot)
        f = self.generalized_force(t, q, omega, args)
        force = dL_dq if f is None else tree_add(dL_dq, f)
        rhs = tree_sub(space.from_covector(q, force), space.angular_terms(q, omega, p, mixed))
        return _tangent_solve(self.state_space, hvp, q, rhs)

    def angular_acceleration(self, t, q: Points, omega: Tangents, args: Args = None):
        """`omegadot` from the Euler-Lagrange equations in `(q, omega)` (Proposition 2),
        after checking the state.

        **Arguments:**
        - `t`, `q`, `omega`, `args`: time, `(n, 3)` unit vectors, angular velocities tangent
          at `q`, the user's `args`.

        **Returns:** `omegadot`, `(n, 3)`.
        """
        check_time(t)
        q, omega = self.check_state(q, omega)
        return check_rates(self._vdot(t, q, omega, args), SINGULAR_MESSAGE, self, args)
