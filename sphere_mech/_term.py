"""`MechanicsTerm`: the diffrax term that carries a mechanical system."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from ._spaces import AbstractSpace, Spheres
from ._system import AbstractSystem, check_system, vector_field


class MechanicsTerm(diffrax.AbstractTerm):
    """A system's vector field as a diffrax term: `diffrax.diffeqsolve(MechanicsTerm(system),
    solver, t0, t1, dt0, (q0, v0), args=args)` integrates `system.rates`. Solvers that need
    more (the variational integrator: the Lagrangian) take the system from this term.

    **Arguments:**
    - `system`: any sphere_mech system (`AbstractSystem`)."""

    system: AbstractSystem

    def __check_init__(self):
        check_system(self.system, "MechanicsTerm")

    def vf(self, t, y, args):
        return vector_field(self.system, t, y, args)

    def contr(self, t0, t1, **kwargs):
        return t1 - t0

    def prod(self, vf, control):
        return jax.tree.map(lambda v: control * v, vf)


def _mechanics_terms(terms) -> list[MechanicsTerm]:
    """The `MechanicsTerm`s among `terms` (diffrax may wrap them, e.g. backwards in time)."""
    is_mechanics = lambda x: isinstance(x, MechanicsTerm)
    return [x for x in jax.tree.leaves(terms, is_leaf=is_mechanics) if is_mechanics(x)]


def system_of(terms) -> AbstractSystem:
    """The system of the `MechanicsTerm` among `terms`."""
    found = _mechanics_terms(terms)
    if len(found) != 1:
        raise ValueError(
            "This solver needs the mechanical system: integrate sphere_mech.MechanicsTerm("
            "system) (as sphere_mech.simulate does), e.g. diffrax.diffeqsolve("
            "sphere_mech.MechanicsTerm(system), solver, t0, t1, dt0, y0, args=args)."
        )
    return found[0].system


def physical_time(terms, t):
    """The physical time of diffrax's time `t` (`-t` backwards, mapped back by `contr`)."""
    return terms.contr(0 * t, t)


def space_of(terms, y, solver: str) -> AbstractSpace:
    """The space of the states `y = (q, v)` that `solver` integrates with `terms`, `y`'s
    shapes checked: the `MechanicsTerm`'s system's, else `Spheres()` for plain arrays."""
    if not (isinstance(y, tuple) and len(y) == 2):
        raise ValueError(
            f"{solver} integrates states y = (q, v) of two arrays of shape (n, 3) (points on "
            "(S^2)^n and a tangent vector; dicts of arrays on a mixed space), got "
            f"{jax.tree.map(jnp.shape, y)}."
        )
    found = _mechanics_terms(terms)
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
