"""The Corollary-1 fast path: `L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(t, q)` with a
constant scalar inertia matrix `M`. No Hessian of `L` is formed: the reduced mass matrix
is `M_ij T_i^T T_j` and the accelerations come from one Cholesky solve of size 2n."""

import abc
from collections.abc import Callable
from typing import ClassVar

import jax
import jax.numpy as jnp

from ._checks import check_scalar
from ._custom_types import Args, ForceFn, Points, Scalar, Tangents
from ._geometry import dot, project, tangent_basis
from ._lagrangian import AbstractLagrangianSystem
from ._linalg import from_tangent, scalar_inertia_matrix, spd_solve, to_tangent
from ._system import as_time, user_forces


class AbstractConstantInertiaLagrangian(AbstractLagrangianSystem):
    """Base of systems whose kinetic energy is `1/2 sum_jk M_jk qdot_j . qdot_k` with a
    constant symmetric positive-definite `M` (n x n). Subclasses give `inertia` and
    `potential` (and `generalized_force`)."""

    quadratic_in_velocity: ClassVar[bool] = True

    @abc.abstractmethod
    def inertia(self, args: Args) -> jax.Array:
        """The scalar inertia matrix `M`, `(n, n)`."""

    @abc.abstractmethod
    def potential(self, t, q: Points, args: Args) -> Scalar:
        """The potential energy `U(t, q, args)`."""

    def _potential_gradient(self, t, q, args):
        U = lambda q_: check_scalar(self.potential(t, q_, args), "potential(t, q, args)")
        return jax.grad(U)(q)

    def kinetic_energy(self, q, qdot, args) -> Scalar:
        M = self.inertia(args)
        return 0.5 * jnp.sum(M * (qdot @ qdot.T))

    def lagrangian(self, t, q, qdot, args):
        return self.kinetic_energy(q, qdot, args) - self.potential(t, q, args)

    def energy(self, t, q, qdot, args=None):
        return self.kinetic_energy(q, qdot, args) + self.potential(t, q, args)

    def momentum(self, t, q, qdot, args=None):
        return project(q, self.inertia(args).astype(qdot.dtype) @ qdot)

    def _acceleration(self, t, q, qdot, args):
        t = as_time(t, q)
        M = self.inertia(args).astype(q.dtype)
        c = dot(qdot, qdot) * q
        rhs = M @ c - self._potential_gradient(t, q, args)
        f = self.generalized_force(t, q, qdot, args)
        if f is not None:
            rhs = rhs + f
        T = tangent_basis(q)
        a = spd_solve(scalar_inertia_matrix(M, T), to_tangent(T, rhs))
        return from_tangent(T, a) - c

    def velocity_from_momentum(self, t, q, mu, args=None) -> Tangents:
        """The inverse Legendre map: the tangent `qdot` with `P M qdot = mu` (exact)."""
        T = tangent_basis(q)
        M = self.inertia(args).astype(q.dtype)
        return from_tangent(T, spd_solve(scalar_inertia_matrix(M, T), to_tangent(T, mu)))


class ConstantInertiaLagrangian(AbstractConstantInertiaLagrangian):
    """`L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(t, q, args)` on the fast path.

    **Arguments:**
    - `inertia`: the `(n, n)` symmetric positive-definite scalar inertia matrix, or a
      function `inertia(args) -> (n, n)`.
    - `potential`: `U(t, q, args) -> scalar`.
    - `forces`: optional `forces(t, q, qdot, args) -> (n, 3)` (virtual-work convention).

    Gives the same answers as `Lagrangian(L)` for this `L`, without any Hessian.
    """

    inertia_matrix: jax.Array | Callable
    potential_fn: Callable
    forces: ForceFn | None = None

    def __init__(self, inertia, potential, forces=None):
        self.inertia_matrix = inertia if callable(inertia) else jnp.asarray(inertia)
        self.potential_fn = potential
        self.forces = forces

    def __check_init__(self):
        if not callable(self.inertia_matrix):
            shape = jnp.shape(self.inertia_matrix)
            if len(shape) != 2 or shape[0] != shape[1]:
                raise ValueError(f"inertia must be a square (n, n) matrix, got shape {shape}.")

    def inertia(self, args):
        M = self.inertia_matrix
        return M(args) if callable(M) else M

    def potential(self, t, q, args):
        return self.potential_fn(t, q, args)

    @property
    def has_forces(self) -> bool:
        return self.forces is not None

    def generalized_force(self, t, q, qdot, args):
        return user_forces(self.forces, t, q, qdot, args)
