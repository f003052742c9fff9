"""`Scene`: the system assembled from exactly the effects it lists."""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from .._inertia import AbstractConstantInertiaLagrangian
from .base import AbstractEffect, AbstractForce, AbstractKinetic, AbstractPotential, ParameterError
from .forces import BaseTorque, TipForce
from .kinetic import Chain
from .potentials import Gravity


class Scene(AbstractConstantInertiaLagrangian):
    """The system `L = sum kinetic - sum potentials`, `f = sum forces` of the listed
    effects, on the Corollary-1 fast path (O(n)); state `(q, qdot)`.

    Kinetic terms stack their spheres in the order given. Only the listed effects are
    traced, each under its class name (no force effect: `forces` is `None`). Each
    effect is checked against the scene (indices, counts) at construction.

    **Arguments:**
    - `effects`: the effects, in any order: at least one kinetic term (`Chain`,
      `Particles`, `SharedSphere`), then any potentials (`Gravity`, `Spring`, `Bending`,
      `PairInteraction`) and forces (`JointDamping`, `BaseTorque`, `TipForce`,
      `VibratingSupport`).
    """

    kinetic: tuple[AbstractKinetic, ...]
    potentials: tuple[AbstractPotential, ...]
    force_effects: tuple[AbstractForce, ...]

    def __init__(self, *effects: AbstractEffect):
        for e in effects:
            if not isinstance(e, AbstractKinetic | AbstractPotential | AbstractForce):
                raise ValueError(f"Scene takes effects (kinetic terms, potentials, forces), "
                                 f"got {type(e).__name__}.")
        self.kinetic = tuple(e for e in effects if isinstance(e, AbstractKinetic))
        self.potentials = tuple(e for e in effects if isinstance(e, AbstractPotential))
        self.force_effects = tuple(e for e in effects if isinstance(e, AbstractForce))
        if not self.kinetic:
            raise ValueError("A scene needs at least one kinetic term (Chain, Particles "
                             "or SharedSphere).")

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
        return self.kinetic + self.potentials + self.force_effects

    def _offsets(self) -> list[int]:
        return list(np.cumsum([0] + [k.n for k in self.kinetic]))

    def inertia(self, args=None):
        return jsl.block_diag(*[k.inertia() for k in self.kinetic])

    def inverse_inertia_bands(self, args=None):
        """The bands of `M^-1`: `M` is block-diagonal over the kinetic terms and each
        block has a tridiagonal inverse, so `M^-1` is tridiagonal (zero coupling between
        blocks): O(n) solves.

        **Arguments:**
        - `args`: unused (the inertia is the effects' own).

        **Returns:** its diagonal `(n,)` and off-diagonal `(n - 1,)`.
        """
        bands = [k.inverse_inertia_bands() for k in self.kinetic]
        d = jnp.concatenate([b[0] for b in bands])
        zero = jnp.zeros((1,), dtype=d.dtype)
        e = jnp.concatenate([part for k, b in enumerate(bands)
                             for part in ((zero,) if k else ()) + (b[1],)])
        return d, e

    def masses(self) -> jax.Array:
        """The point masses of the kinetic terms, in the order of the spheres.

        **Returns:** an `(n,)` array (kg).
        """
        return jnp.concatenate([k.masses for k in self.kinetic])

    def positions(self, q: jax.Array) -> jax.Array:
        """Positions of the masses in the support frame.

        **Arguments:**
        - `q`: the scene's unit vectors, `(n, 3)`.

        **Returns:** the positions, `(n, 3)` (m).
        """
        o = self._offsets()
        return jnp.concatenate(
            [k.positions(q[a:b]) for k, a, b in zip(self.kinetic, o[:-1], o[1:], strict=True)]
        ).astype(q.dtype)

    def parents(self) -> np.ndarray:
        """The joint structure of the scene.

        **Returns:** the global index of each sphere's parent in its joint (-1: the support),
        an `(n,)` integer array.
        """
        blocks = zip(self.kinetic, self._offsets(), strict=False)
        return np.asarray([p + a if p >= 0 else -1 for k, a in blocks for p in k.parents()],
                          dtype=int)

    def bend_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Where bending stiffness acts.

        **Returns:** global index arrays `(i, j)` of consecutive links.
        """
        blocks = zip(self.kinetic, self._offsets(), strict=False)
        pairs = [(i + a, j + a) for k, a in blocks for i, j in k.bends()]
        return np.asarray(pairs, dtype=int).reshape(-1, 2).T

    def kinetic_energy(self, q, qdot, args=None):
        """`T = 1/2 sum_i m_i |xdot_i|^2`, O(n).

        **Arguments:**
        - `q`: the scene's unit vectors, `(n, 3)`.
        - `qdot`: their velocities, `(n, 3)`.
        - `args`: unused.

        **Returns:** a scalar (J).
        """
        xdot = jax.jvp(self.positions, (q,), (qdot,))[1]
        return (0.5 * jnp.sum(self.masses() * jnp.sum(xdot**2, axis=-1))).astype(q.dtype)

    def potential(self, t, q, args=None):
        U = jnp.zeros((), dtype=q.dtype)
        for p in self.potentials:
            with jax.named_scope(type(p).__name__):
                U = U + p.potential(t, q, self, args).astype(q.dtype)
        return U

    def _force(self, t, q, qdot, args):
        f = jnp.zeros_like(q)
        for e in self.force_effects:
            with jax.named_scope(type(e).__name__):
                f = f + e.generalized_force(t, q, qdot, self, args).astype(q.dtype)
        return f

    @property
    def forces(self) -> Callable | None:
        """`forces(t, q, qdot, args) -> (n, 3)`, the sum of the force effects, or `None`
        when the scene lists none."""
        return self._force if self.force_effects else None


def chain_pendulum(masses, lengths, g=9.81, *, torque=None, tip_force=None) -> Scene:
    """The chain pendulum of Lee, Leok & McClamroch, section V.

    `Scene(Chain(masses, lengths), Gravity(g) [, BaseTorque(torque)] [, TipForce(tip_force)])`,
    with lengths and `g` in the floating dtype of `masses`.

    **Arguments:**
    - `masses`: the masses at the tips of the links (kg), one per link.
    - `lengths`: the link lengths (m), one per link.
    - `g`: gravity (m/s^2), along `-e3`.
    - `torque`: optional torque applied by the base on the first link
      (`f_1 = torque x q_1`): a `(3,)` vector or a function `(t, q, qdot, args) -> (3,)`.
    - `tip_force`: optional force on the last mass: a `(3,)` vector or a function
      `(t, q, qdot, args) -> (3,)`.

    **Returns:** the `Scene` (state `(q, qdot)`, Corollary-1 fast path).
    """
    masses = jnp.asarray(masses)
    dtype = jnp.result_type(masses, float)
    effects = [Chain(masses.astype(dtype), jnp.asarray(lengths, dtype)),
               Gravity(jnp.asarray(g, dtype))]
    effects += [] if torque is None else [BaseTorque(torque)]
    effects += [] if tip_force is None else [TipForce(tip_force)]
    return Scene(*effects)
