"""Potentials: conservative effects, `U(q)` of the scene's configuration."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .base import AbstractPotential, as_float, check_scalar_param, check_vector


def safe_norm(x: jax.Array) -> jax.Array:
    """Row-wise norm whose gradient at zero is zero instead of NaN."""
    s = jnp.sum(x * x, axis=-1)
    nonzero = s > 0
    return jnp.where(nonzero, jnp.sqrt(jnp.where(nonzero, s, 1.0)), 0.0)


class Gravity(AbstractPotential):
    """Uniform gravity of strength `g` along the unit vector `direction` (default
    `-e3`): `U = -g sum_i m_i direction . x_i`."""

    g: jax.Array = eqx.field(default=9.81, converter=as_float)
    direction: jax.Array = eqx.field(default=(0.0, 0.0, -1.0), converter=as_float)

    def __check_init__(self):
        check_scalar_param("g", self.g)
        check_vector("direction", self.direction)

    def potential(self, t, q, scene, args):
        x = scene.positions(q)
        return -self.g * jnp.sum(scene.masses() * (x @ self.direction))


class Spring(AbstractPotential):
    """A linear spring between two points of the scene, `U = 1/2 k (|x_a - x_b| - L0)^2`.

    Each end is either the index of a mass of the scene (an `int`, static) or a fixed
    point in the support frame (a `(3,)` vector)."""

    stiffness: jax.Array = eqx.field(converter=as_float)
    rest_length: jax.Array = eqx.field(converter=as_float)
    anchors: jax.Array
    ends: tuple = eqx.field(static=True)

    def __init__(self, a, b, stiffness, rest_length=0.0):
        ends, anchors = [], []
        for end in (a, b):
            if isinstance(end, int | np.integer):
                ends.append(int(end))
                anchors.append(jnp.zeros(3))
            else:
                check_vector("a spring end (a mass index or a point)", end)
                ends.append(None)
                anchors.append(as_float(end))
        self.ends = tuple(ends)
        self.anchors = jnp.stack(anchors)
        self.stiffness = stiffness
        self.rest_length = rest_length

    def __check_init__(self):
        check_scalar_param("stiffness", self.stiffness)
        check_scalar_param("rest_length", self.rest_length)

    def _point(self, k, x):
        return self.anchors[k] if self.ends[k] is None else x[self.ends[k]]

    def potential(self, t, q, scene, args):
        x = scene.positions(q)
        d = safe_norm(self._point(0, x) - self._point(1, x))
        return 0.5 * self.stiffness * (d - self.rest_length) ** 2


class Bending(AbstractPotential):
    """Bending stiffness between consecutive links of every chain:
    `U = k sum_joints (1 - q_i . q_{i+1})` (about `k theta^2 / 2` for small bend
    angles; for a rod of bending stiffness `EI` cut into links of length `l`, `k = EI/l`)."""

    stiffness: jax.Array = eqx.field(converter=as_float)

    def __check_init__(self):
        if jnp.ndim(self.stiffness) > 1:
            raise ValueError("stiffness must be a scalar or one value per joint.")

    def potential(self, t, q, scene, args):
        i, j = scene.bend_pairs()
        if len(i) == 0:
            raise ValueError("Bending needs a Chain with at least two links in the scene.")
        return jnp.sum(self.stiffness * (1.0 - jnp.sum(q[i] * q[j], axis=-1)))


class PairInteraction(AbstractPotential):
    """A pairwise interaction between masses, `U = k sum_{i<j} c_i c_j / |x_i - x_j|^p`
    (inverse-distance repulsion of charges `c_i` for `p = 1`, `k > 0`).

    `masses`: the indices of the interacting masses (static; default all of the scene);
    `charges`: one per interacting mass (default ones)."""

    strength: jax.Array = eqx.field(converter=as_float)
    exponent: jax.Array = eqx.field(default=1.0, converter=as_float)
    charges: jax.Array | None = None
    masses: tuple[int, ...] | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        check_scalar_param("strength", self.strength)
        check_scalar_param("exponent", self.exponent)
        if self.charges is not None and jnp.ndim(self.charges) != 1:
            raise ValueError("charges must be a 1-D array (one per interacting mass).")

    def potential(self, t, q, scene, args):
        x = scene.positions(q)
        idx = np.arange(x.shape[0]) if self.masses is None else np.asarray(self.masses)
        if len(idx) < 2:
            raise ValueError("PairInteraction needs at least two masses.")
        c = jnp.ones(len(idx)) if self.charges is None else jnp.asarray(self.charges)
        if c.shape != (len(idx),):
            raise ValueError(f"charges must have one value per interacting mass "
                             f"({len(idx)}), got shape {c.shape}.")
        i, j = np.triu_indices(len(idx), k=1)
        d = jnp.linalg.norm(x[idx[i]] - x[idx[j]], axis=-1)
        return self.strength * jnp.sum(c[i] * c[j] * d ** (-self.exponent))
