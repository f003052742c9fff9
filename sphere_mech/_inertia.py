"""The Corollary-1 fast path: `L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(t, q)` with a
constant scalar inertia matrix `M`. No Hessian of `L` is formed.

The projected equations `P_i (sum_j M_ij qddot_j - g_i) = 0`, `q_i . qddot_i = -|qdot_i|^2`
(with `g = -dU/dq + f`) are solved with one scalar multiplier per sphere:
`qddot = M^-1 (g + lam q)` where `S lam = -|qdot|^2 - q . (M^-1 g)` and
`S_ij = (M^-1)_ij q_i . q_j` is n x n symmetric positive definite (Schur product of two
positive-definite matrices). This is equivalent to the 2n x 2n tangent-coordinate system
`T^T (M kron I) T`, a quarter of its size, and needs no tangent basis. When `M^-1` is
tridiagonal (the chain pendulum: `M = diag(l) A^T diag(m) A diag(l)` with `A` lower
triangular ones, so `A^-1` is bidiagonal) `S` is tridiagonal too and everything is O(n):
the multipliers are the link tensions."""

import abc
from collections.abc import Callable
from typing import ClassVar

import jax
import jax.numpy as jnp
from diffrax import RESULTS

from ._checks import check_scalar
from ._custom_types import Args, ForceFn, Points, Scalar
from ._geometry import normalize
from ._linalg import spd_solve, tridiagonal_matvec, tridiagonal_spd_solve
from ._spaces import AbstractSpace, Spheres
from ._system import AbstractLagrangianSystem, as_time


