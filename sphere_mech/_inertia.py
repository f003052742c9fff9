"""The Corollary-1 fast path, `L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(t, q)`, constant `M`:
`qddot = M^-1 (g + lam q)` (`g = -dU/dq + f`), `S lam = -|qdot|^2 - q . (M^-1 g)`,
`S_ij = (M^-1)_ij q_i . q_j` (n x n SPD); tridiagonal `M^-1` (chains) makes it O(n), the
multipliers the link tensions. A point-mass base in a subspace (rows `A`, `P = I - A^T A`)
is one more row of `M`, its normal force eliminated exactly: a rank-one change of `S`. A
rigid base (mass `m_b`, body inertia `J`, the chain hung at the body point `d`) is the same
row at the joint `p = x + R d`, whose inverse mass `I/m_b` gains the 3x3 block `K = (R
hat(d)) J^-1 (R hat(d))^T` (again a rank-one change of `S`), with the body's torques and
velocity terms entering as a known acceleration of `p`: still O(n) (Newton-Euler at the
joint)."""

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
from ._geometry import hat, normalize
from ._linalg import spd_solve, tridiagonal_matvec, tridiagonal_spd_solve
from ._misc import all_finite
from ._momentum import check_inverse_options
from ._spaces import AbstractSpace, Spheres, chain_attitude, chain_parts, chain_state
from ._system import AbstractLagrangianSystem, as_time


class RigidBody(eqx.Module):
    """What the fast path needs of a rigid base: its mass `m_b` (scalar), inertia `J`
    about its centre of mass in body axes (`(3, 3)` SPD) and the body point `d` (`(3,)`)
    the chain hangs from. Checked by the scene effect that builds it."""

    mass: jax.Array
    inertia: jax.Array
    attach: jax.Array


