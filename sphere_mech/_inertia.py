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
the multipliers are the link tensions.

A point-mass base moving in a subspace (a cart on a line, a trolley in a plane, a drone in
space) carrying the spheres keeps this structure (DESIGN.md section 7): its 3-D position
`z_0 = position + A^T x` (`A`, `(m, 3)` orthonormal rows) is one more row of `M`, and the
forces normal to its subspace (`P = I - A^T A`) are eliminated exactly, which changes
only the first sphere's entries of `S` (a rank-one correction): still O(n)."""

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
    """Base of systems whose kinetic energy is `1/2 sum_jk M_jk qdot_j . qdot_k` with a
    constant symmetric positive-definite `M` (n x n); state `(q, qdot)`: the machinery of
    the fast path. Subclasses give `inertia`, `inverse_inertia_bands` (O(n) solves when
    `M^-1` is tridiagonal), `kinetic_energy`, `potential`, `forces`, `base_axes` and
    their `space` (`Scene`, `ConstantInertiaLagrangian`; a user's system subclasses
    `AbstractConstantInertiaLagrangian`).

    With a base (`base_axes` not `None`) the space is `chain_space(m, n)`: states,
    velocities and forces hold the base's coordinates along the axes and the unit
    vectors (`chain_parts`), and `inertia`, `inverse_inertia_bands` and
    `kinetic_energy` are over the `n + 1` points `[base, spheres]`, the base's point
    being `A^T x` (plus a fixed offset)."""

    quadratic_in_velocity: ClassVar[bool] = True
    state_name: ClassVar[str] = "qdot"
    angular: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def base_axes(self) -> jax.Array | None:
        """The directions a point-mass base moves along (`A`, `(m, 3)` with orthonormal
        rows; `m` = 1: a line, 2: a plane, 3: space), or `None`: the spheres hang from a
        fixed support."""

    @abc.abstractmethod
    def inertia(self, args: Args) -> jax.Array:
        """The scalar inertia matrix `M` (over `[base, spheres]` with a base).

        **Arguments:**
        - `args`: the user's `args` (`M` may depend on them, not on `q` or time).

        **Returns:** `M`, `(n, n)` (`(n + 1, n + 1)` with a base), symmetric positive
        definite.
        """

    @abc.abstractmethod
    def inverse_inertia_bands(self, args: Args) -> tuple[jax.Array, jax.Array] | None:
        """The bands of `M^-1` when it is tridiagonal (then every solve costs O(n)).

        **Arguments:**
        - `args`: the user's `args`.

        **Returns:** its diagonal `(N,)` and off-diagonal `(N - 1,)` (`N` the size of `M`),
        or `None` for a dense `M`.
        """

    @abc.abstractmethod
    def kinetic_energy(self, q, qdot, args) -> Scalar:
        """The kinetic energy `1/2 sum_jk M_jk qdot_j . qdot_k`.

        **Arguments:**
        - `q`: the configuration.
        - `qdot`: its velocity (same structure).
        - `args`: the user's `args`.

        **Returns:** a scalar.
        """

    @abc.abstractmethod
    def potential(self, t, q: Points, args: Args) -> Scalar:
        """The potential energy `U(t, q, args)`.

        **Arguments:**
        - `t`: time.
        - `q`: the configuration: `(n, 3)` unit vectors (with a base, the state of a
          `chain_space`).
        - `args`: the user's `args`.

        **Returns:** a scalar.
        """

    def spheres(self, q):
        """The unit vectors of a configuration (`q` itself without a base).

        **Arguments:**
        - `q`: a configuration (or any state-structured value: velocities, forces).

        **Returns:** its `(n, 3)` sphere part.
        """
        return chain_parts(q)[1]

    def lift(self, v) -> jax.Array:
        """The 3-D rows of a state-structured vector: the base's components along its
        axes become a 3-D vector (`A^T v_base`) stacked before the spheres' rows.

        **Arguments:**
        - `v`: a velocity, force or momentum of this system.

        **Returns:** an `(n, 3)` array, `(n + 1, 3)` with a base.
        """
        base, spheres = chain_parts(v)
        return (
            spheres if base is None else jnp.concatenate([(base @ self.base_axes)[None], spheres])
        )

    def drop(self, z: jax.Array):
        """The inverse of `lift` on vectors in the base's subspace: `A z_0` and the
        spheres' rows.

        **Arguments:**
        - `z`: 3-D rows as `lift` returns them.

        **Returns:** the state-structured vector.
        """
        A = self.base_axes
        return z if A is None else chain_state(A @ z[0], z[1:])

    def lagrangian(self, t, q, qdot, args):
        return self.kinetic_energy(q, qdot, args) - self.potential(t, q, args)

    def multiplier_solver(self, q, args: Args) -> Callable:
        """The linear solve of the constrained inertia at the configuration `q`: the map
        `(rhs, target) -> x` with `sum_j M_ij x_j = rhs_i + lam_i q_i` and
        `q_i . x_i = target_i` (one scalar multiplier per sphere; with a base, its row
        also takes the force normal to its subspace that keeps `x_base` in it). With
        `target = 0`, `x` is the tangent vector with `P M x = P rhs`: the inverse of
        `T^T (M kron I) T` applied to `T^T rhs`, without forming it. Everything that
        depends on `q` only is built once (`_Dense` or `_Banded`, with `_BaseRow` for a
        base), so the map can be applied to many right-hand sides (the Newton iterations
        of `Variational`); each application is O(n) when `M^-1` is tridiagonal.

        **Arguments:**
        - `q`: the configuration (its unit vectors are normalized first).
        - `args`: the system's `args` (they may set `M`).

        **Returns:** a function `(rhs, target=None) -> x`, `rhs` and `x` structured as
        the state, `target` of shape `(n,)` (default zeros).
        """
        s = normalize(self.spheres(q))
        bands = self.inverse_inertia_bands(args)
        if bands is None:
            inverse = _Dense(self.inertia(args).astype(s.dtype), s)
        else:
            inverse = _Banded(*(b.astype(s.dtype) for b in bands), s)
        if self.base_axes is not None:
            inverse = _BaseRow(inverse, self.base_axes.astype(s.dtype))

        def multiplier_solve(rhs, target=None):
            return self.drop(inverse.solve(self.lift(rhs), target))

        return multiplier_solve

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
        v = self.multiplier_solver(q, args)(p)
        return v, RESULTS.where(all_finite(v), RESULTS.successful, RESULTS.singular)


