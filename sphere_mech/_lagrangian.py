"""Lagrangian systems: form 1 in `(q, qdot)` (Proposition 1) and form 2 in `(q, omega)`
(Proposition 2), derived from the user's `L` by autodiff."""

import abc
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ._checks import check_finite, check_scalar
from ._custom_types import Args, ForceFn, Points, Scalar, State, Tangents
from ._geometry import dot, project, tangent_basis
from ._linalg import from_tangent, reduced_matrix, to_tangent
from ._system import AbstractSystem, as_time, user_forces

SINGULAR_MESSAGE = (
    "the reduced mass matrix T^T (d^2 L / d v^2) T is singular or not finite: the "
    "Lagrangian is degenerate at this state (for example a zero mass or length)"
)


class AbstractLagrangianSystem(AbstractSystem):
    """A system given by a Lagrangian in `(q, qdot)`; state `(q, qdot)`."""

    state_name: ClassVar[str] = "qdot"

    @abc.abstractmethod
    def lagrangian(self, t, q: Points, qdot: Tangents, args: Args) -> Scalar:
        """The Lagrangian `L(t, q, qdot, args)`."""

    @abc.abstractmethod
    def _acceleration(self, t, q, qdot, args) -> Tangents:
        """Accelerations with no input checks."""

    def acceleration(self, t, q: Points, qdot: Tangents, args: Args = None) -> Tangents:
        """`qddot` from the Euler-Lagrange equations on (S^2)^n (Proposition 1).

        Checks its input (shapes, unit `q`, tangent `qdot`) and raises on a singular
        reduced mass matrix."""
        q, qdot = self.check_state(q, qdot)
        return check_finite(self._acceleration(t, q, qdot, args), SINGULAR_MESSAGE)

    def rates(self, t, y: State, args: Args) -> State:
        q, qdot = y
        return qdot, self._acceleration(t, q, qdot, args)

    def velocity(self, t, q, qdot, args):
        return qdot

    def _dL_dqdot(self, t, q, qdot, args) -> Tangents:
        L = lambda v: check_scalar(self.lagrangian(t, q, v, args), "L(t, q, qdot, args)")
        return jax.grad(L)(qdot)

    def momentum(self, t, q: Points, qdot: Tangents, args: Args = None) -> Tangents:
        """The conjugate momentum `mu_i = (I - q_i q_i^T) dL/dqdot_i`."""
        return project(q, self._dL_dqdot(t, q, qdot, args))

    def energy(self, t, q: Points, qdot: Tangents, args: Args = None) -> Scalar:
        """`E = sum_i qdot_i . dL/dqdot_i - L`."""
        return jnp.sum(qdot * self._dL_dqdot(t, q, qdot, args)) - self.lagrangian(
            t, q, qdot, args
        )


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


class Lagrangian(AbstractLagrangianSystem):
    """A system given by any Lagrangian `L(t, q, qdot, args) -> scalar` on (S^2)^n.

    **Arguments:**
    - `L`: the Lagrangian, a JAX function of time, `q` (`(n, 3)` unit vectors), `qdot`
      (`(n, 3)` tangent) and `args`. Only its values on the tangent bundle matter.
    - `forces`: optional `forces(t, q, qdot, args) -> (n, 3)`, generalized forces with
      virtual work `sum_i f_i . delta q_i`.
    - `quadratic_in_velocity`: declare that `L` is (at most) quadratic in `qdot`; then
      `legendre` inverts the momentum map by one linear solve instead of Newton.

    Accelerations solve `(P H_vv + Q) qddot = P b - c` in tangent coordinates (2n x 2n),
    with `H_vv = d^2L/dqdot^2` applied by forward-over-reverse autodiff.
    """

    L: Callable
    forces: ForceFn | None = None
    quadratic_in_velocity: bool = eqx.field(default=False, static=True)

    def lagrangian(self, t, q, qdot, args):
        return self.L(t, q, qdot, args)

    @property
    def has_forces(self) -> bool:
        return self.forces is not None

    def generalized_force(self, t, q, qdot, args):
        return user_forces(self.forces, t, q, qdot, args)

    def _acceleration(self, t, q, qdot, args):
        _, dL_dq, mixed, hvp = _lagrangian_terms(self.L, t, q, qdot, args, qdot)
        c = dot(qdot, qdot) * q  # keeps q_i . qddot_i = -|qdot_i|^2
        b = dL_dq - mixed
        f = self.generalized_force(t, q, qdot, args)
        if f is not None:
            b = b + f
        T = tangent_basis(q)
        a = jnp.linalg.solve(reduced_matrix(hvp, T), to_tangent(T, b + hvp(c)))
        return from_tangent(T, a) - c


class AngularLagrangian(AbstractSystem):
    """A system given by a Lagrangian `L(t, q, omega, args)` in the angular velocities
    `omega_i = q_i x qdot_i` (form 2, Proposition 2); state `(q, omega)`.

    `forces(t, q, omega, args) -> (n, 3)` use the same virtual-work convention as
    everywhere. `sphere_mech.angular(Lagrangian(...))` builds one from a form-1 system.
    """

    L: Callable
    forces: ForceFn | None = None
    quadratic_in_velocity: bool = eqx.field(default=False, static=True)
    state_name: ClassVar[str] = "omega"

    def lagrangian(self, t, q, omega, args):
        return self.L(t, q, omega, args)

    @property
    def has_forces(self) -> bool:
        return self.forces is not None

    def generalized_force(self, t, q, omega, args):
        return user_forces(self.forces, t, q, omega, args)

    def velocity(self, t, q, omega, args):
        return jnp.cross(omega, q)

    def _angular_acceleration(self, t, q, omega, args):
        qdot = jnp.cross(omega, q)
        p, dL_dq, mixed, hvp = _lagrangian_terms(self.L, t, q, omega, args, qdot)
        f = self.generalized_force(t, q, omega, args)
        force = dL_dq if f is None else dL_dq + f
        rhs = -project(q, mixed - 2.0 * jnp.cross(omega, p)) + jnp.cross(q, force)
        T = tangent_basis(q)
        return from_tangent(T, jnp.linalg.solve(reduced_matrix(hvp, T), to_tangent(T, rhs)))

    def angular_acceleration(self, t, q: Points, omega: Tangents, args: Args = None):
        """`omegadot` from the Euler-Lagrange equations in `(q, omega)` (Proposition 2)."""
        q, omega = self.check_state(q, omega)
        return check_finite(self._angular_acceleration(t, q, omega, args), SINGULAR_MESSAGE)

    def rates(self, t, y, args):
        q, omega = y
        return jnp.cross(omega, q), self._angular_acceleration(t, q, omega, args)

    def _dL_domega(self, t, q, omega, args):
        L = lambda w: check_scalar(self.L(t, q, w, args), "L(t, q, omega, args)")
        return jax.grad(L)(omega)

    def momentum(self, t, q: Points, omega: Tangents, args: Args = None) -> Tangents:
        """The conjugate momentum `pi_i = (I - q_i q_i^T) dL/domega_i`."""
        return project(q, self._dL_domega(t, q, omega, args))

    def energy(self, t, q, omega, args=None):
        """`E = sum_i omega_i . dL/domega_i - L`."""
        return jnp.sum(omega * self._dL_domega(t, q, omega, args)) - self.L(t, q, omega, args)
