"""The abstract base shared by every mechanical system on (S^2)^n."""

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ._checks import check_forces, check_state
from ._custom_types import Args, Points, Scalar, State, Tangents


def as_time(t, like: jax.Array) -> jax.Array:
    """`t` as a scalar array of `like`'s floating dtype (so it can be differentiated)."""
    return jnp.asarray(t, dtype=jnp.result_type(like))


class AbstractSystem(eqx.Module):
    """A mechanical system whose state is `(q, v)`: `q` an `(n, 3)` array of unit vectors
    and `v` the system's second state variable (`qdot`, `omega`, `mu` or `pi`, named by
    `state_name`), tangent to the spheres in every form.

    Concrete systems implement `rates` (the unchecked time derivative of the state, what
    the integrators call), `energy`, `velocity` (the `qdot` of a state) and
    `generalized_force`.
    """

    state_name: ClassVar[str]

    @abc.abstractmethod
    def rates(self, t, y: State, args: Args) -> State:
        """`d(q, v)/dt` at the state `y = (q, v)`, with no input checks: this is the
        vector field handed to diffrax (its stages may be slightly off the spheres)."""

    @abc.abstractmethod
    def energy(self, t, q: Points, v: Tangents, args: Args) -> Scalar:
        """Total energy (the Hamiltonian) at the state `(q, v)`."""

    @abc.abstractmethod
    def velocity(self, t, q: Points, v: Tangents, args: Args) -> Tangents:
        """`qdot` at the state `(q, v)`."""

    @abc.abstractmethod
    def generalized_force(self, t, q: Points, v: Tangents, args: Args) -> Tangents | None:
        """The generalized force `f` (virtual work `sum_i f_i . delta q_i`) at `(q, v)`, or
        `None` when the system has no forces (then no force operation is compiled)."""

    @property
    @abc.abstractmethod
    def has_forces(self) -> bool:
        """Whether non-conservative forces act (static)."""

    def power(self, t, q: Points, v: Tangents, args: Args) -> Scalar:
        """Power of the generalized forces, `sum_i f_i . qdot_i` (zero without forces)."""
        f = self.generalized_force(t, q, v, args)
        if f is None:
            return jnp.zeros((), dtype=jnp.result_type(q))
        return jnp.sum(f * self.velocity(t, q, v, args))

    def check_state(self, q: Points, v: Tangents) -> State:
        """Raise a clear error if `(q, v)` is not a valid state (shape, unit length,
        tangency); returns the unchanged state."""
        return check_state(q, v, self.state_name)


def user_forces(forces, t, q, v, args):
    """Evaluate a user's `forces(t, q, v, args)` (or `None`) and check its shape."""
    if forces is None:
        return None
    return check_forces(forces(t, q, v, args), jnp.shape(q))
