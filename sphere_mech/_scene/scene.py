"""`Scene`: the system assembled from exactly the effects it lists."""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from .._inertia import AbstractFastPath
from .._misc import tree_dtype
from .._spaces import AbstractSpace, chain_attitude, chain_parts, chain_space, chain_state
from .base import (
    AbstractEffect,
    AbstractForce,
    AbstractKinetic,
    AbstractPotential,
    ParameterError,
    as_float,
)
from .forces import BaseTorque, TipForce
from .kinetic import AbstractBase, Chain, chain_inertia, chain_inverse_bands
from .potentials import Gravity


class Scene(AbstractFastPath):
    """The system `L = sum kinetic - sum potentials`, `f = sum forces` of the listed
    effects, on the Corollary-1 fast path (O(n)); state `(q, qdot)`. Kinetic terms stack
    their spheres in the order given; only the listed effects are traced, each under its
    class name (no force effect: `forces` is `None`), and each is checked against the
    scene (indices, counts) at construction. With a `Base`, the one `Chain` hangs from it
    and the state holds its coordinates `(m,)` beside the unit vectors (`chain_space(m, n)`);
    with a `RigidBase`, its centre of mass `(3,)` and attitude `(1, 3, 3)` too
    (`chain_space(3, n, attitude=True)`).

    **Arguments:**
    - `effects`: in any order: at least one kinetic term (`Chain`, `Particles`,
      `SharedSphere`), at most one base (`Base` or `RigidBase`), any potentials and forces
      (see each).
    """

    kinetic: tuple[AbstractKinetic, ...]
    base: AbstractBase | None
    potentials: tuple[AbstractPotential, ...]
    force_effects: tuple[AbstractForce, ...]

    def __init__(self, *effects: AbstractEffect):
        for e in effects:
            if not isinstance(
                e, AbstractKinetic | AbstractBase | AbstractPotential | AbstractForce
            ):
                what = "effects (kinetic terms, a base, potentials, forces)"
                raise ValueError(f"Scene takes {what}, got {type(e).__name__}.")
        bases = [e for e in effects if isinstance(e, AbstractBase)]
        if len(bases) > 1:
            raise ValueError(f"A scene takes at most one base (Base, RigidBase), got {len(bases)}.")
        self.base = bases[0] if bases else None
        self.kinetic = tuple(e for e in effects if isinstance(e, AbstractKinetic))
        self.potentials = tuple(e for e in effects if isinstance(e, AbstractPotential))
        self.force_effects = tuple(e for e in effects if isinstance(e, AbstractForce))
        if not self.kinetic:
            what = "at least one kinetic term (Chain, Particles or SharedSphere)"
            raise ValueError(f"A scene needs {what}.")

    def __check_init__(self):
        for e in self.effects:
            try:
                e.check(self)
            except ParameterError as error:
                error.effect = e
                raise

    @property
    def n(self) -> int:
        """Number of spheres (static)."""
        return sum(k.n for k in self.kinetic)

    @property
    def effects(self) -> tuple[AbstractEffect, ...]:
        base = () if self.base is None else (self.base,)
        return self.kinetic + base + self.potentials + self.force_effects

    @property
    def space(self) -> AbstractSpace:
        """`Spheres(n)`, or with a `Base` `chain_space(m, n)` (a `RigidBase`: `chain_space(3,
        n, attitude=True)`)."""
        if self.base is None:
            return chain_space(None, self.n)
        return chain_space(self.base.m, self.n, attitude=self.rigid_body is not None)

    @property
    def base_axes(self):
        return None if self.base is None else self.base.axes

    @property
    def rigid_body(self):
        return None if self.base is None else self.base.rigid_body

    def _blocks(self):
        """Each kinetic term with the global indices `start, stop` of its spheres."""
        o = np.cumsum([0] + [k.n for k in self.kinetic])
        return zip(self.kinetic, o[:-1], o[1:], strict=True)

    def _with_base(self) -> tuple[jax.Array, jax.Array]:
        """The masses and lengths of the chain with the base as its first point."""
        chain = self.kinetic[0]
        masses = jnp.concatenate([self.base.mass[None], chain.point_masses()])
        return masses, jnp.concatenate([jnp.ones_like(chain.lengths[:1]), chain.lengths])

    def inertia(self, args=None):
        if self.base is not None:
            return chain_inertia(*self._with_base())
        return jsl.block_diag(*[k.inertia() for k in self.kinetic])

    def inverse_inertia_bands(self, args=None):
        # M is block-diagonal, each block with a tridiagonal inverse: zero coupling between.
        if self.base is not None:
            return chain_inverse_bands(*self._with_base())
        bands = [k.inverse_inertia_bands() for k in self.kinetic]
        d = jnp.concatenate([b[0] for b in bands])
        zero = jnp.zeros((1,), dtype=d.dtype)
        return d, jnp.concatenate([part for b in bands for part in (zero, b[1])][1:])

    def masses(self) -> jax.Array:
        """The point masses of the kinetic terms, sphere by sphere. **Returns:** `(n,)` (kg)."""
        return jnp.concatenate([k.point_masses() for k in self.kinetic])

    def positions(self, q) -> jax.Array:
        """Positions of the masses the spheres carry, in the support frame.

        **Arguments:**
        - `q`: the configuration, `(n, 3)` unit vectors (with a base, `chain_space`'s).

        **Returns:** the positions, `(n, 3)` (m)."""
        base, s = chain_parts(q)
        x = jnp.concatenate([k.positions(s[a:b]) for k, a, b in self._blocks()]).astype(s.dtype)
        return x if base is None else x + self.base.joint(base, chain_attitude(q))

    def points(self, q) -> jax.Array:
        """Positions of every point mass: the base's point (with a `Base`), then `positions`.

        **Arguments:**
        - `q`: the configuration.

        **Returns:** an `(n, 3)` array (`(n + 1, 3)` with a `Base`) (m)."""
        x, base = self.positions(q), chain_parts(q)[0]
        return x if base is None else jnp.concatenate([self.base.point(base)[None], x])

    def drawn_points(self, q) -> jax.Array:
        """The points a picture shows: `points(q)`, then with a `RigidBase` the chain's joint
        and the ends of the body's arms (`RigidBase.arms`).

        **Arguments:**
        - `q`: the configuration.

        **Returns:** `(p, 3)` points (m)."""
        x = self.points(q)
        if self.rigid_body is None:
            return x
        base, attitude = chain_parts(q)[0], chain_attitude(q)
        body = [self.base.joint(base, attitude)[None], self.base.arms(base, attitude)]
        return jnp.concatenate([x, *body])

    def point_masses(self) -> jax.Array:
        """The masses at `points(q)`. **Returns:** `(n,)` (`(n + 1,)` with a `Base`) (kg)."""
        m = self.masses()
        return m if self.base is None else jnp.concatenate([self.base.mass[None], m])

    def on_spheres(self, f: jax.Array):
        """A generalized force on the spheres only, structured as the state.

        **Arguments:**
        - `f`: the spheres' part, `(n, 3)`.

        **Returns:** `f`, or with a base the force with zeros on the base (and attitude)."""
        if self.base is None:
            return f
        attitude = None if self.rigid_body is None else jnp.zeros((1, 3, 3), f.dtype)
        return chain_state(jnp.zeros((self.base.m,), f.dtype), f, attitude)

    def on_base(self, q, force: jax.Array, torque: jax.Array | None = None):
        """A generalized force on the base (and a rigid base's attitude), zeros elsewhere,
        structured as the state; the attitude's part as a covector like `jax.grad`'s,
        `1/2 R hat(torque)` (the scene's `forces` turn it into the body torque).

        **Arguments:**
        - `q`: the configuration.
        - `force`: the base's part, `(m,)` (a rigid base's: at its centre of mass).
        - `torque`: a rigid base's body torque, `(3,)` (default zero).

        **Returns:** the generalized force."""
        f = jnp.zeros((self.n, 3), force.dtype)
        if self.rigid_body is None:
            return chain_state(force, f)
        torque = jnp.zeros((3,), force.dtype) if torque is None else torque
        covector = self._rotation.force_covector(chain_attitude(q), torque[None])
        return chain_state(force, f, covector.astype(force.dtype))

    @property
    def _rotation(self):
        """The attitude's factor (a rigid base only)."""
        return chain_attitude(self.space.factors)

    def parents(self) -> np.ndarray:
        """The joint structure of the scene. **Returns:** each sphere's parent's global
        index (-1: the support), an `(n,)` integer array."""
        parents = [p + a if p >= 0 else -1 for k, a, _ in self._blocks() for p in k.parents()]
        return np.asarray(parents, dtype=int)

    def bend_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Where bending stiffness acts. **Returns:** index arrays `(i, j)` of consecutive links."""
        pairs = [(i + a, j + a) for k, a, _ in self._blocks() for i, j in k.bends()]
        return np.asarray(pairs, dtype=int).reshape(-1, 2).T

    def kinetic_energy(self, q, qdot, args=None):  # 1/2 sum_i m_i |xdot_i|^2, O(n)
        xdot = jax.jvp(self.points, (q,), (qdot,))[1]
        T = 0.5 * jnp.sum(self.point_masses() * jnp.sum(xdot**2, axis=-1))
        if self.rigid_body is not None:
            T = T + self.base.rotational_energy(chain_attitude(q), chain_attitude(qdot))
        return T.astype(xdot.dtype)

    def _sum(self, effects, total, term):
        """`total` plus each effect's `term(e)` (in `total`'s dtype), under its class name."""
        for e in effects:
            with jax.named_scope(type(e).__name__):
                total = jax.tree.map(lambda a, b: a + b.astype(a.dtype), total, term(e))
        return total

    def potential(self, t, q, args=None):
        U = jnp.zeros((), dtype=tree_dtype(q))
        return self._sum(self.potentials, U, lambda p: p.potential(t, q, self, args))

    def _force(self, t, q, qdot, args):
        f = lambda e: e.generalized_force(t, q, qdot, self, args)
        total = self._sum(self.force_effects, self.on_spheres(jnp.zeros_like(self.spheres(q))), f)
        if self.rigid_body is None:
            return total
        # Effects give the attitude's part as a covector (virtual work's gradient): the torque.
        torque = self._rotation.from_covector(chain_attitude(q), chain_attitude(total))
        return chain_state(*chain_parts(total), torque)

    @property
    def forces(self) -> Callable | None:
        """`forces(t, q, qdot, args)`, the sum of the force effects, or `None` if none."""
        return self._force if self.force_effects else None


def chain_pendulum(masses, lengths, g=9.81, *, torque=None, tip_force=None) -> Scene:
    """The chain pendulum of Lee, Leok & McClamroch, section V: `Scene(Chain(masses,
    lengths), Gravity(g) [, BaseTorque(torque)] [, TipForce(tip_force)])`, with lengths
    and `g` in the floating dtype of `masses`.

    **Arguments:**
    - `masses`, `lengths`: one per link: the masses at their tips (kg), their lengths (m).
    - `g`: gravity (m/s^2), along `-e3`.
    - `torque`, `tip_force`: optional torque of the base on the first link (`f_1 = torque x
      q_1`) and force on the last mass, each `(3,)` or a function `(t, q, qdot, args)`.

    **Returns:** the `Scene` (state `(q, qdot)`, Corollary-1 fast path).
    """
    masses = as_float(masses, "masses")  # checked before any conversion: True is no mass
    lengths, g = (
        as_float(x, name).astype(masses.dtype) for x, name in ((lengths, "lengths"), (g, "g"))
    )
    effects = [Chain(masses, lengths), Gravity(g)]
    effects += [] if torque is None else [BaseTorque(torque)]
    effects += [] if tip_force is None else [TipForce(tip_force)]
    return Scene(*effects)
