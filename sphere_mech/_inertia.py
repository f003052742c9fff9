"""The Corollary-1 fast path, `L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(t, q)`, constant `M`:
`qddot = M^-1 (g + lam q)` (`g = -dU/dq + f`), `S lam = -|qdot|^2 - q . (M^-1 g)`,
`S_ij = (M^-1)_ij q_i . q_j` (n x n SPD); tridiagonal `M^-1` (chains) makes it O(n), the
multipliers the link tensions. A point-mass base in a subspace (rows `A`, `P = I - A^T A`)
is one more row of `M`, its normal force eliminated exactly: a rank-one change of `S`."""

import abc
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from diffrax import RESULTS

from ._checks import check_function, check_scalar
from ._custom_types import Args, ForceFn, Points, Scalar
from ._geometry import normalize
from ._linalg import spd_solve, tridiagonal_matvec, tridiagonal_spd_solve
from ._misc import all_finite
from ._spaces import AbstractSpace, Spheres, chain_parts, chain_state
from ._system import AbstractLagrangianSystem, as_time


class AbstractFastPath(AbstractLagrangianSystem):
    """The fast path's machinery (state `(q, qdot)`): subclasses give `inertia`,
    `inverse_inertia_bands`, `kinetic_energy`, `potential`, `forces`, `base_axes` and
    `space`. With a base the space is `chain_space(m, n)` and `M` is over the `n + 1`
    points `[base, spheres]`, the base's point `A^T x` (plus a fixed offset)."""

    quadratic_in_velocity: ClassVar[bool] = True
    state_name: ClassVar[str] = "qdot"
    angular: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def base_axes(self) -> jax.Array | None:
        """`A`, the `(m, 3)` orthonormal directions a point-mass base moves along, or `None`."""

    @abc.abstractmethod
    def inertia(self, args: Args) -> jax.Array:
        """The scalar SPD inertia matrix `M(args)` (not a function of `q` or time), `(n, n)`;
        `(n + 1, n + 1)` over `[base, spheres]` with a base."""

    @abc.abstractmethod
    def inverse_inertia_bands(self, args: Args) -> tuple[jax.Array, jax.Array] | None:
        """The diagonal `(N,)` and off-diagonal `(N - 1,)` of `M^-1` when it is tridiagonal
        (O(n) solves), or `None` for a dense `M`."""

    @abc.abstractmethod
    def kinetic_energy(self, q, qdot, args) -> Scalar:
        """The kinetic energy `1/2 sum_jk M_jk qdot_j . qdot_k`."""

    @abc.abstractmethod
    def potential(self, t, q: Points, args: Args) -> Scalar:
        """The potential energy `U(t, q, args)`, a scalar (`q` state-structured)."""

    def spheres(self, q):
        """The `(n, 3)` sphere part of a state-structured `q` (`q` itself without a base)."""
        return chain_parts(q)[1]

    def lift(self, v) -> jax.Array:
        """The 3-D rows of a state-structured `v`: `A^T v_base` (with a base), then the spheres'."""
        base, spheres = chain_parts(v)
        return (
            spheres if base is None else jnp.concatenate([(base @ self.base_axes)[None], spheres])
        )

    def drop(self, z: jax.Array):
        """The inverse of `lift` on vectors in the base's subspace (`A z_0`, the spheres)."""
        A = self.base_axes
        return z if A is None else chain_state(A @ z[0], z[1:])

    def lagrangian(self, t, q, qdot, args):
        return self.kinetic_energy(q, qdot, args) - self.potential(t, q, args)

    def multiplier_solver(self, q, args: Args) -> Callable:
        """The solve `(rhs, target=None) -> x`, built once per `q`: `sum_j M_ij x_j = rhs_i +
        lam_i q_i`, `q_i . x_i = target_i` (default 0: the tangent `x` with `P M x = P rhs`);
        a base's row also takes its normal force."""
        s = normalize(self.spheres(q))
        bands = self.inverse_inertia_bands(args)
        if bands is None:
            inverse = _Dense(self.inertia(args).astype(s.dtype), s)
        else:
            inverse = _Banded(*(b.astype(s.dtype) for b in bands), s)
        if self.base_axes is not None:
            inverse = _BaseRow(inverse, self.base_axes.astype(s.dtype))
        return lambda rhs, target=None: self.drop(inverse.solve(self.lift(rhs), target))

    def _vdot(self, t, q, qdot, args):
        t = as_time(t, q)
        U = lambda q_: check_scalar(self.potential(t, q_, args), "potential(t, q, args)")
        g = jax.tree.map(jnp.negative, jax.grad(U)(q))
        f = self.generalized_force(t, q, qdot, args)
        g = g if f is None else jax.tree.map(jnp.add, g, f)
        qdot_s = self.spheres(qdot)
        return self.multiplier_solver(q, args)(g, -jnp.sum(qdot_s * qdot_s, axis=-1))

    def velocity_from_momentum(
        self, t, q, p, args=None, *, guess=None, quadratic=None, tol=None, max_steps=32
    ):
        """The exact tangent `qdot` with `P M qdot = p` by the multiplier solve (the general
        method's options do not apply); `(qdot, result)`, `singular` if not finite."""
        del guess, quadratic, tol, max_steps
        v = self.multiplier_solver(q, args)(p)
        return v, RESULTS.where(all_finite(v), RESULTS.successful, RESULTS.singular)