class _AbstractInverse(eqx.Module):
    """`M^-1` and the Schur matrix `S_ij = (M^-1)_ij q_i . q_j` of the multipliers at a
    configuration (its unit vectors `s`), over the rows of `lift` (the spheres' rows
    last), built once per configuration."""

    s: eqx.AbstractVar[jax.Array]

    @abc.abstractmethod
    def apply(self, x: jax.Array) -> jax.Array:
        """`M^-1 x` for 3-D rows `x`."""

    @abc.abstractmethod
    def schur_solve(self, r: jax.Array) -> jax.Array:
        """`S^-1 r`."""

    @abc.abstractmethod
    def with_base_row(self, A: jax.Array) -> tuple["_AbstractInverse", jax.Array]:
        """For a base moving along the rows of `A` (its row first): this inverse with
        `S` changed by the elimination of the base's normal force, `Minv_00 c c^T
        (q_i . P q_j)` with `c = Minv[1:, 0] / Minv_00`, `P = I - A^T A` (its first
        diagonal entry only when `M^-1` is tridiagonal), and `M^-1 e_0`."""

    def solve(self, z: jax.Array, target=None) -> jax.Array:
        """`w = M^-1 (z + lam q)` with `q_i . w_i = target_i` (no base)."""
        y = self.apply(z)
        r = -jnp.sum(self.s * y, axis=-1)
        lam = self.schur_solve(r if target is None else r + target)
        return self.add_multipliers(y, lam)

    def add_multipliers(self, y: jax.Array, lam: jax.Array) -> jax.Array:
        """`y + M^-1 (lam q)` (the spheres' rows being the last ones)."""
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
    """A base's row added to `inverse`: the force normal to the base's subspace
    (`P = I - A^T A`) that keeps it there, `-P w_0 / Minv_00` with `w = Minv (rhs + lam q)`,
    is eliminated exactly: `x = w - Minv e_0 (P w_0) / Minv_00`, and `S` changes by a
    rank-one term (`with_base_row`): still O(n)."""

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
    """The fast path of a chain on a fixed support with a dense `M`: no base, no bands,
    `T = 1/2 sum_jk M_jk qdot_j . qdot_k`."""

    @property
    def base_axes(self) -> None:
        return None

    def inverse_inertia_bands(self, args):
        return None

    def kinetic_energy(self, q, qdot, args):
        return 0.5 * jnp.sum(self.inertia(args) * (qdot @ qdot.T))


class AbstractConstantInertiaLagrangian(_AbstractFixedDense):
    """Base of a user's system `L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(t, q, args)` on
    the fast path, hanging from a fixed support: subclasses give `inertia(args)`,
    `potential(t, q, args)` and `forces`; the space is `Spheres()` (any `n`), `M` is
    dense."""

    @property
    def space(self) -> AbstractSpace:
        return Spheres()


class ConstantInertiaLagrangian(_AbstractFixedDense):
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
        """`Spheres(n)` with the inertia matrix's `n` (`Spheres()`, any `n`, for an
        inertia function)."""
        return Spheres(None if callable(self.inertia_matrix) else self.inertia_matrix.shape[0])

    def inertia(self, args):
        M = self.inertia_matrix
        return M(args) if callable(M) else M

    def potential(self, t, q, args):
        return self.potential_fn(t, q, args)
