"""Kinetic terms: point masses on spheres, with constant scalar inertia (fast path)."""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import unit_tolerance
from .._geometry import vee
from .._inertia import RigidBody
from .base import (
    AbstractEffect,
    AbstractKinetic,
    Drawing,
    ParameterError,
    as_float,
    check_axes,
    check_magnitude,
    check_shape,
    check_sign,
    check_vector,
    number,
    per_item,
)


def chain_inertia(masses: jax.Array, lengths: jax.Array) -> jax.Array:
    """`M_ij = l_i l_j sum_{k>=max(i,j)} m_k`: the scalar inertia of point masses `m_i` at
    `x_i = sum_{j<=i} l_j q_j` (a chain; a moving base is its first point, `l = 1`)."""
    tail = jnp.cumsum(masses[::-1])[::-1]
    idx = jnp.arange(masses.shape[0])
    return jnp.outer(lengths, lengths) * tail[jnp.maximum(idx[:, None], idx)]


def chain_inverse_bands(masses: jax.Array, lengths: jax.Array):
    """The bands of `chain_inertia(masses, lengths)^-1`. `M = L^T diag(m) L` scaled by the
    lengths, `L` lower-triangular ones: `M^-1` is tridiagonal (`L^-1` is bidiagonal)."""
    inv_m = 1.0 / masses
    previous = jnp.concatenate([jnp.zeros_like(inv_m[:1]), inv_m[:-1]])
    return (inv_m + previous) / lengths**2, -inv_m[:-1] / (lengths[:-1] * lengths[1:])


class Chain(AbstractKinetic):
    """The paper's chain: point masses on massless links hanging from a spherical joint.

    Mass `m_i` sits at the tip of link `i` (length `l_i`, along `q_i`), at
    `x_i = base + sum_{j<=i} l_j q_j`; `M_ij = l_i l_j sum_{k>=max(i,j)} m_k` (constant:
    Corollary 1 applies). In a scene with a `Base`, the chain hangs from the moving base
    and `base` is the offset of its first joint from the base's point; on a `RigidBase`
    the offset is its `attach` (body axes) and `base` must be zero.

    **Arguments:**
    - `masses`, `lengths`: `m_i` (kg) and `l_i` (m), `> 0`: one value per link, or a scalar
      for every link.
    - `base`: the pivot, a `(3,)` point (m).
    - `links`: the number of links (needed only when `masses` and `lengths` are scalars).
    - `payload`: a point mass (kg, `>= 0`) carried at the chain's end, added to the last
      link's mass (the load at the end of a cable).
    """

    masses: jax.Array
    lengths: jax.Array
    base: jax.Array
    payload: jax.Array

    def __init__(
        self,
        masses: jax.Array,
        lengths: jax.Array,
        base: jax.Array = (0.0, 0.0, 0.0),
        links: int | None = None,
        payload: jax.Array = 0.0,
    ):
        self.masses, self.lengths = per_item(links, "links", masses=masses, lengths=lengths)
        self.base, self.payload = as_float(base, "base"), as_float(payload, "payload")

    def __check_init__(self):
        check_sign("masses", self.masses, " (kg)")
        check_sign("lengths", self.lengths, " (m)")
        check_vector("base", self.base)
        check_sign("payload", self.payload, " (kg)", strict=False, scalar=True)

    def point_masses(self):
        return self.masses.at[-1].add(self.payload)

    def inertia(self):
        return chain_inertia(self.point_masses(), self.lengths)

    def inverse_inertia_bands(self):
        return chain_inverse_bands(self.point_masses(), self.lengths)

    def positions(self, q):
        return self.base + jnp.cumsum(self.lengths[:, None] * q, axis=0)

    def parents(self):
        return tuple(range(-1, self.n - 1))

    def bends(self):
        return tuple((i, i + 1) for i in range(self.n - 1))

    def drawing(self):
        return Drawing(links=((np.asarray(self.base, float), tuple(range(self.n))),))