class _AbstractInverse(eqx.Module):
    """`M^-1` and the Schur matrix `S` at the unit vectors `s`, over `lift`'s rows."""

    s: eqx.AbstractVar[jax.Array]

    @abc.abstractmethod
    def apply(self, x: jax.Array) -> jax.Array:
        """`M^-1 x` for 3-D rows `x`."""

    @abc.abstractmethod
    def schur_solve(self, r: jax.Array) -> jax.Array:
        """`S^-1 r`."""

    @abc.abstractmethod
    def with_base_row(self, A: jax.Array) -> tuple["_AbstractInverse", jax.Array]:
        """`S` less `Minv_00 c c^T (q_i . P q_j)`, `c = Minv[1:, 0] / Minv_00` (the base's
        normal force eliminated; one entry when banded), and `M^-1 e_0`."""

    def solve(self, z: jax.Array, target=None) -> jax.Array:
        """`w = M^-1 (z + lam q)` with `q_i . w_i = target_i` (no base)."""
        y = self.apply(z)
        r = -jnp.sum(self.s * y, axis=-1)
        lam = self.schur_solve(r if target is None else r + target)
        return self.add_multipliers(y, lam)

    def add_multipliers(self, y: jax.Array, lam: jax.Array) -> jax.Array:
        """`y + M^-1 (lam q)`."""
        padding = jnp.zeros((y.shape[0] - self.s.shape[0], 3), self.s.dtype)
        return y + self.apply(jnp.concatenate([padding, lam[:, None] * self.s]))


def _normal_projector(A):
    return jnp.eye(3, dtype=A.dtype) - A.T @ A


class _Dense(_AbstractInverse):
    Minv: jax.Array
    s: jax.Array
    S: jax.Array

    def __init__(self, M, s):
        k = M.shape[0] - s.shape[0]  # the first sphere's row
        self.Minv, self.s = spd_solve(M, jnp.eye(M.shape[0], dtype=s.dtype)), s
        self.S = self.Minv[k:, k:] * jnp.sum(s[:, None] * s[None], axis=-1)

    def apply(self, x):
        return jnp.sum(self.Minv[:, :, None] * x[None], axis=1)

    def schur_solve(self, r):
        return spd_solve(self.S, r)

    def with_base_row(self, A):
        column = self.Minv[:, 0]
        c, sP = column[1:] / column[0], self.s @ _normal_projector(A)
        S = self.S - column[0] * jnp.outer(c, c) * (sP @ self.s.T)
        return eqx.tree_at(lambda x: x.S, self, S), column


class _Banded(_AbstractInverse):
    d: jax.Array
    e: jax.Array
    s: jax.Array
    S_diagonal: jax.Array
    S_off: jax.Array

    def __init__(self, d, e, s):
        k = d.shape[0] - s.shape[0]  # the first sphere's row
        self.d, self.e, self.s = d, e, s
        self.S_diagonal, self.S_off = d[k:], e[k:] * jnp.sum(s[:-1] * s[1:], axis=-1)

    def apply(self, x):
        return tridiagonal_matvec(self.d, self.e, x)

    def schur_solve(self, r):
        return tridiagonal_spd_solve(self.S_diagonal, self.S_off, r)

    def with_base_row(self, A):
        column = jnp.zeros_like(self.d).at[:2].set(jnp.stack([self.d[0], self.e[0]]))
        c0, s0 = column[1] / column[0], self.s[0]
        first = -column[0] * c0**2 * (s0 @ _normal_projector(A) @ s0)
        return eqx.tree_at(lambda x: x.S_diagonal, self, self.S_diagonal.at[0].add(first)), column