class AbstractFastPath(AbstractLagrangianSystem):
    """The fast path's machinery (state `(q, qdot)`): subclasses give `inertia`,
    `inverse_inertia_bands`, `kinetic_energy`, `potential`, `forces`, `base_axes`,
    `rigid_body` and `space`. With a base the space is `chain_space(m, n)` and `M` is over
    the `n + 1` points `[base, spheres]`, the base's point `A^T x` (plus a fixed offset);
    with a rigid base `chain_space(3, n, attitude=True)`, its row the chain's joint."""

    quadratic_in_velocity: ClassVar[bool] = True
    state_name: ClassVar[str] = "qdot"
    angular: ClassVar[bool] = False

    @property
    @abc.abstractmethod
    def base_axes(self) -> jax.Array | None:
        """`A`, the `(m, 3)` orthonormal directions a point-mass base moves along, or `None`
        (a fixed support or a rigid base)."""

    @property
    @abc.abstractmethod
    def rigid_body(self) -> RigidBody | None:
        """The rigid base carrying the chain (`M`'s first row its mass), or `None`."""

    @abc.abstractmethod
    def inertia(self, args: Args) -> jax.Array:
        """The scalar SPD inertia matrix `M(args)` (not a function of `q` or time), `(n, n)`;
        `(n + 1, n + 1)` over `[base, spheres]` with a base (a rigid one: its mass at the
        chain's joint, the rotation apart)."""

    @abc.abstractmethod
    def inverse_inertia_bands(self, args: Args) -> tuple[jax.Array, jax.Array] | None:
        """The diagonal `(N,)` and off-diagonal `(N - 1,)` of `M^-1` when it is tridiagonal
        (O(n) solves), or `None` for a dense `M`."""

    @abc.abstractmethod
    def kinetic_energy(self, q, qdot, args) -> Scalar:
        """The kinetic energy `1/2 sum_jk M_jk qdot_j . qdot_k` (a rigid base's rotation
        added)."""

    @abc.abstractmethod
    def potential(self, t, q: Points, args: Args) -> Scalar:
        """The potential energy `U(t, q, args)`, a scalar (`q` state-structured)."""

    def spheres(self, q):
        """The `(n, 3)` sphere part of a state-structured `q` (`q` itself without a base)."""
        return chain_parts(q)[1]

    def lift(self, v) -> jax.Array:
        """The 3-D rows of a state-structured `v`: `A^T v_base` (with a base; a rigid one's
        as is), then the spheres'."""
        base, spheres = chain_parts(v)
        if base is None:
            return spheres
        A = self.base_axes
        return jnp.concatenate([(base if A is None else base @ A)[None], spheres])

    def drop(self, z: jax.Array):
        """The inverse of `lift` on vectors in the base's subspace (`A z_0`, the spheres)."""
        A = self.base_axes
        return z if A is None else chain_state(A @ z[0], z[1:])

    def lagrangian(self, t, q, qdot, args):
        return self.kinetic_energy(q, qdot, args) - self.potential(t, q, args)

    def multiplier_solver(self, q, args: Args) -> Callable:
        """The solve `(rhs, qdot=None) -> x`, built once per `q`: the tangent `x` with
        `P M x = P rhs` (`sum_j M_ij x_j = rhs_i + lam_i q_i`, `q_i . x_i = 0`; a base's row
        also takes its normal force); given `qdot`, the accelerations instead (`q_i . x_i =
        -|qdot_i|^2`, a rigid base's velocity terms)."""
        s = normalize(self.spheres(q))
        bands = self.inverse_inertia_bands(args)
        if bands is None:
            M = self.inertia(args)
            base = self.base_axes is not None or self.rigid_body is not None
            rows = s.shape[0] + base
            if jnp.shape(M) != (rows, rows):
                raise ValueError(
                    f"inertia(args) must be a ({rows}, {rows}) matrix, one row for each of the "
                    f"{s.shape[0]} points{' and the base' if base else ''}, got shape "
                    f"{jnp.shape(M)}."
                )
            inverse = _Dense(M.astype(s.dtype), s)
        else:
            inverse = _Banded(*(b.astype(s.dtype) for b in bands), s)
        if self.rigid_body is not None:
            return _RigidRow(inverse, self.rigid_body, chain_attitude(q)[0]).solver(self)
        if self.base_axes is not None:
            inverse = _BaseRow(inverse, self.base_axes.astype(s.dtype))

        def solve(rhs, qdot=None):
            target = None if qdot is None else _normal(self.spheres(qdot))
            return self.drop(inverse.solve(self.lift(rhs), target))

        return solve

    def _vdot(self, t, q, qdot, args):
        t = as_time(t, q)
        U = lambda q_: check_scalar(self.potential(t, q_, args), "potential(t, q, args)")
        g = jax.tree.map(jnp.negative, jax.grad(U)(q))
        f = self.generalized_force(t, q, qdot, args)
        g = g if f is None else jax.tree.map(jnp.add, g, f)
        return self.multiplier_solver(q, args)(g, qdot)

    def velocity_from_momentum(
        self, t, q, p, args=None, *, guess=None, quadratic=None, tol=None, max_steps=32
    ):
        """The exact tangent `qdot` with `P M qdot = p` by the multiplier solve (the general
        method's options do not apply, but are checked as there); `(qdot, result)`,
        `singular` if not finite."""
        check_inverse_options(p, guess=guess, quadratic=quadratic, tol=tol, max_steps=max_steps)
        v = self.multiplier_solver(q, args)(p)
        return v, RESULTS.where(all_finite(v), RESULTS.successful, RESULTS.singular)


