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
from collections.abc import Callable, Mapping
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from diffrax import RESULTS

from ._checks import check_function, check_scalar
from ._custom_types import Args, ForceFn, Points, Scalar
from ._geometry import normalize
from ._linalg import spd_solve, tridiagonal_matvec, tridiagonal_spd_solve
from ._misc import all_finite
from ._spaces import AbstractSpace, Euclidean, Product, Spheres
from ._system import AbstractLagrangianSystem, as_time


class AbstractConstantInertiaLagrangian(AbstractLagrangianSystem):
    """Base of systems whose kinetic energy is `1/2 sum_jk M_jk qdot_j . qdot_k` with a
    constant symmetric positive-definite `M` (n x n); state `(q, qdot)`. Subclasses give
    `inertia`, `potential` and `forces`, and may override `inverse_inertia_bands` (O(n)
    solves) and `kinetic_energy` (a cheaper formula than the dense one)."""

    quadratic_in_velocity: ClassVar[bool] = True
    state_name: ClassVar[str] = "qdot"
    angular: ClassVar[bool] = False

    @property
    def base_axes(self) -> jax.Array | None:
        """The directions a point-mass base moves along, or `None` (the default: the
        spheres hang from a fixed support).

        With a base, configurations are dicts `{"base": (m,), "spheres": (n, 3)}` (the
        base's coordinates along the axes, the unit vectors), velocities and forces alike,
        and `inertia`, `inverse_inertia_bands` and `kinetic_energy` are over the `n + 1`
        points `[base, spheres]`, the base's point being `A^T x` (plus a fixed offset).

        **Returns:** `A`, `(m, 3)` with orthonormal rows (`m` = 1: a line, 2: a plane,
        3: space), or `None`.
        """
        return None

    @property
    def space(self) -> AbstractSpace:
        """`Spheres()`, or with a base `{"base": Euclidean(m), "spheres": Spheres()}` (any
        number of spheres: `check_size` checks it where the system fixes it)."""
        A = self.base_axes
        if A is None:
            return Spheres()
        return Product({"base": Euclidean(A.shape[-2]), "spheres": Spheres()})

    def check_size(self, q) -> None:
        super().check_size(self.spheres(q) if isinstance(q, Mapping) else q)

    def spheres(self, q):
        """The unit vectors of a configuration (`q` itself without a base).

        **Arguments:**
        - `q`: a configuration (or any state-structured value: velocities, forces).

        **Returns:** its `(n, 3)` sphere part.
        """
        return q if self.base_axes is None else q["spheres"]

    def lift(self, v) -> jax.Array:
        """The 3-D rows of a state-structured vector: the base's components along its
        axes become a 3-D vector (`A^T v_base`) stacked before the spheres' rows.

        **Arguments:**
        - `v`: a velocity, force or momentum of this system.

        **Returns:** an `(n, 3)` array, `(n + 1, 3)` with a base.
        """
        A = self.base_axes
        return v if A is None else jnp.concatenate([(v["base"] @ A)[None], v["spheres"]])

    def drop(self, z: jax.Array):
        """The inverse of `lift` on vectors in the base's subspace: `A z_0` and the
        spheres' rows.

        **Arguments:**
        - `z`: 3-D rows as `lift` returns them.

        **Returns:** the state-structured vector.
        """
        A = self.base_axes
        return z if A is None else {"base": A @ z[0], "spheres": z[1:]}

    @abc.abstractmethod
    def inertia(self, args: Args) -> jax.Array:
        """The scalar inertia matrix `M` (over `[base, spheres]` with a base).

        **Arguments:**
        - `args`: the user's `args` (`M` may depend on them, not on `q` or time).

        **Returns:** `M`, `(n, n)` (`(n + 1, n + 1)` with a base), symmetric positive
        definite.
        """

    @abc.abstractmethod
    def potential(self, t, q: Points, args: Args) -> Scalar:
        """The potential energy `U(t, q, args)`.

        **Arguments:**
        - `t`: time.
        - `q`: the configuration: `(n, 3)` unit vectors (a dict with a base).
        - `args`: the user's `args`.

        **Returns:** a scalar.
        """

    def inverse_inertia_bands(self, args: Args) -> tuple[jax.Array, jax.Array] | None:
        """The bands of `M^-1` when it is tridiagonal (then every solve costs O(n)).

        **Arguments:**
        - `args`: the user's `args`.

        **Returns:** its diagonal `(N,)` and off-diagonal `(N - 1,)` (`N` the size of `M`),
        or `None` (the default) for a dense `M`.
        """
        return None

    def kinetic_energy(self, q, qdot, args) -> Scalar:
        """The kinetic energy `1/2 sum_jk M_jk qdot_j . qdot_k`.

        **Arguments:**
        - `q`: the configuration.
        - `qdot`: its velocity (same structure).
        - `args`: the user's `args`.

        **Returns:** a scalar.
        """
        z = self.lift(qdot)
        return 0.5 * jnp.sum(self.inertia(args) * (z @ z.T))

    def lagrangian(self, t, q, qdot, args):
        return self.kinetic_energy(q, qdot, args) - self.potential(t, q, args)

    def energy(self, t, q, qdot, args=None):
        return self.kinetic_energy(q, qdot, args) + self.potential(t, q, args)

    def multiplier_solver(self, q, args: Args) -> Callable:
        """The linear solve of the constrained inertia at the configuration `q`: the map
        `(rhs, target) -> x` with `sum_j M_ij x_j = rhs_i + lam_i q_i` and
        `q_i . x_i = target_i` (one scalar multiplier per sphere; with a base, its row
        also takes the force normal to its subspace that keeps `x_base` in it). With
        `target = 0`, `x` is the tangent vector with `P M x = P rhs`: the inverse of
        `T^T (M kron I) T` applied to `T^T rhs`, without forming it. Everything that
        depends on `q` only is built once, so the map can be applied to many right-hand
        sides (the Newton iterations of `Variational`); each application is O(n) when
        `M^-1` is tridiagonal.

        **Arguments:**
        - `q`: the configuration (its unit vectors are normalized first).
        - `args`: the system's `args` (they may set `M`).

        **Returns:** a function `(rhs, target=None) -> x`, `rhs` and `x` structured as
        the state, `target` of shape `(n,)` (default zeros).
        """
        s = normalize(self.spheres(q))
        k = 0 if self.base_axes is None else 1  # the first sphere's row
        bands = self.inverse_inertia_bands(args)
        if bands is None:
            M = self.inertia(args).astype(s.dtype)
            Minv = spd_solve(M, jnp.eye(M.shape[0], dtype=s.dtype))
            apply = lambda x: jnp.sum(Minv[:, :, None] * x[None], axis=1)
            column = Minv[:, 0]  # Minv e_0, used with a base
            S = Minv[k:, k:] * jnp.sum(s[:, None] * s[None], axis=-1)
        else:
            d, e = (b.astype(s.dtype) for b in bands)
            apply = lambda x: tridiagonal_matvec(d, e, x)
            column = jnp.zeros_like(d).at[: 1 + k].set(jnp.concatenate([d[:1], e[:k]]))
            S_diag, S_off = d[k:], e[k:] * jnp.sum(s[:-1] * s[1:], axis=-1)
        if k:
            # Eliminate the base's normal force `-P w_0 / Minv_00` (w = Minv (rhs + lam q)):
            # x = w - Minv[:, 0] (P w_0) / Minv_00.
            A = self.base_axes.astype(s.dtype)
            P = jnp.eye(3, dtype=s.dtype) - A.T @ A
            c = column[1:] / column[0]
            sPs = (s @ P) @ s.T
            if bands is None:
                S = S - column[0] * jnp.outer(c, c) * sPs
            else:
                S_diag = S_diag.at[0].add(-column[0] * c[0] ** 2 * sPs[0, 0])
        solve = (
            (lambda r: spd_solve(S, r))
            if bands is None
            else (lambda r: tridiagonal_spd_solve(S_diag, S_off, r))
        )

        def multiplier_solve(rhs, target=None):
            y = apply(self.lift(rhs))
            r = -jnp.sum(s * y[k:], axis=-1)
            r = r if target is None else r + target
            if k:
                r = r + c * (s @ (P @ y[0]))
            lam = solve(r)
            w = y + apply(jnp.concatenate([jnp.zeros((k, 3), s.dtype), lam[:, None] * s]))
            if k:
                w = w - column[:, None] * (P @ w[0]) / column[0]
            return self.drop(w)

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
    def n(self) -> int | None:
        return None if callable(self.inertia_matrix) else self.inertia_matrix.shape[0]

    def inertia(self, args):
        M = self.inertia_matrix
        return M(args) if callable(M) else M

    def potential(self, t, q, args):
        return self.potential_fn(t, q, args)
