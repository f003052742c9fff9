"""Changes of state variables and of forms: qdot <-> omega <-> mu <-> pi, `angular`
(form 1 -> 2, form 3 -> 4) and `legendre` (form 1 -> 3, form 2 -> 4). The inverse
Legendre map is each Lagrangian system's `velocity_from_momentum` (the constant-inertia
fast path, one linear solve, or Newton)."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from diffrax import RESULTS

from ._hamiltonian import AngularHamiltonian, Hamiltonian
from ._lagrangian import AngularLagrangian
from ._misc import fill_zeros, tree_sub, tree_vdot
from ._spaces import AbstractSpace, Spheres
from ._system import AbstractHamiltonianSystem, AbstractLagrangianSystem, AbstractSystem


def omega_from_qdot(q, qdot):
    """Angular velocities from velocities: `omega_i = q_i x qdot_i`.

    **Arguments:**
    - `q`: points, `(n, 3)` unit vectors.
    - `qdot`: velocities tangent at `q`, `(n, 3)`.

    **Returns:** the angular velocities `omega`, `(n, 3)`, tangent at `q` too.
    """
    return Spheres().from_linear(q, qdot)


def qdot_from_omega(q, omega):
    """Velocities from angular velocities: `qdot_i = omega_i x q_i`.

    **Arguments:**
    - `q`: points, `(n, 3)` unit vectors.
    - `omega`: angular velocities tangent at `q`, `(n, 3)`.

    **Returns:** the velocities `qdot`, `(n, 3)`.
    """
    return Spheres().to_linear(q, omega)


def pi_from_mu(q, mu):
    """Angular momenta from momenta: `pi_i = q_i x mu_i` (the same map as for
    velocities).

    **Arguments:**
    - `q`: points, `(n, 3)` unit vectors.
    - `mu`: momenta tangent at `q` (form 3), `(n, 3)`.

    **Returns:** the angular momenta `pi` (form 4), `(n, 3)`.
    """
    return Spheres().from_linear(q, mu)


def mu_from_pi(q, pi):
    """Momenta from angular momenta: `mu_i = pi_i x q_i`.

    **Arguments:**
    - `q`: points, `(n, 3)` unit vectors.
    - `pi`: angular momenta tangent at `q` (form 4), `(n, 3)`.

    **Returns:** the momenta `mu` (form 3), `(n, 3)`.
    """
    return Spheres().to_linear(q, pi)


class _Reparametrized(eqx.Module):
    """`fn(t, q, w x q, args)`: a function of `qdot` (or, `momentum`, of `mu`) read as a
    function of `omega` (or `pi`) (Euclidean factors keep their variable). A Module, so
    the wrapped system's arrays stay pytree leaves."""

    fn: Callable
    space: AbstractSpace
    momentum: bool = eqx.field(static=True)

    def __call__(self, t, q, w, args):
        space = self.space
        return self.fn(t, q, (space.to_covector if self.momentum else space.to_linear)(q, w), args)


def angular(system: AbstractSystem) -> AbstractSystem:
    """The same system in angular variables.

    A form-1 Lagrangian system becomes an `AngularLagrangian`
    (`L~(q, omega) = L(q, omega x q)`), a `Hamiltonian` becomes an `AngularHamiltonian`
    (`H~(q, pi) = H(q, pi x q)`). Forces are carried over.

    **Arguments:**
    - `system`: a form-1 Lagrangian system (`Lagrangian`, `ConstantInertiaLagrangian`, a
      `Scene`, ...) or a `Hamiltonian`. A system already in angular variables raises
      `TypeError`.

    **Returns:** an `AngularLagrangian` or an `AngularHamiltonian`.
    """
    if system.angular:
        raise TypeError(
            f"angular() takes a form-1 or form-3 system; {type(system).__name__} "
            "is in angular variables already."
        )
    space = system.space
    hamiltonian = isinstance(system, AbstractHamiltonianSystem)
    forces = _Reparametrized(system.forces, space, hamiltonian) if system.has_forces else None
    if isinstance(system, AbstractLagrangianSystem):
        L = _Reparametrized(system.lagrangian, space, False)
        return AngularLagrangian(L, forces, system.quadratic_in_velocity, space)
    if hamiltonian:
        return AngularHamiltonian(_Reparametrized(system.H, space, True), forces, space)
    raise TypeError(f"angular() takes a Lagrangian or Hamiltonian system, got {type(system)}.")


def _velocity(system, t, q, p, args, quadratic):
    """The inverse Legendre map, NaN where it failed (never raised here: inside a run
    that is a result code; the checked `vector_field` raises, naming the transform)."""
    v, result = system.velocity_from_momentum(t, q, p, args, quadratic=quadratic)
    return jax.tree.map(lambda x: jnp.where(result == RESULTS.successful, x, jnp.nan), v)