def _normal(qdot):
    """`q_i . qddot_i` on the spheres: `-|qdot_i|^2`."""
    return -jnp.sum(qdot * qdot, axis=-1)


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
    def base_column(self) -> jax.Array:
        """`M^-1 e_0`, the first row's column (scalars, `(N,)`)."""

    @abc.abstractmethod
    def with_schur_update(self, c: jax.Array, X: jax.Array) -> "_AbstractInverse":
        """`S + (c c^T) * (q_i . X q_j)` for a 3x3 `X`, `c` `(n,)` the first row's coupling
        to the spheres (`c = M^-1[1:, 0] / M^-1_00`; one entry when banded)."""

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
        # Its symmetric part: the kinetic energy sees nothing else (a function's matrix is
        # traced, so its symmetry cannot be checked), and the Cholesky solve reads one half.
        M = 0.5 * (M + M.T)
        self.Minv, self.s = spd_solve(M, jnp.eye(M.shape[0], dtype=s.dtype)), s
        self.S = self.Minv[k:, k:] * jnp.sum(s[:, None] * s[None], axis=-1)

    def apply(self, x):
        return jnp.sum(self.Minv[:, :, None] * x[None], axis=1)

    def schur_solve(self, r):
        return spd_solve(self.S, r)

    def base_column(self):
        return self.Minv[:, 0]

    def with_schur_update(self, c, X):
        return eqx.tree_at(lambda x: x.S, self, self.S + jnp.outer(c, c) * (self.s @ X @ self.s.T))


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

    def base_column(self):
        return jnp.zeros_like(self.d).at[:2].set(jnp.stack([self.d[0], self.e[0]]))

    def with_schur_update(self, c, X):
        first = c[0] ** 2 * (self.s[0] @ X @ self.s[0])
        return eqx.tree_at(lambda x: x.S_diagonal, self, self.S_diagonal.at[0].add(first))


class _BaseRow(eqx.Module):
    """A base's row added to `inverse`: with `w = Minv (rhs + lam q)`,
    `x = w - Minv e_0 (P w_0) / Minv_00` (`S` less `Minv_00 c c^T (q_i . P q_j)`, the
    base's normal force eliminated)."""

    inverse: _AbstractInverse
    P: jax.Array
    column: jax.Array

    def __init__(self, inverse, A):
        self.column, self.P = inverse.base_column(), _normal_projector(A)
        c = self.column[1:] / self.column[0]
        self.inverse = inverse.with_schur_update(c, -self.column[0] * self.P)

    def solve(self, z, target=None):
        inverse, P, s, column = self.inverse, self.P, self.inverse.s, self.column
        c = column[1:] / column[0]
        y = inverse.apply(z)
        r = -jnp.sum(s * y[1:], axis=-1)
        r = (r if target is None else r + target) + c * (s @ (P @ y[0]))
        w = inverse.add_multipliers(y, inverse.schur_solve(r))
        return w - column[:, None] * (P @ w[0]) / column[0]