class AbstractConstantInertiaLagrangian(AbstractLagrangianSystem):
    """Base of systems whose kinetic energy is `1/2 sum_jk M_jk qdot_j . qdot_k` with a
    constant symmetric positive-definite `M` (n x n); state `(q, qdot)`. Subclasses give
    `inertia`, `potential` and `forces`, and may override `inverse_inertia_bands` (O(n)
    solves) and `kinetic_energy` (a cheaper formula than the dense one)."""

    quadratic_in_velocity: ClassVar[bool] = True
    space: ClassVar[AbstractSpace] = Spheres()
    state_name: ClassVar[str] = "qdot"
    angular: ClassVar[bool] = False

    @abc.abstractmethod
    def inertia(self, args: Args) -> jax.Array:
        """The scalar inertia matrix `M`.

        **Arguments:**
        - `args`: the user's `args` (`M` may depend on them, not on `q` or time).

        **Returns:** `M`, `(n, n)`, symmetric positive definite.
        """

    @abc.abstractmethod
    def potential(self, t, q: Points, args: Args) -> Scalar:
        """The potential energy `U(t, q, args)`.

        **Arguments:**
        - `t`: time.
        - `q`: `(n, 3)` unit vectors.
        - `args`: the user's `args`.

        **Returns:** a scalar.
        """

    def inverse_inertia_bands(self, args: Args) -> tuple[jax.Array, jax.Array] | None:
        """The bands of `M^-1` when it is tridiagonal (then every solve costs O(n)).

        **Arguments:**
        - `args`: the user's `args`.

        **Returns:** its diagonal `(n,)` and off-diagonal `(n - 1,)`, or `None` (the default)
        for a dense `M`.
        """
        return None

    def kinetic_energy(self, q, qdot, args) -> Scalar:
        """The kinetic energy `1/2 sum_jk M_jk qdot_j . qdot_k`.

        **Arguments:**
        - `q`: `(n, 3)` unit vectors.
        - `qdot`: velocities, `(n, 3)`.
        - `args`: the user's `args`.

        **Returns:** a scalar.
        """
        return 0.5 * jnp.sum(self.inertia(args) * (qdot @ qdot.T))

    def lagrangian(self, t, q, qdot, args):
        return self.kinetic_energy(q, qdot, args) - self.potential(t, q, args)

    def energy(self, t, q, qdot, args=None):
        return self.kinetic_energy(q, qdot, args) + self.potential(t, q, args)

    def multiplier_solver(self, q: Points, args: Args) -> Callable:
        """The linear solve of the constrained inertia at the configuration `q`: the map
        `(rhs, target) -> x` with `sum_j M_ij x_j = rhs_i + lam_i q_i` and
        `q_i . x_i = target_i` (one scalar multiplier per sphere). With `target = 0`, `x`
        is the tangent vector with `P M x = P rhs`: the inverse of `T^T (M kron I) T`
        applied to `T^T rhs`, without forming it. Everything that depends on `q` only is
        built once, so the map can be applied to many right-hand sides (the Newton
        iterations of `Variational`); each application is O(n) when `M^-1` is
        tridiagonal.

        **Arguments:**
        - `q`: the `(n, 3)` configuration (normalized first).
        - `args`: the system's `args` (they may set `M`).

        **Returns:** a function `(rhs, target) -> x`, `rhs` and `x` of shape `(n, 3)`,
        `target` of shape `(n,)`.
        """
        q = normalize(q)
        bands = self.inverse_inertia_bands(args)
        if bands is None:
            M = self.inertia(args).astype(q.dtype)
            Minv = spd_solve(M, jnp.eye(M.shape[0], dtype=q.dtype))
            apply = lambda x: jnp.sum(Minv[:, :, None] * x[None], axis=1)
            S = Minv * jnp.sum(q[:, None] * q[None], axis=-1)
            solve = lambda r: spd_solve(S, r)
        else:
            d, e = (b.astype(q.dtype) for b in bands)
            apply = lambda x: tridiagonal_matvec(d, e, x)
            s_off = e * jnp.sum(q[:-1] * q[1:], axis=-1)
            solve = lambda r: tridiagonal_spd_solve(d, s_off, r)

        def multiplier_solve(rhs, target):
            y = apply(rhs)
            lam = solve(target - jnp.sum(q * y, axis=-1))
            return y + apply(lam[:, None] * q)

        return multiplier_solve

    def _vdot(self, t, q, qdot, args):
        t = as_time(t, q)
        U = lambda q_: check_scalar(self.potential(t, q_, args), "potential(t, q, args)")
        g = -jax.grad(U)(q)
        f = self.generalized_force(t, q, qdot, args)
        g = g if f is None else g + f
        return self.multiplier_solver(q, args)(g, -jnp.sum(qdot * qdot, axis=-1))

    def velocity_from_momentum(self, t, q, p, args=None, *, guess=None, quadratic=None,
                               tol=None, max_steps=32):
        """The fast path of the inverse Legendre map: the tangent `qdot` with
        `P M qdot = p`, exact, by the same multiplier solve as the accelerations (O(n) when
        `M^-1` is tridiagonal).

        **Arguments:**
        - `t`: time.
        - `q`: `(n, 3)` unit vectors.
        - `p`: the momentum `mu`, `(n, 3)`.
        - `args`: the user's `args`.
        - `guess`, `quadratic`, `tol`, `max_steps`: the options of the general method; they do
          not apply here.

        **Returns:** `(qdot, result)`: the velocity, `(n, 3)`, and a `RESULTS` code
        (`singular` if it is not finite).
        """
        del guess, quadratic, tol, max_steps
        v = self.multiplier_solver(q, args)(p, jnp.zeros(q.shape[:1], dtype=q.dtype))
        return v, RESULTS.where(jnp.all(jnp.isfinite(v)), RESULTS.successful,
                                RESULTS.singular)


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

    @property
    def n(self) -> int | None:
        return None if callable(self.inertia_matrix) else self.inertia_matrix.shape[0]

    def inertia(self, args):
        M = self.inertia_matrix
        return M(args) if callable(M) else M

    def potential(self, t, q, args):
        return self.potential_fn(t, q, args)
