"""Hamiltonian systems: form 3 in `(q, mu)` (Proposition 3) and form 4 in `(q, pi)`
(Proposition 4). They need gradients of `H` only, no linear solve."""

from collections.abc import Callable
from typing import ClassVar

import jax.numpy as jnp

from ._custom_types import ForceFn
from ._geometry import project
from ._system import AbstractHamiltonianSystem


class Hamiltonian(AbstractHamiltonianSystem):
    """A system given by a Hamiltonian `H(t, q, mu, args) -> scalar` in the momenta
    `mu_i = (I - q_i q_i^T) dL/dqdot_i` (form 3, Proposition 3); state `(q, mu)`.

    Hamilton's equations need gradients of `H` only, no linear solve.

    **Arguments:**
    - `H`: the Hamiltonian, a JAX function of time, `q` (`(n, 3)` unit vectors), `mu`
      (`(n, 3)` tangent) and `args`.
    - `forces`: optional `forces(t, q, mu, args) -> (n, 3)`, generalized forces with
      virtual work `sum_i f_i . delta q_i`.
    """

    H: Callable
    forces: ForceFn | None = None
    state_name: ClassVar[str] = "mu"
    angular: ClassVar[bool] = False

    def rates(self, t, y, args):
        q, mu = y
        dH_dq, dH_dmu = self._gradients(t, q, mu, args)
        f = self.generalized_force(t, q, mu, args)
        force = dH_dq if f is None else dH_dq - f
        mudot = -project(q, force) + jnp.cross(dH_dmu, jnp.cross(mu, q))
        return project(q, dH_dmu), mudot


class AngularHamiltonian(AbstractHamiltonianSystem):
    """A system given by a Hamiltonian `H(t, q, pi, args) -> scalar` in the momenta
    `pi_i = q_i x mu_i` conjugate to the angular velocities (form 4, Proposition 4); state
    `(q, pi)`.

    **Arguments:**
    - `H`: the Hamiltonian, a JAX function of time, `q` (`(n, 3)` unit vectors), `pi`
      (`(n, 3)` tangent) and `args`.
    - `forces`: optional `forces(t, q, pi, args) -> (n, 3)`, generalized forces with
      virtual work `sum_i f_i . delta q_i`.
    """

    H: Callable
    forces: ForceFn | None = None
    state_name: ClassVar[str] = "pi"
    angular: ClassVar[bool] = True

    def rates(self, t, y, args):
        q, pi = y
        dH_dq, dH_dpi = self._gradients(t, q, pi, args)
        f = self.generalized_force(t, q, pi, args)
        torque = -dH_dq if f is None else f - dH_dq
        return jnp.cross(dH_dpi, q), jnp.cross(q, torque) + jnp.cross(dH_dpi, pi)
