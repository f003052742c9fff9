"""Changes of state variables and of forms: qdot <-> omega <-> mu <-> pi, `angular`
(form 1 -> 2, form 3 -> 4) and `legendre` (form 1 -> 3, form 2 -> 4)."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from ._checks import check_finite, check_scalar
from ._geometry import tangent_basis
from ._hamiltonian import AngularHamiltonian, Hamiltonian
from ._lagrangian import AbstractLagrangianSystem, AngularLagrangian
from ._linalg import from_tangent, reduced_matrix, to_tangent
from ._system import AbstractSystem


def omega_from_qdot(q, qdot):
    """Angular velocities `omega_i = q_i x qdot_i` (tangent to the sphere)."""
    return jnp.cross(q, qdot)


def qdot_from_omega(q, omega):
    """Velocities `qdot_i = omega_i x q_i`."""
    return jnp.cross(omega, q)


def pi_from_mu(q, mu):
    """Angular momenta `pi_i = q_i x mu_i` (the same map as for velocities)."""
    return jnp.cross(q, mu)


def mu_from_pi(q, pi):
    """Momenta `mu_i = pi_i x q_i`."""
    return jnp.cross(pi, q)


class _Reparametrized(eqx.Module):
    """`fn(t, q, w x q, args)`: a function of `qdot` (or `mu`) read as a function of
    `omega` (or `pi`). A Module, so the wrapped system's arrays stay pytree leaves."""

    fn: Callable

    def __call__(self, t, q, w, args):
        return self.fn(t, q, jnp.cross(w, q), args)


def angular(system: AbstractSystem) -> AbstractSystem:
    """The same system in angular variables: a form-1 Lagrangian system becomes an
    `AngularLagrangian` (`L~(q, omega) = L(q, omega x q)`), a `Hamiltonian` becomes an
    `AngularHamiltonian` (`H~(q, pi) = H(q, pi x q)`). Forces are carried over."""
    forces = _Reparametrized(system.generalized_force) if system.has_forces else None
    quadratic = getattr(system, "quadratic_in_velocity", False)
    if isinstance(system, AbstractLagrangianSystem):
        return AngularLagrangian(_Reparametrized(system.lagrangian), forces, quadratic)
    if isinstance(system, Hamiltonian):
        return AngularHamiltonian(_Reparametrized(system.H), forces)
    raise TypeError(
        f"angular() takes a form-1 Lagrangian system or a Hamiltonian, got {type(system)}."
    )


LEGENDRE_SINGULAR_MESSAGE = (
    "the Legendre transform is not invertible at this state: the reduced mass matrix "
    "T^T (d^2 L / d v^2) T is singular or not finite (degenerate Lagrangian, for example a "
    "zero mass or length, or a sphere without kinetic energy)"
)


def _newton_tolerance(dtype) -> float:
    return float(jnp.finfo(dtype).eps) ** 0.75


def invert_momentum(L, t, q, p, args, *, quadratic: bool, max_steps: int = 32):
    """The tangent velocity `v` with `P dL/dv(t, q, v) = p` (the inverse Legendre map).

    One linear solve (exact when `L` is quadratic in `v`), then, unless `quadratic`,
    Newton's method in tangent coordinates (optimistix), differentiable by the implicit
    function theorem. Solved in a tangent basis, so `v` stays tangent as `q` varies: this
    is what makes Hamilton's equations (Propositions 3 and 4) hold for the resulting `H`.
    """
    T = tangent_basis(q)

    def dL_dv(v):
        return jax.grad(lambda v_: check_scalar(L(t, q, v_, args), "L(t, q, v, args)"))(v)

    def residual(a, _):
        return to_tangent(T, dL_dv(from_tangent(T, a))) - to_tangent(T, p)

    zero = jnp.zeros_like(q)
    p0, hvp = jax.linearize(dL_dv, zero)
    a = jnp.linalg.solve(reduced_matrix(hvp, T), to_tangent(T, p - p0))
    a = check_finite(a, LEGENDRE_SINGULAR_MESSAGE)
    if not quadratic:
        tol = _newton_tolerance(q.dtype)
        sol = optx.root_find(
            residual, optx.Newton(rtol=tol, atol=tol), a, max_steps=max_steps, throw=True
        )
        a = sol.value
    return from_tangent(T, a)