@eqx.filter_custom_jvp
def _legendre_value(system, t, q, p, args, *, quadratic):
    """`H(t, q, p) = p . v - L(t, q, v)` with `v` the inverse Legendre map of `p`."""
    v = _velocity(system, t, q, p, args, quadratic)
    return tree_vdot(p, v) - system.lagrangian(t, q, v, args)


@_legendre_value.def_jvp
def _legendre_jvp(primals, tangents, *, quadratic):
    """Envelope theorem: no derivative of the inverse Legendre map is needed.

    With `r = p - dL/dv` normal to the spheres at the solution (`r_i = rho_i q_i`) and
    `v` tangent for every `q` (so `q_i . dv_i = -v_i . dq_i`),
    `dH = v . dp - dL|_(v fixed) - sum_i rho_i v_i . dq_i`, where `dL|_(v fixed)` also
    carries the derivatives with respect to `t`, `args` and the system's own arrays.
    Higher derivatives still work: this rule is itself differentiable."""
    system, t, q, p, args = primals
    tangents = fill_zeros(tangents, primals)
    t_system, t_t, t_q, t_p, t_args = tangents
    v = _velocity(system, t, q, p, args, quadratic)

    def L_fixed_v(system_, t_, q_, args_):
        return system_.lagrangian(t_, q_, v, args_)

    L, dL = eqx.filter_jvp(L_fixed_v, (system, t, q, args), (t_system, t_t, t_q, t_args))
    r = tree_sub(p, jax.grad(lambda v_: system.lagrangian(t, q, v_, args))(v))
    dH = -fill_zeros(dL, L)  # a symbolic zero when L depends on no differentiated input
    if t_p is not None:
        dH = dH + tree_vdot(v, t_p)
    if t_q is not None:
        dH = dH + tree_vdot(system.state_space.tangency_covector(q, r, v), t_q)
    return tree_vdot(p, v) - L, dH


class _LegendreH(eqx.Module):
    """`H(t, q, p) = p . v - L(t, q, v)` with `v` the inverse Legendre map of `p`,
    differentiated by the envelope theorem (`_legendre_jvp`), not through the solve."""

    system: AbstractLagrangianSystem
    quadratic: bool | None = eqx.field(static=True)

    def velocity(self, t, q, p, args):
        return _velocity(self.system, t, q, p, args, self.quadratic)

    def __call__(self, t, q, p, args):
        return _legendre_value(self.system, t, q, p, args, quadratic=self.quadratic)


class _LegendreForces(eqx.Module):
    """A Lagrangian system's forces `f(t, q, v)` read as a function of the momentum."""

    H: _LegendreH

    def __call__(self, t, q, p, args):
        system = self.H.system
        return system.forces(t, q, self.H.velocity(t, q, p, args), args)


def legendre(system: AbstractSystem, *, quadratic: bool | None = None) -> AbstractSystem:
    """The Hamiltonian counterpart of a Lagrangian system, computed numerically.

    A form-1 system (`Lagrangian`, `ConstantInertiaLagrangian`, a `Scene`, ...) gives a
    `Hamiltonian` in `(q, mu)`; an `AngularLagrangian` gives an `AngularHamiltonian` in
    `(q, pi)`. The velocity is recovered from the momentum by the system's
    `velocity_from_momentum`: O(n) and exact for constant-inertia systems (chains,
    scenes), one linear solve when `L` is quadratic in the velocity, otherwise Newton's
    method (globalized by a line search when the linear guess leaves the domain of `L`).
    `H` is differentiated by the envelope theorem, not through the solve.

    **Arguments:**
    - `system`: a Lagrangian system (forms 1 and 2); anything else raises `TypeError`.
    - `quadratic`: overrides the system's `quadratic_in_velocity` declaration on the general
      path: `True` assumes `L` is quadratic in the velocity (one linear solve; a wrong
      velocity if it is not), `False` forces Newton's method, `None` (default) keeps the
      system's declaration.

    **Returns:** a `Hamiltonian` (from form 1) or an `AngularHamiltonian` (from form 2),
    with the system's forces carried over.
    """
    if not isinstance(system, AbstractLagrangianSystem):
        raise TypeError(f"legendre() takes a Lagrangian system, got {type(system)}.")
    H = _LegendreH(system, quadratic)
    forces = _LegendreForces(H) if system.has_forces else None
    return (AngularHamiltonian if system.angular else Hamiltonian)(H, forces, system.space)
