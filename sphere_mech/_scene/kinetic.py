"""Kinetic terms: point masses on spheres, with constant scalar inertia (fast path)."""

import equinox as eqx
import jax
import jax.numpy as jnp

from .base import AbstractKinetic, as_float, check_scalar_param, check_vector


def _check_1d(**arrays):
    shapes = {k: jnp.shape(v) for k, v in arrays.items()}
    first = next(iter(shapes.values()))
    if len(first) != 1 or first[0] == 0 or any(s != first for s in shapes.values()):
        text = ", ".join(f"{k} {s}" for k, s in shapes.items())
        raise ValueError(f"{' and '.join(shapes)} must be non-empty 1-D arrays of the same "
                         f"length, got shapes {text}.")


class Chain(AbstractKinetic):
    """The paper's chain: point masses `m_i` at the tips of massless links of lengths
    `l_i`, hanging from a spherical joint at `base`. Link `i` points along `q_i` and the
    masses sit at `x_i = base + sum_{j<=i} l_j q_j`.

    `M_ij = l_i l_j sum_{k>=max(i,j)} m_k` (constant: Corollary 1 applies)."""

    masses: jax.Array = eqx.field(converter=as_float)
    lengths: jax.Array = eqx.field(converter=as_float)
    base: jax.Array = eqx.field(default=(0.0, 0.0, 0.0), converter=as_float)

    def __check_init__(self):
        _check_1d(masses=self.masses, lengths=self.lengths)
        check_vector("base", self.base)

    @property
    def n(self) -> int:
        return self.masses.shape[0]

    def inertia(self):
        tail = jnp.cumsum(self.masses[::-1])[::-1]
        idx = jnp.arange(self.n)
        return jnp.outer(self.lengths, self.lengths) * tail[jnp.maximum(idx[:, None], idx)]

    def inverse_inertia_bands(self):
        # M = L^T diag(m) L scaled by the lengths, L lower-triangular ones: M^-1 is
        # tridiagonal (L^-1 is bidiagonal).
        inv_m = 1.0 / self.masses
        previous = jnp.concatenate([jnp.zeros_like(inv_m[:1]), inv_m[:-1]])
        d = (inv_m + previous) / self.lengths**2
        e = -inv_m[:-1] / (self.lengths[:-1] * self.lengths[1:])
        return d, e

    def point_masses(self):
        return self.masses

    def positions(self, q):
        return self.base + jnp.cumsum(self.lengths[:, None] * q, axis=0)

    def parents(self):
        return tuple(range(-1, self.n - 1))

    def bends(self):
        return tuple((i, i + 1) for i in range(self.n - 1))


class Particles(AbstractKinetic):
    """Free point masses, mass `m_i` on its own sphere of radius `r_i` centred at
    `c_i`: `x_i = c_i + r_i q_i`, `M = diag(m_i r_i^2)`."""

    masses: jax.Array
    radii: jax.Array
    centers: jax.Array

    def __init__(self, masses, radii, centers=None):
        self.masses = as_float(masses)
        self.radii = as_float(radii)
        shape = (jnp.shape(self.masses)[0] if jnp.ndim(self.masses) == 1 else 0, 3)
        self.centers = jnp.zeros(shape, self.masses.dtype) if centers is None else as_float(
            centers)

    def __check_init__(self):
        _check_1d(masses=self.masses, radii=self.radii)
        if jnp.shape(self.centers) != (self.n, 3):
            raise ValueError(f"centers must have shape ({self.n}, 3), got "
                             f"{jnp.shape(self.centers)}.")

    @property
    def n(self) -> int:
        return self.masses.shape[0]

    def inertia(self):
        return jnp.diag(self.masses * self.radii**2)

    def inverse_inertia_bands(self):
        d = 1.0 / (self.masses * self.radii**2)
        return d, jnp.zeros_like(d[1:])

    def point_masses(self):
        return self.masses

    def positions(self, q):
        return self.centers + self.radii[:, None] * q


class SharedSphere(AbstractKinetic):
    """Several point masses `m_i` moving on one sphere of radius `radius` centred at
    `center` (beads on a sphere): `x_i = center + radius q_i`."""

    masses: jax.Array = eqx.field(converter=as_float)
    radius: jax.Array = eqx.field(default=1.0, converter=as_float)
    center: jax.Array = eqx.field(default=(0.0, 0.0, 0.0), converter=as_float)

    def __check_init__(self):
        _check_1d(masses=self.masses)
        check_scalar_param("radius", self.radius)
        check_vector("center", self.center)

    @property
    def n(self) -> int:
        return self.masses.shape[0]

    def inertia(self):
        return jnp.diag(self.masses * self.radius**2)

    def inverse_inertia_bands(self):
        d = 1.0 / (self.masses * self.radius**2)
        return d, jnp.zeros_like(d[1:])

    def point_masses(self):
        return self.masses

    def positions(self, q):
        return self.center + self.radius * q