def _materialize(primal, tangent):
    if tangent is None and eqx.is_inexact_array(primal):
        return jnp.zeros_like(primal)
    return tangent


@eqx.filter_custom_jvp
def _legendre_value(lagrangian, t, q, p, args, *, quadratic):
    """`H(t, q, p) = p . v - L(t, q, v)` with `v` the inverse Legendre map of `p`."""
    v = invert_momentum(lagrangian, t, q, p, args, quadratic=quadratic)
    return jnp.sum(p * v) - lagrangian(t, q, v, args)


@_legendre_value.def_jvp
def _legendre_jvp(primals, tangents, *, quadratic):
    """Envelope theorem: no derivative of the inverse Legendre map is needed.

    With `r = p - dL/dv` normal to the spheres at the solution (`r_i = rho_i q_i`) and
    `v` tangent for every `q` (so `q_i . dv_i = -v_i . dq_i`),
    `dH = v . dp - dL|_(v fixed) - sum_i rho_i v_i . dq_i`, where `dL|_(v fixed)` also
    carries the derivatives with respect to `t`, `args` and the Lagrangian's own arrays.
    Higher derivatives still work: this rule is itself differentiable."""
    lagrangian, t, q, p, args = primals
    tangents = jax.tree.map(_materialize, primals, tangents)
    t_lagrangian, t_t, t_q, t_p, t_args = tangents
    v = invert_momentum(lagrangian, t, q, p, args, quadratic=quadratic)

    def L_fixed_v(lagrangian_, t_, q_, args_):
        return lagrangian_(t_, q_, v, args_)

    L, dL = eqx.filter_jvp(L_fixed_v, (lagrangian, t, q, args), (t_lagrangian, t_t, t_q, t_args))
    r = p - jax.grad(lambda v_: lagrangian(t, q, v_, args))(v)
    rho = jnp.sum(q * r, axis=-1) / jnp.sum(q * q, axis=-1)
    H = jnp.sum(p * v) - L
    dH = -dL
    if t_p is not None:
        dH = dH + jnp.sum(v * t_p)
    if t_q is not None:
        dH = dH - jnp.sum(rho * jnp.sum(v * t_q, axis=-1))
    return H, dH


class _LegendreH(eqx.Module):
    """`H(t, q, p) = p . v - L(t, q, v)` with `v` the inverse Legendre map of `p`.
    Differentiated by the envelope theorem (`_legendre_jvp`), not through the solve."""

    lagrangian: Callable
    quadratic: bool = eqx.field(static=True)

    def velocity(self, t, q, p, args):
        return invert_momentum(self.lagrangian, t, q, p, args, quadratic=self.quadratic)

    def __call__(self, t, q, p, args):
        return _legendre_value(self.lagrangian, t, q, p, args, quadratic=self.quadratic)


class _LegendreForces(eqx.Module):
    """A Lagrangian system's forces `f(t, q, v)` read as a function of the momentum."""

    H: _LegendreH
    forces: Callable

    def __call__(self, t, q, p, args):
        return self.forces(t, q, self.H.velocity(t, q, p, args), args)


def legendre(system: AbstractSystem, *, quadratic: bool | None = None) -> AbstractSystem:
    """The Hamiltonian counterpart of a Lagrangian system, computed numerically.

    A form-1 system (`Lagrangian`, `ConstantInertiaLagrangian`, `ChainPendulum`, ...)
    gives a `Hamiltonian` in `(q, mu)`; an `AngularLagrangian` gives an
    `AngularHamiltonian` in `(q, pi)`. The velocity is recovered from the momentum by one
    linear solve when `L` is quadratic in the velocity (`quadratic=True`, the default for
    constant-inertia systems and for `Lagrangian(..., quadratic_in_velocity=True)`),
    otherwise by Newton's method with implicit differentiation.
    """
    if quadratic is None:
        quadratic = getattr(system, "quadratic_in_velocity", False)
    if isinstance(system, AbstractLagrangianSystem):
        cls = Hamiltonian
    elif isinstance(system, AngularLagrangian):
        cls = AngularHamiltonian
    else:
        raise TypeError(f"legendre() takes a Lagrangian system, got {type(system)}.")
    H = _LegendreH(system.lagrangian, quadratic)
    forces = _LegendreForces(H, system.generalized_force) if system.has_forces else None
    return cls(H, forces)
