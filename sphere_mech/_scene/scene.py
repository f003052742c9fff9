"""`Scene`: the system assembled from exactly the effects it lists."""

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from .._inertia import AbstractConstantInertiaLagrangian
from .base import AbstractEffect, AbstractForce, AbstractKinetic, AbstractPotential


class Scene(AbstractConstantInertiaLagrangian):
    """A system on `(S^2)^n` made of the listed effects, usable with `simulate`,
    `legendre`, `angular` and every integrator.

    `Scene(*effects)`: kinetic terms (`Chain`, `Particles`, `SharedSphere`) stack their
    spheres in the order given; `L = sum kinetic - sum potentials` and
    `f = sum forces`. Only the effects listed are traced: with no force effect,
    `generalized_force` is `None` and no force operation is compiled. Every kinetic term
    has a constant scalar inertia with a tridiagonal inverse, so the scene runs on the
    Corollary-1 fast path with O(n) solves (no Hessian, no dense factorization). Each
    effect's operations carry its class name in the jaxpr's name stack.

    The state is `(q, qdot)`; `positions(q)` gives the masses in the support frame.
    """

    kinetic: tuple[AbstractKinetic, ...]
    potentials: tuple[AbstractPotential, ...]
    forces: tuple[AbstractForce, ...]

    def __init__(self, *effects: AbstractEffect):
        if len(effects) == 1 and isinstance(effects[0], list | tuple):
            effects = tuple(effects[0])
        for e in effects:
            if not isinstance(e, AbstractKinetic | AbstractPotential | AbstractForce):
                raise ValueError(f"Scene takes effects (kinetic terms, potentials, forces), "
                                 f"got {type(e).__name__}.")
        self.kinetic = tuple(e for e in effects if isinstance(e, AbstractKinetic))
        self.potentials = tuple(e for e in effects if isinstance(e, AbstractPotential))
        self.forces = tuple(e for e in effects if isinstance(e, AbstractForce))
        if not self.kinetic:
            raise ValueError("A scene needs at least one kinetic term (Chain, Particles "
                             "or SharedSphere).")

    @property
    def n(self) -> int:
        """Number of spheres (static)."""
        return sum(k.n for k in self.kinetic)

    @property
    def effects(self) -> tuple[AbstractEffect, ...]:
        return self.kinetic + self.potentials + self.forces

    def _offsets(self) -> list[int]:
        return list(np.cumsum([0] + [k.n for k in self.kinetic]))

    def inertia(self, args=None):
        return jsl.block_diag(*[k.inertia() for k in self.kinetic])

    def inverse_inertia_bands(self, args=None):
        """`M` is block-diagonal over the kinetic terms and each block has a tridiagonal
        inverse, so `M^-1` is tridiagonal (zero coupling between blocks): O(n) solves."""
        bands = [k.inverse_inertia_bands() for k in self.kinetic]
        d = jnp.concatenate([b[0] for b in bands])
        zero = jnp.zeros((1,), dtype=d.dtype)
        e = jnp.concatenate([part for k, b in enumerate(bands)
                             for part in ((zero,) if k else ()) + (b[1],)])
        return d, e

    def masses(self) -> jax.Array:
        """The `(n,)` point masses."""
        return jnp.concatenate([k.point_masses() for k in self.kinetic])

    def positions(self, q: jax.Array) -> jax.Array:
        """Positions of the masses in the support frame, `(n, 3)`."""
        o = self._offsets()
        return jnp.concatenate(
            [k.positions(q[a:b]) for k, a, b in zip(self.kinetic, o[:-1], o[1:], strict=True)]
        )

    def parents(self) -> np.ndarray:
        """Global index of each sphere's parent in its joint (-1: the support)."""
        out = []
        for k, a in zip(self.kinetic, self._offsets()[:-1], strict=True):
            out += [p + a if p >= 0 else -1 for p in k.parents()]
        return np.asarray(out, dtype=int)

    def bend_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """Global index arrays `(i, j)` of consecutive links."""
        pairs = [(i + a, j + a) for k, a in zip(self.kinetic, self._offsets()[:-1], strict=True)
                 for i, j in k.bends()]
        i, j = (np.asarray(p, dtype=int) for p in zip(*pairs, strict=True)) if pairs else ([], [])
        return np.asarray(i, dtype=int), np.asarray(j, dtype=int)

    def potential(self, t, q, args=None):
        U = jnp.zeros((), dtype=q.dtype)
        for p in self.potentials:
            with jax.named_scope(type(p).__name__):
                U = U + p.potential(t, q, self, args)
        return U

    @property
    def has_forces(self) -> bool:
        return len(self.forces) > 0

    def generalized_force(self, t, q, qdot, args=None):
        if not self.forces:
            return None
        f = jnp.zeros_like(q)
        for e in self.forces:
            with jax.named_scope(type(e).__name__):
                f = f + e.force(t, q, qdot, self, args)
        return f
