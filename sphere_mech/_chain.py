"""The chain pendulum of the paper's section V, on the constant-inertia fast path."""

from collections.abc import Callable

import jax
import jax.numpy as jnp

from ._inertia import AbstractConstantInertiaLagrangian

Drive = jax.Array | Callable | None
"""A constant `(3,)` vector, a function `(t, q, qdot, args) -> (3,)`, or `None`."""


def _evaluate(drive: Drive, t, q, qdot, args, dtype):
    if callable(drive):
        return jnp.asarray(drive(t, q, qdot, args), dtype=dtype)
    return jnp.asarray(drive, dtype=dtype)


class ChainPendulum(AbstractConstantInertiaLagrangian):
    """`n` point masses `m_i` at the tips of massless links of lengths `l_i`, hanging from
    a fixed spherical joint at the origin, in uniform gravity `-g e3`.

    Link `i` points along `q_i`; the masses sit at `x_i = sum_{j<=i} l_j q_j`.
    `masses`, `lengths` and `g` are array leaves (differentiable, vmappable).
    Optional `torque` (applied by the base to link 1) and `tip_force` (at the last mass)
    are constant `(3,)` vectors or functions `(t, q, qdot, args) -> (3,)`; their
    generalized forces are derived from virtual work: `f_1 = torque x q_1`,
    `f_j = l_j tip_force`.
    """

    masses: jax.Array
    lengths: jax.Array
    g: jax.Array
    torque: Drive = None
    tip_force: Drive = None

    def __check_init__(self):
        shapes = (jnp.shape(self.masses), jnp.shape(self.lengths))
        if len(shapes[0]) != 1 or shapes[0] != shapes[1]:
            raise ValueError(
                f"masses and lengths must be 1-D arrays of the same length n, got shapes "
                f"{shapes[0]} and {shapes[1]}."
            )
        if jnp.shape(self.g) != ():
            raise ValueError(f"g must be a scalar, got shape {jnp.shape(self.g)}.")
        for name, drive in (("torque", self.torque), ("tip_force", self.tip_force)):
            if drive is not None and not callable(drive) and jnp.shape(drive) != (3,):
                raise ValueError(f"{name} must be a (3,) vector or a function, got "
                                 f"shape {jnp.shape(drive)}.")

    @property
    def n(self) -> int:
        return self.masses.shape[0]

    def inertia(self, args=None):
        # M_ij = l_i l_j sum_{k >= max(i, j)} m_k
        tail = jnp.cumsum(self.masses[::-1])[::-1]
        idx = jnp.arange(self.n)
        return jnp.outer(self.lengths, self.lengths) * tail[jnp.maximum(idx[:, None], idx)]

    def inverse_inertia_bands(self, args=None):
        # M = diag(l) A^T diag(m) A diag(l) with A lower-triangular ones, so that
        # M^-1 = diag(1/l) A^-1 diag(1/m) A^-T diag(1/l) is tridiagonal (A^-1 bidiagonal).
        inv_m = 1.0 / self.masses
        d = (inv_m + jnp.concatenate([jnp.zeros_like(inv_m[:1]), inv_m[:-1]])) / self.lengths**2
        e = -inv_m[:-1] / (self.lengths[:-1] * self.lengths[1:])
        return d, e

    def positions(self, q: jax.Array) -> jax.Array:
        """Positions of the masses, `x_i = sum_{j<=i} l_j q_j`, shape `(n, 3)`."""
        return jnp.cumsum(self.lengths[:, None].astype(q.dtype) * q, axis=0)

    def potential(self, t, q, args=None):
        return self.g * jnp.sum(self.masses * self.positions(q)[:, 2])

    @property
    def has_forces(self) -> bool:
        return self.torque is not None or self.tip_force is not None

    def generalized_force(self, t, q, qdot, args):
        if not self.has_forces:
            return None
        f = jnp.zeros_like(q)
        if self.tip_force is not None:
            d = _evaluate(self.tip_force, t, q, qdot, args, q.dtype)
            f = f + jax.grad(lambda q_: jnp.dot(d, self.positions(q_)[-1]))(q)
        if self.torque is not None:
            tau = _evaluate(self.torque, t, q, qdot, args, q.dtype)
            f = f.at[0].add(jnp.cross(tau, q[0]))
        return f


def chain_pendulum(masses, lengths, g=9.81, *, torque: Drive = None, tip_force: Drive = None):
    """The chain pendulum of Lee, Leok & McClamroch, section V, as a `ChainPendulum`.

    **Arguments:**
    - `masses`, `lengths`: `(n,)` arrays (positive); `g`: gravitational acceleration.
    - `torque`: optional control torque applied by the base on the first link, a `(3,)`
      vector or `torque(t, q, qdot, args) -> (3,)`.
    - `tip_force`: optional force on the last mass, same forms.

    The state is `(q, qdot)`; accelerations use the constant-inertia fast path.
    """
    masses = jnp.asarray(masses)
    dtype = jnp.result_type(masses, float)
    masses = masses.astype(dtype)
    lengths = jnp.asarray(lengths, dtype=dtype)
    g = jnp.asarray(g, dtype=dtype)
    return ChainPendulum(masses, lengths, g, torque, tip_force)