class AbstractBase(AbstractEffect):
    """A moving support that carries the scene's one `Chain`: its coordinates `x` join the
    unit vectors in the state (`sm.chain_space`), the chain hanging from its `joint`."""

    mass: eqx.AbstractVar[jax.Array]

    @property
    @abc.abstractmethod
    def m(self) -> int:
        """The number of coordinates `x` (static)."""

    axes: eqx.AbstractVar[jax.Array | None]
    """The `(m, 3)` directions a point-mass base moves along, `None` for a rigid base."""

    @property
    @abc.abstractmethod
    def rigid_body(self) -> RigidBody | None:
        """What the fast path needs of a rigid base, or `None` for a point mass."""

    @abc.abstractmethod
    def point(self, x: jax.Array) -> jax.Array:
        """The base's point (its mass) in the support frame.

        **Arguments:**
        - `x`: its coordinates, `(m,)`.

        **Returns:** a `(3,)` point (m)."""

    @abc.abstractmethod
    def joint(self, x: jax.Array, attitude: jax.Array | None) -> jax.Array:
        """The point the chain hangs from.

        **Arguments:**
        - `x`: the base's coordinates, `(m,)`.
        - `attitude`: its `(1, 3, 3)` rotation (a rigid base), else `None`.

        **Returns:** a `(3,)` point (m)."""

    def check(self, scene):
        if len(scene.kinetic) != 1 or not isinstance(scene.kinetic[0], Chain):
            got = [type(k).__name__ for k in scene.kinetic]
            name = type(self).__name__
            message = f"a {name} carries one Chain: the scene must list exactly one kinetic term"
            raise ParameterError("", f"{message}, a Chain, got {got}")


