"""`MechanicsTerm`: the diffrax term that carries a mechanical system."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from ._spaces import AbstractSpace, Spheres
from ._system import AbstractSystem


class MechanicsTerm(diffrax.AbstractTerm):
    """The vector field of a sphere_mech system as a diffrax term.

    `diffrax.diffeqsolve(MechanicsTerm(system), solver, t0, t1, dt0, (q0, v0), args=args)`
    integrates `d(q, v)/dt = system.rates(t, (q, v), args)` with the user's own `args`.
    Solvers that need more than the vector field (the variational integrator needs the
    Lagrangian) take the system from this term.

    **Arguments:**
    - `system`: any sphere_mech system (`AbstractSystem`).
    """

    system: AbstractSystem

    def vf(self, t, y, args):
        return self.system.rates(t, y, args)

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        return jax.tree.map(lambda v: control * v, vf)


def _is_mechanics(x) -> bool:
    return isinstance(x, MechanicsTerm)


def system_of(terms) -> AbstractSystem:
    """The system of the `MechanicsTerm` among `terms` (diffrax hands solvers its terms
    wrapped, e.g. to integrate backwards in time)."""
    found = [x for x in jax.tree.leaves(terms, is_leaf=_is_mechanics) if _is_mechanics(x)]
    if len(found) != 1:
        raise ValueError(
            "This solver needs the mechanical system: integrate sphere_mech.MechanicsTerm("
            "system) (as sphere_mech.simulate does), e.g. diffrax.diffeqsolve("
            "sphere_mech.MechanicsTerm(system), solver, t0, t1, dt0, y0, args=args)."
        )
    return found[0].system


def physical_time(terms, t):
    """The physical time of diffrax's time `t`: diffrax integrates `t1 < t0` in the
    reversed time `-t` through wrapped terms, whose `contr` maps intervals back."""
    return terms.contr(0 * t, t)


def space_of(terms, y, solver: str) -> AbstractSpace:
    """The configuration space of the states `y = (q, v)` that `solver` (its name, for
    errors) integrates with `terms`: the space of the system of the `MechanicsTerm` among
    `terms`; with other diffrax terms (which the solvers that only need a vector field,
    `Projected` and `LieRK(..., action="SO3xR3")`, accept), a state of two plain `(n, 3)`
    arrays is on `Spheres()`, anything else needs the `MechanicsTerm`. The state's
    shapes are checked against it (`ValueError`)."""
    if not (isinstance(y, tuple) and len(y) == 2):
        raise ValueError(
            f"{solver} integrates states y = (q, v) of two arrays of shape (n, 3) (points on "
            "(S^2)^n and a tangent vector; dicts of arrays on a mixed space), got "
            f"{jax.tree.map(jnp.shape, y)}."
        )
    found = [x for x in jax.tree.leaves(terms, is_leaf=_is_mechanics) if _is_mechanics(x)]
    if found:
        space = found[0].system.state_space
    elif all(isinstance(x, jax.Array | np.ndarray) for x in y):
        space = Spheres()
    else:
        raise ValueError(
            f"{solver} needs the configuration space of a state of dicts: integrate "
            "sphere_mech.MechanicsTerm(system) (as sphere_mech.simulate does)."
        )
    space.check_shapes(*y)
    return space