class _BaseRow(eqx.Module):
    """A base's row added to `inverse`: with `w = Minv (rhs + lam q)`,
    `x = w - Minv e_0 (P w_0) / Minv_00` (`with_base_row` changes `S`)."""

    inverse: _AbstractInverse
    P: jax.Array
    column: jax.Array

    def __init__(self, inverse, A):
        self.inverse, self.column = inverse.with_base_row(A)
        self.P = _normal_projector(A)

    def solve(self, z, target=None):
        inverse, P, s, column = self.inverse, self.P, self.inverse.s, self.column
        c = column[1:] / column[0]
        y = inverse.apply(z)
        r = -jnp.sum(s * y[1:], axis=-1)
        r = (r if target is None else r + target) + c * (s @ (P @ y[0]))
        w = inverse.add_multipliers(y, inverse.schur_solve(r))
        return w - column[:, None] * (P @ w[0]) / column[0]


class _AbstractFixedDense(AbstractFastPath):
    """The fast path on a fixed support with a dense `M`."""

    base_axes: ClassVar[None] = None

    def inverse_inertia_bands(self, args):
        return None

    def kinetic_energy(self, q, qdot, args):
        return 0.5 * jnp.sum(self.inertia(args) * (qdot @ qdot.T))


class AbstractConstantInertiaLagrangian(_AbstractFixedDense):
    """Base of a user's system `L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(t, q, args)` on the
    fast path, on a fixed support: subclasses give `inertia(args)`, `potential(t, q, args)`
    and `forces`; the space is `Spheres()` (any `n`), `M` dense."""

    @property
    def space(self) -> AbstractSpace:
        return Spheres()


class ConstantInertiaLagrangian(_AbstractFixedDense):
    """`L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(t, q, args)` on the fast path: the answers of
    `Lagrangian(L)` without any Hessian.

    **Arguments:**
    - `inertia`: the `(n, n)` symmetric positive-definite scalar inertia matrix, or a
      function `inertia(args) -> (n, n)`.
    - `potential`: `U(t, q, args) -> scalar`.
    - `forces`: optional `forces(t, q, qdot, args) -> (n, 3)` (virtual-work convention)."""

    inertia_matrix: jax.Array | Callable
    potential_fn: Callable
    forces: ForceFn | None = None

    def __init__(self, inertia, potential, forces=None):
        self.inertia_matrix = inertia if callable(inertia) else jnp.asarray(inertia)
        self.potential_fn, self.forces = potential, forces

    def __check_init__(self):
        if not callable(self.inertia_matrix):
            shape = jnp.shape(self.inertia_matrix)
            if len(shape) != 2 or shape[0] != shape[1]:
                raise ValueError(f"inertia must be a square (n, n) matrix, got shape {shape}.")
            if not isinstance(self.inertia_matrix, jax.core.Tracer):  # concrete: check now
                M = np.asarray(self.inertia_matrix, dtype=float)
                smallest = np.linalg.eigvalsh(M)[0] if np.all(np.isfinite(M)) else np.nan
                if not (np.max(np.abs(M - M.T)) <= 1e-10 * np.max(np.abs(M)) and smallest > 0):
                    raise ValueError(
                        f"inertia must be a symmetric positive-definite matrix "
                        f"(got smallest eigenvalue {smallest:g} of {M.tolist()})."
                    )
        else:
            check_function(self.inertia_matrix, "inertia", "inertia(args)", 1)
        check_function(self.potential_fn, "potential", "U(t, q, args)", 3)

    @property
    def space(self) -> AbstractSpace:
        """`Spheres(n)`, `n` from the matrix (`Spheres()` for an inertia function)."""
        return Spheres(None if callable(self.inertia_matrix) else self.inertia_matrix.shape[0])

    def inertia(self, args):
        M = self.inertia_matrix
        return M(args) if callable(M) else M

    def potential(self, t, q, args):
        return self.potential_fn(t, q, args)
