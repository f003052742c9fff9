"""Hamiltonian systems: form 3 in `(q, mu)` (Proposition 3) and form 4 in `(q, pi)`
(Proposition 4). They need gradients of `H` only, no linear solve."""

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx

from ._custom_types import ForceFn
from ._misc import tree_sub
from ._spaces import AbstractSpace, Spheres, as_space
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
    - `space`: the configuration space: `Spheres()` (default: plain `(n, 3)` arrays) or
      a dict of factors (`sm.Spheres(n)`, `sm.Euclidean(m)`); states and forces are
      then dicts with its keys. A Euclidean factor's momentum is `dL/dxdot`, with
      `xdot = dH/dp_x`, `p_x' = -dH/dx + f_x`.
    """

    H: Callable
    forces: ForceFn | None = None
    space: AbstractSpace = eqx.field(default_factory=Spheres, converter=as_space)
    state_name: ClassVar[str] = "mu"
    angular: ClassVar[bool] = False

    def _hamilton(self, q, mu, dH_dmu, dH_dq_less_f):
        space = self.space
        transport = space.momentum_transport(q, mu, dH_dmu)
        mudot = tree_sub(transport, space.project(q, dH_dq_less_f))
        return space.project(q, dH_dmu), mudot


class AngularHamiltonian(AbstractHamiltonianSystem):
    """A system given by a Hamiltonian `H(t, q, pi, args) -> scalar` in the momenta
    `pi_i = q_i x mu_i` conjugate to the angular velocities (form 4, Proposition 4); state
    `(q, pi)`.

    **Arguments:**
    - `H`: the Hamiltonian, a JAX function of time, `q` (`(n, 3)` unit vectors), `pi`
      (`(n, 3)` tangent) and `args`.
    - `forces`: optional `forces(t, q, pi, args) -> (n, 3)`, generalized forces with
      virtual work `sum_i f_i . delta q_i`.
    - `space`: the configuration space, as in `Hamiltonian`; only the sphere factors
      have angular momenta, Euclidean factors keep `p_x = dL/dxdot`.
    """

    H: Callable
    forces: ForceFn | None = None
    space: AbstractSpace = eqx.field(default_factory=Spheres, converter=as_space)
    state_name: ClassVar[str] = "pi"
    angular: ClassVar[bool] = True

    def _hamilton(self, q, pi, dH_dpi, dH_dq_less_f):
        space = self.space
        pidot = tree_sub(space.bracket(dH_dpi, pi), space.from_covector(q, dH_dq_less_f))
        return space.to_linear(q, dH_dpi), pidot