class Base(AbstractBase):
    """A point-mass base that moves and carries the scene's chain: a cart on a line, a
    trolley in a plane, a drone in space.

    Its coordinates `x` along `axes` join the unit vectors in the scene's state, whose
    space becomes `sm.chain_space(m, n)` (a dict of the two: see there; velocities and
    generalized forces alike); its point is `position + x @ axes`, and the chain hangs
    from it. The scene keeps the O(n) fast path (the base is one more point of the
    chain's inertia). A point does not rotate: torques in the first joint
    (`JointDamping`, `BaseTorque` at link 0) react on the support, as on a fixed pivot;
    a `RigidBase` takes them on its body.

    **Arguments:**
    - `mass`: the base's mass (kg, `> 0`).
    - `axes`: the directions it moves along, `(m, 3)` orthonormal rows: one for a line,
      two for a plane, three (default: `e1`, `e2`, `e3`) for space.
    - `position`: its point at `x = 0`, a `(3,)` point (m).
    """

    mass: jax.Array = eqx.field(converter=number("mass"))
    axes: jax.Array = eqx.field(
        default=((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), converter=number("axes")
    )
    position: jax.Array = eqx.field(default=(0.0, 0.0, 0.0), converter=number("position"))

    def __check_init__(self):
        check_sign("mass", self.mass, " (kg)", scalar=True)
        check_axes("axes", self.axes)
        check_vector("position", self.position)

    @property
    def m(self) -> int:
        return self.axes.shape[-2]

    @property
    def rigid_body(self) -> None:
        return None

    def point(self, x):
        return self.position.astype(x.dtype) + x @ self.axes.astype(x.dtype)

    def joint(self, x, attitude):
        return self.point(x)


def inertia_matrix(x) -> jax.Array:
    """A `(3,)` of principal moments as `diag(x)`; a `(3, 3)` as is."""
    x = as_float(x, "inertia")
    return jnp.diag(x) if jnp.shape(x) == (3,) else x


def check_rigid_inertia(inertia) -> None:
    """A rigid body's inertia (from `inertia_matrix`), unless traced: `(3, 3)`, symmetric
    positive-definite, its principal moments satisfying the triangle inequality."""
    check_shape("inertia", inertia, (3, 3), "three principal moments or a (3, 3) matrix")
    check_magnitude("inertia", inertia)
    if isinstance(inertia, jax.core.Tracer):
        return
    J = np.asarray(inertia, dtype=np.float64)
    tol = unit_tolerance(jnp.result_type(inertia)) * np.max(np.abs(J))
    moments = np.linalg.eigvalsh(J) if np.all(np.isfinite(J)) else np.full(3, np.nan)
    if not (np.max(np.abs(J - J.T)) <= tol and moments[0] > 0):
        message = "inertia must be symmetric positive-definite (kg m^2)"
        raise ParameterError("inertia", f"{message}, got {J.tolist()}")
    if not moments[0] + moments[1] >= moments[2] - tol:
        message = "inertia's principal moments must satisfy J1 + J2 >= J3 (a rigid body's)"
        raise ParameterError("inertia", f"{message}, got {moments.tolist()}")


class RigidBase(AbstractBase):
    """A rigid body that moves freely in space and carries the scene's chain: a quadrotor,
    a helicopter, a spacecraft with a tether.

    Its centre of mass `x` (`(3,)`, world frame) and attitude `R` (body to world) join the
    unit vectors in the state, whose space becomes `sm.chain_space(3, n, attitude=True)`
    (`{"attitude": Rotations(1), "base": Euclidean(3), "spheres": Spheres(n)}`;
    velocities `xdot`, `Rdot`, `qdot`; forces: a force on the centre of mass, a body
    torque, the spheres'). The chain hangs from the body point `attach`; kinetic energy
    `1/2 m |xdot|^2 + 1/2 Omega . J Omega` plus the chain's. The scene keeps the O(n)
    fast path (Newton-Euler at the joint: the body adds a 3x3 block).

    **Arguments:**
    - `mass`: the body's mass (kg, `> 0`).
    - `inertia`: its inertia about the centre of mass in body axes (kg m^2): three
      principal moments `(3,)` or a symmetric positive-definite `(3, 3)` matrix whose
      principal moments satisfy the triangle inequality (`J1 + J2 >= J3`).
    - `attach`: the body point the chain hangs from (m, body frame; default the centre of
      mass).
    - `size`: the length of the arms pictures draw along the body's `+-e1`, `+-e2` and
      `e3` (m, `> 0`; default 0.2; for pictures only).
    """

    mass: jax.Array = eqx.field(converter=number("mass"))
    inertia: jax.Array = eqx.field(converter=inertia_matrix)
    attach: jax.Array = eqx.field(default=(0.0, 0.0, 0.0), converter=number("attach"))
    size: jax.Array = eqx.field(default=0.2, converter=number("size"))

    def __check_init__(self):
        check_sign("mass", self.mass, " (kg)", scalar=True)
        check_rigid_inertia(self.inertia)
        check_vector("attach", self.attach)
        check_sign("size", self.size, " (m)", scalar=True)

    @property
    def m(self) -> int:
        return 3

    @property
    def axes(self) -> None:
        return None

    @property
    def rigid_body(self) -> RigidBody:
        return RigidBody(self.mass, self.inertia, self.attach)

    def point(self, x):
        return x

    def joint(self, x, attitude):
        return x + attitude[0] @ self.attach.astype(x.dtype)

    def check(self, scene):
        super().check(scene)
        offset = scene.kinetic[0].base
        if not isinstance(offset, jax.core.Tracer) and np.any(np.asarray(offset) != 0):
            got = np.asarray(offset).tolist()
            message = (
                "a Chain on a RigidBase hangs from the body point attach: give the offset "
                f"as RigidBase(attach=...) (body axes), not Chain(base=...), got {got}"
            )
            raise ParameterError("base", message)

    def arms(self, x, attitude) -> jax.Array:
        """The ends of the arms a picture draws: `x + size R e` for `e` = `e1`, `-e1`, `e2`,
        `-e2`, `e3`.

        **Arguments:**
        - `x`, `attitude`: the centre of mass `(3,)` and the rotation `(1, 3, 3)`.

        **Returns:** `(5, 3)` points (m)."""
        e = jnp.asarray([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], x.dtype)
        return x + self.size.astype(x.dtype) * e @ attitude[0].T

    def rotational_energy(self, attitude, velocity) -> jax.Array:
        """`1/2 Omega . J Omega`, `Omega = vee(R^T Rdot)`.

        **Arguments:**
        - `attitude`, `velocity`: `R` and `Rdot`, `(1, 3, 3)`.

        **Returns:** a scalar (J)."""
        Omega = vee(attitude[0].T @ velocity[0])
        return 0.5 * Omega @ (self.inertia.astype(Omega.dtype) @ Omega)


class AbstractSphereMasses(AbstractKinetic):
    """Point masses `m_i` each on a sphere of radius `r_i` centred at `c_i`:
    `x_i = c_i + r_i q_i`, `M = diag(m_i r_i^2)`; each sphere its own joint, no bending."""

    masses: eqx.AbstractVar[jax.Array]
    radii: eqx.AbstractVar[jax.Array]
    centers: eqx.AbstractVar[jax.Array]

    def __check_init__(self):
        check_sign("masses", self.masses, " (kg)")
        check_sign("radii", self.radii, " (m)")
        check_shape("centers", self.centers, (self.n, 3), f"a (3,) or ({self.n}, 3) array")

    def point_masses(self):
        return self.masses

    def inertia(self):
        return jnp.diag(self.masses * self.radii**2)

    def inverse_inertia_bands(self):
        d = 1.0 / (self.masses * self.radii**2)
        return d, jnp.zeros_like(d[1:])

    def positions(self, q):
        return self.centers + self.radii[:, None] * q

    def parents(self):
        return (-1,) * self.n

    def bends(self):
        return ()


class Particles(AbstractSphereMasses):
    """Free point masses, each on its own sphere: `x_i = c_i + r_i q_i`.

    **Arguments:**
    - `masses`, `radii`: `m_i` (kg) and `r_i` (m), `> 0`: one per particle, or a scalar
      for every particle.
    - `centers`: `c_i` (m): one `(3,)` centre for all, or an `(n, 3)` array.
    - `count`: the number of particles (needed only when `masses` and `radii` are scalars).
    """

    masses: jax.Array
    radii: jax.Array
    centers: jax.Array

    def __init__(self, masses, radii, centers=(0.0, 0.0, 0.0), count: int | None = None):
        self.masses, self.radii = per_item(count, "count", masses=masses, radii=radii)
        centers = as_float(centers, "centers")
        one = centers.shape == (3,)  # one centre for all; any other shape is checked as is
        self.centers = jnp.broadcast_to(centers, (self.n, 3)) if one else centers

    def drawing(self):  # each particle on a link from its centre
        centers = np.asarray(self.centers, float)
        return Drawing(links=tuple((centers[i], (i,)) for i in range(self.n)))


class SharedSphere(AbstractSphereMasses):
    """Several point masses (beads) moving on one sphere: `x_i = center + radius q_i`.

    **Arguments:**
    - `masses`: `m_i` (kg, `> 0`): one per bead, or a scalar for all `count` beads.
    - `radius`, `center`: the sphere's radius (m, `> 0`) and centre, a `(3,)` point (m).
    - `count`: the number of beads (optional; needed when `masses` is a scalar).
    """

    masses: jax.Array
    radius: jax.Array
    center: jax.Array

    def __init__(self, masses, radius=1.0, center=(0.0, 0.0, 0.0), count: int | None = None):
        self.center, self.radius = as_float(center, "center"), as_float(radius, "radius")
        check_sign("radius", self.radius, " (m)", scalar=True)
        check_vector("center", self.center)
        (self.masses,) = per_item(count, "count", masses=masses)

    @property
    def radii(self):
        return jnp.broadcast_to(self.radius, self.masses.shape)

    @property
    def centers(self):
        return jnp.broadcast_to(self.center, (self.n, 3))

    def drawing(self):  # the beads free on their sphere, drawn
        centre, radius = np.asarray(self.center, float), float(self.radius)
        return Drawing(spheres=((centre, radius),), free=tuple(range(self.n)))