class _RigidRow(eqx.Module):
    """A rigid base's row: the chain's joint `p = x + R d`. Newton-Euler: the body takes
    the force `F` its row carries (`u . (rhs + lam q)`, `u = M^-1 e_0 / M^-1_00`, the base's
    force `f_x` included), `m_b xddot = F`, `J Omegadot = tau' + d x R^T F` with `tau' =
    tau - d x R^T f_x` (`f_x` moved from the centre of mass to the joint) and with
    accelerations the gyroscopic `J Omega x Omega`; so `pddot = F / m_b + K F + b`, `K =
    (R hat(d)) J^-1 (R hat(d))^T`, `b = (R J^-1 tau') x (R d)` plus `R (Omega x (Omega x
    d))`. `Minv = Minv_0 + u u^T K`: a rank-one change of `S`, the solve still O(n)."""

    inverse: _AbstractInverse
    u: jax.Array
    R: jax.Array
    mass: jax.Array
    J: jax.Array
    Jinv: jax.Array
    d: jax.Array
    K: jax.Array

    def __init__(self, inverse, body, R):
        self.R, self.mass = R, body.mass.astype(R.dtype)
        self.J, self.d = body.inertia.astype(R.dtype), body.attach.astype(R.dtype)
        self.Jinv = spd_solve(self.J, jnp.eye(3, dtype=R.dtype))  # factorized once
        column = inverse.base_column()
        self.u = column / column[0]
        lever = R @ hat(self.d)
        self.K = lever @ self.Jinv @ lever.T
        self.inverse = inverse.with_schur_update(self.u[1:], self.K)

    def total(self, x):
        """`Minv x` with the body's rotation: `Minv_0 x + u K (u . x)`."""
        return self.inverse.apply(x) + self.u[:, None] * (self.K @ (self.u @ x))

    def solve(self, z, torque, target, joint):
        """Rows `z` (`[f_x, spheres]`), the body torque about the centre of mass, the
        spheres' `q_i . x_i` and the joint's known acceleration: `(F, Omegadot, spheres)`,
        `F` the force on the body (`xddot = F / m_b`)."""
        inverse, s, R, Jinv, d = self.inverse, self.inverse.s, self.R, self.Jinv, self.d
        torque = torque - jnp.cross(d, R.T @ z[0])
        b = jnp.cross(R @ (Jinv @ torque), R @ d) + joint
        y = self.total(z) + self.u[:, None] * b
        r = -jnp.sum(s * y[1:], axis=-1)
        lam = inverse.schur_solve(r + target)
        pulls = jnp.concatenate([jnp.zeros_like(s[:1]), lam[:, None] * s])
        F = self.u @ (z + pulls)
        return F, Jinv @ (torque + jnp.cross(d, R.T @ F)), (y + self.total(pulls))[1:]

    def solver(self, system) -> Callable:
        """The fast path's solve `(rhs, qdot=None)` (see `multiplier_solver`)."""
        R, J, d = self.R, self.J, self.d
        rotation = chain_attitude(system.space.factors)

        def solve(rhs, qdot=None):
            torque = rotation.from_covector(R[None], chain_attitude(rhs))[0]
            n = system.spheres(rhs).shape[0]
            target, joint = jnp.zeros(n, R.dtype), jnp.zeros(3, R.dtype)
            if qdot is not None:
                Omega = rotation.from_linear(R[None], chain_attitude(qdot))[0]
                torque = torque + jnp.cross(J @ Omega, Omega)
                joint = R @ jnp.cross(Omega, jnp.cross(Omega, d))
                target = _normal(system.spheres(qdot))
            F, Omegadot, spheres = self.solve(system.lift(rhs), torque, target, joint)
            attitude = rotation.to_linear(R[None], Omegadot[None])
            if qdot is not None:
                normal = rotation.normal_acceleration(R[None], chain_attitude(qdot))
                attitude = attitude - normal
            return chain_state(F / self.mass, spheres, attitude)

        return solve


class _AbstractFixedDense(AbstractFastPath):
    """The fast path on a fixed support with a dense `M`."""

    base_axes: ClassVar[None] = None
    rigid_body: ClassVar[None] = None

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


def check_spd_inertia(M) -> np.ndarray:
    """A concrete inertia matrix `M` as NumPy floats, checked symmetric positive-definite
    (`ValueError`; NaN fails)."""
    M = np.asarray(M, dtype=float)
    smallest = np.linalg.eigvalsh(M)[0] if np.all(np.isfinite(M)) else np.nan
    if not (np.max(np.abs(M - M.T)) <= 1e-10 * np.max(np.abs(M)) and smallest > 0):
        raise ValueError(
            f"inertia must be a symmetric positive-definite matrix "
            f"(got smallest eigenvalue {smallest:g} of {M.tolist()})."
        )
    return M


class ConstantInertiaLagrangian(_AbstractFixedDense):
    """`L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(t, q, args)` on the fast path: the answers of
    `Lagrangian(L)` without any Hessian.

    **Arguments:**
    - `inertia`: the `(n, n)` symmetric positive-definite scalar inertia matrix, or a
      function `inertia(args) -> (n, n)` (traced: its matrix enters through its symmetric
      part, the only part the kinetic energy sees).
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
                check_spd_inertia(self.inertia_matrix)
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
