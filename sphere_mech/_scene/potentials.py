"""Potentials: conservative effects, `U(q)` of the scene's configuration."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._misc import is_integer
from . import base
from .base import AbstractPotential, ParameterError


def safe_norm(x: jax.Array) -> jax.Array:
    """Row-wise norm whose gradient at zero is zero instead of NaN."""
    s = jnp.sum(x * x, axis=-1)
    return jnp.where(s > 0, jnp.sqrt(jnp.where(s > 0, s, 1.0)), 0.0)


class Gravity(AbstractPotential):
    """Uniform gravity. `U = -g sum_i m_i direction . x_i` over the positions `x_i` of the
    masses (a `Base` too).

    **Arguments:**
    - `g`: strength (m/s^2), a scalar `>= 0`.
    - `direction`: the unit vector gravity points along.
    """

    g: jax.Array = eqx.field(default=9.81, converter=base.number("g"))
    direction: jax.Array = eqx.field(default=(0.0, 0.0, -1.0), converter=base.number("direction"))

    def __check_init__(self):
        base.check_sign("g", self.g, " (m/s^2)", strict=False, scalar=True)
        base.check_vector("direction", self.direction, unit=True)

    def potential(self, t, q, scene, args):
        x = scene.points(q)
        return -self.g * jnp.sum(scene.point_masses() * (x @ self.direction))


class Spring(AbstractPotential):
    """A linear spring between two points of the scene. `U = 1/2 k (|x_a - x_b| - L0)^2`.

    **Arguments:**
    - `a`, `b`: the ends: each the index of a mass of the scene (an `int`, static;
      negative counts from the end) or a fixed point in the support frame (a `(3,)` vector).
    - `stiffness`, `rest_length`: `k` (N/m) and `L0` (m), scalars `>= 0`.
    """

    stiffness: jax.Array = eqx.field(converter=base.number("stiffness"))
    rest_length: jax.Array = eqx.field(converter=base.number("rest_length"))
    anchors: jax.Array
    ends: tuple = eqx.field(static=True)

    def __init__(
        self, a: int | jax.Array, b: int | jax.Array, stiffness: jax.Array, rest_length=0.0
    ):
        self.ends = tuple(int(e) if is_integer(e) else None for e in (a, b))
        anchors, what = [], "an integer sphere index or a (3,) anchor point"
        for name, end, i in zip("ab", (a, b), self.ends, strict=True):
            anchor = base.as_float(jnp.zeros(3) if i is not None else end, name, what)
            if i is None:  # a float such as 1.0 is neither: say what an end may be
                base.check_vector(name, anchor, what=what)
            anchors.append(anchor)
        self.anchors = jnp.stack(anchors)
        self.stiffness, self.rest_length = stiffness, rest_length

    def __check_init__(self):
        base.check_sign("stiffness", self.stiffness, " (N/m)", strict=False, scalar=True)
        base.check_sign("rest_length", self.rest_length, " (m)", strict=False, scalar=True)

    def check(self, scene):
        for name, i in zip("ab", self.ends, strict=True):
            if i is not None:
                base.check_index(self, name, i, scene.n)

    def _point(self, k, x):
        return self.anchors[k] if self.ends[k] is None else x[self.ends[k]]

    def potential(self, t, q, scene, args):
        x = scene.positions(q)
        d = safe_norm(self._point(0, x) - self._point(1, x))
        return 0.5 * self.stiffness * (d - self.rest_length) ** 2


class Bending(AbstractPotential):
    """Bending stiffness between consecutive links of every chain.

    `U = k sum_joints (1 - q_i . q_{i+1})`, about `k theta^2 / 2` for small bend angles
    (for a rod of bending stiffness `EI` cut into links of length `l`, `k = EI/l`). Needs
    a `Chain` of two links or more in the scene.

    **Arguments:**
    - `stiffness`: `k` (N m per rad^2), `>= 0`: a scalar or one value per joint.
    """

    stiffness: jax.Array = eqx.field(converter=base.number("stiffness"))

    def __check_init__(self):
        base.check_sign("stiffness", self.stiffness, " (N m per rad^2)", strict=False)

    def check(self, scene):
        joints = len(scene.bend_pairs()[0])
        if joints == 0:
            raise ParameterError("", "Bending needs a Chain with at least two links in the scene")
        if jnp.ndim(self.stiffness):
            what = f"a scalar or {joints} values, one per joint"
            base.check_shape("stiffness", self.stiffness, (joints,), what)

    def potential(self, t, q, scene, args):
        (i, j), s = scene.bend_pairs(), scene.spheres(q)
        return jnp.sum(self.stiffness * (1.0 - jnp.sum(s[i] * s[j], axis=-1)))


MAX_PAIRS = 10**7
"""The most pairs a `PairInteraction` may sum over (its cost and memory grow with them)."""


class PairInteraction(AbstractPotential):
    """A pairwise interaction between masses, `U = k sum_{i<j} c_i c_j / |x_i - x_j|^p`.
    Inverse-distance repulsion of charges `c_i` for `p = 1`, `k > 0`.

    **Arguments:**
    - `strength`, `exponent`: `k` (J m^p) and `p > 0`, scalars.
    - `charges`: one value per interacting mass (default: ones).
    - `masses`: the indices of the interacting masses (static; default: all of the scene),
      at most `MAX_PAIRS` pairs (about 4500 masses).
    """

    strength: jax.Array = eqx.field(converter=base.number("strength"))
    exponent: jax.Array = eqx.field(default=1.0, converter=base.number("exponent"))
    charges: jax.Array | None = eqx.field(
        default=None, converter=lambda c: c if c is None else base.as_float(c, "charges")
    )
    masses: tuple[int, ...] | None = eqx.field(default=None, static=True)

    def __check_init__(self):
        base.check_shape("strength", self.strength, (), "a scalar")
        base.check_sign("exponent", self.exponent, "", scalar=True)
        try:
            ragged = self.masses is not None and np.ndim(self.masses) != 1
        except ValueError:  # NumPy's "inhomogeneous shape"
            ragged = True
        if ragged:  # failed with len() of True in the scene's check, before
            message = "PairInteraction.masses must be a sequence of integer sphere indices"
            raise ParameterError("masses", f"{message}, got {self.masses!r}")

    def _indices(self, n) -> np.ndarray:
        return np.arange(n) if self.masses is None else np.asarray(self.masses, dtype=int)

    def check(self, scene):
        for i in () if self.masses is None else self.masses:
            base.check_index(self, "masses", i, scene.n)
        idx = self._indices(scene.n)
        if len(idx) < 2:
            message = f"PairInteraction needs at least two masses, got {len(idx)}"
            raise ParameterError("masses", message)
        pairs = len(idx) * (len(idx) - 1) // 2
        if pairs > MAX_PAIRS:
            message = f"PairInteraction sums over at most {MAX_PAIRS:.0e} pairs, got {len(idx)}"
            raise ParameterError("masses", f"{message} masses ({pairs:.2e} pairs)")
        repeated = [int(i) for i in np.unique(idx % scene.n) if np.sum(idx % scene.n == i) > 1]
        if repeated:
            message = f"PairInteraction.masses must name each mass once, got {self.masses}"
            raise ParameterError("masses", f"{message} (mass {repeated[0]} twice)")
        if self.charges is not None:
            what = f"one value per interacting mass ({len(idx)})"
            base.check_shape("charges", self.charges, (len(idx),), what)

    def potential(self, t, q, scene, args):
        x = scene.positions(q)
        idx = self._indices(x.shape[0])
        c = jnp.ones(len(idx)) if self.charges is None else jnp.asarray(self.charges)
        i, j = np.triu_indices(len(idx), k=1)
        d = jnp.linalg.norm(x[idx[i]] - x[idx[j]], axis=-1)
        return self.strength * jnp.sum(c[i] * c[j] * d ** (-self.exponent))
