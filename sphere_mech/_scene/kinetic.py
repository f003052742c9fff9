"""Kinetic terms: point masses on spheres, with constant scalar inertia (fast path)."""

import jax
import jax.numpy as jnp

from .base import AbstractKinetic, as_float, check_shape, check_sign, check_vector, per_item


class Chain(AbstractKinetic):
    """The paper's chain: point masses on massless links hanging from a spherical joint.

    Mass `m_i` sits at the tip of link `i` (length `l_i`, along `q_i`), at
    `x_i = base + sum_{j<=i} l_j q_j`; `M_ij = l_i l_j sum_{k>=max(i,j)} m_k` (constant:
    Corollary 1 applies).

    **Arguments:**
    - `masses`: `m_i` (kg, `> 0`): one value per link, or a scalar for every link.
    - `lengths`: `l_i` (m, `> 0`): one value per link, or a scalar for every link.
    - `base`: the pivot, a `(3,)` point (m).
    - `links`: the number of links (optional; needed when both `masses` and `lengths` are
      scalars).
    """

    masses: jax.Array
    lengths: jax.Array
    base: jax.Array

    def __init__(self, masses: jax.Array, lengths: jax.Array,
                 base: jax.Array = (0.0, 0.0, 0.0), links: int | None = None):
        self.masses, self.lengths = per_item(links, masses=masses, lengths=lengths)
        self.base = as_float(base)

    def __check_init__(self):
        check_sign("masses", self.masses, " (kg)")
        check_sign("lengths", self.lengths, " (m)")
        check_vector("base", self.base)

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

    def positions(self, q):
        return self.base + jnp.cumsum(self.lengths[:, None] * q, axis=0)

    def parents(self):
        return tuple(range(-1, self.n - 1))

    def bends(self):
        return tuple((i, i + 1) for i in range(self.n - 1))


class AbstractSphereMasses(AbstractKinetic):
    """Point masses `m_i` each on a sphere of radius `r_i` centred at `c_i`:
    `x_i = c_i + r_i q_i`, `M = diag(m_i r_i^2)`."""

    masses: jax.Array
    radii: jax.Array
    centers: jax.Array

    def __init__(self, masses, radii, centers, count):
        self.masses, self.radii = per_item(count, masses=masses, radii=radii)
        centers = as_float(centers)
        self.centers = jnp.broadcast_to(centers, (self.n, 3)) if centers.ndim == 1 else centers

    def __check_init__(self):
        check_sign("masses", self.masses, " (kg)")
        check_sign("radii", self.radii, " (m)")
        check_shape("centers", self.centers, (self.n, 3), f"a (3,) or ({self.n}, 3) array")

    def inertia(self):
        return jnp.diag(self.masses * self.radii**2)

    def inverse_inertia_bands(self):
        d = 1.0 / (self.masses * self.radii**2)
        return d, jnp.zeros_like(d[1:])

    def positions(self, q):
        return self.centers + self.radii[:, None] * q


class Particles(AbstractSphereMasses):
    """Free point masses, each on its own sphere: `x_i = c_i + r_i q_i`.

    **Arguments:**
    - `masses`: `m_i` (kg, `> 0`): one per particle, or a scalar for every particle.
    - `radii`: `r_i` (m, `> 0`): one per particle, or a scalar for every particle.
    - `centers`: `c_i` (m): one `(3,)` centre for all, or an `(n, 3)` array.
    - `count`: the number of particles (optional; needed when `masses` and `radii` are
      scalars).
    """

    def __init__(self, masses: jax.Array, radii: jax.Array,
                 centers: jax.Array = (0.0, 0.0, 0.0), count: int | None = None):
        super().__init__(masses, radii, centers, count)


class SharedSphere(AbstractSphereMasses):
    """Several point masses (beads) moving on one sphere: `x_i = center + radius q_i`.

    **Arguments:**
    - `masses`: `m_i` (kg, `> 0`): one per bead, or a scalar for all `count` beads.
    - `radius`: the sphere's radius (m, `> 0`).
    - `center`: the sphere's centre, a `(3,)` point (m).
    - `count`: the number of beads (optional; needed when `masses` is a scalar).
    """

    def __init__(self, masses: jax.Array, radius: jax.Array = 1.0,
                 center: jax.Array = (0.0, 0.0, 0.0), count: int | None = None):
        check_sign("radius", radius, " (m)", scalar=True)
        check_vector("center", as_float(center))
        super().__init__(masses, radius, center, count)
