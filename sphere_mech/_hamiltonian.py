"""Hamiltonian systems: form 3 in `(q, mu)` (Proposition 3) and form 4 in `(q, pi)`
(Proposition 4). They need gradients of `H` only, no linear solve."""

from collections.abc import Callable
from typing import ClassVar

import jax
import jax.numpy as jnp

from ._checks import check_finite, check_scalar
from ._custom_types import Args, ForceFn, Points, Scalar, State, Tangents
from ._geometry import project
from ._system import AbstractSystem, as_time, user_forces


class _AbstractHamiltonianSystem(AbstractSystem):
    H: Callable
    forces: ForceFn | None = None

    @property
    def has_forces(self) -> bool:
        return self.forces is not None

    def generalized_force(self, t, q, p, args):
        return user_forces(self.forces, t, q, p, args)

    def _gradients(self, t, q, p, args):
        def H(q_, p_):
            return check_scalar(self.H(as_time(t, q), q_, p_, args), "H(t, q, p, args)")

        return jax.grad(H, argnums=(0, 1))(q, p)

    def energy(self, t, q: Points, p: Tangents, args: Args = None) -> Scalar:
        """The Hamiltonian `H(t, q, p, args)`."""
        return self.H(t, q, p, args)

    def vector_field(self, t, q: Points, p: Tangents, args: Args = None) -> State:
        """`(qdot, pdot)` from Hamilton's equations, after checking the state."""
        q, p = self.check_state(q, p)
        qdot, pdot = self.rates(t, (q, p), args)
        message = (
            "Hamilton's equations are not finite at this state: H or its gradient is NaN "
            "or infinite (degenerate Hamiltonian, or NaN parameters)"
        )
        return check_finite(qdot, message), check_finite(pdot, message)


class Hamiltonian(_AbstractHamiltonianSystem):
    """A system given by a Hamiltonian `H(t, q, mu, args) -> scalar` in the momenta
    `mu_i = (I - q_i q_i^T) dL/dqdot_i` (form 3, Proposition 3); state `(q, mu)`.

    `forces(t, q, mu, args) -> (n, 3)` (virtual-work convention).
    """

    state_name: ClassVar[str] = "mu"

    def rates(self, t, y, args):
        q, mu = y
        dH_dq, dH_dmu = self._gradients(t, q, mu, args)
        f = self.generalized_force(t, q, mu, args)
        force = dH_dq if f is None else dH_dq - f
        mudot = -project(q, force) + jnp.cross(dH_dmu, jnp.cross(mu, q))
        return project(q, dH_dmu), mudot

    def velocity(self, t, q, mu, args):
        return project(q, self._gradients(t, q, mu, args)[1])


class AngularHamiltonian(_AbstractHamiltonianSystem):
    """A system given by a Hamiltonian `H(t, q, pi, args) -> scalar` in the momenta
    `pi_i` conjugate to the angular velocities (form 4, Proposition 4); state `(q, pi)`.

    `forces(t, q, pi, args) -> (n, 3)` (virtual-work convention).
    """

    state_name: ClassVar[str] = "pi"

    def rates(self, t, y, args):
        q, pi = y
        dH_dq, dH_dpi = self._gradients(t, q, pi, args)
        f = self.generalized_force(t, q, pi, args)
        torque = -dH_dq if f is None else f - dH_dq
        return jnp.cross(dH_dpi, q), jnp.cross(q, torque) + jnp.cross(dH_dpi, pi)

    def velocity(self, t, q, pi, args):
        return jnp.cross(self._gradients(t, q, pi, args)[1], q)
