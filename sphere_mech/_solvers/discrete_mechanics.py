"""One step of the constrained variational (RATTLE-type) integrator on (S^2)^n.

The discrete Lagrangian is the trapezoidal rule for the user's `L`, extended to the
ambient space R^{3n} by `L(q, P(q) v)`,

    L_d(q0, q1) = h/2 [L(t0, q0, P(q0) c) + L(t1, q1, P(q1) c)],   c = (q1 - q0) / h,

(L is evaluated on the tangent bundle only: `P(q) = I - q q^T` projects the chord
velocity on each tangent plane), and the constraints `|q_i| = 1` enter through Lagrange
multipliers. Projecting the discrete Euler-Lagrange equations onto the tangent planes
removes the multipliers:

    P(q0) [mu0 + D1 L_d(q0, q1) + f0] = 0,   |q1_i| = 1       (solved for q1, Newton)
    mu1 = P(q1) [D2 L_d(q0, q1) + f1]

with `mu = P dL/dqdot` the momentum on T*(S^2)^n and `f0, f1 = h/2 f(t_k, q_k, P(q_k) c)`
the discrete Lagrange-d'Alembert forces (zero for a conservative system). `L_d` is
symmetric (`L_d(q1, q0; -h) = -L_d(q0, q1; h)`), so the map is time-reversible and of
order 2, and, without forces, symplectic on T*(S^2)^n. Velocities come back from the
momentum by the inverse Legendre map on the tangent planes.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from diffrax import RESULTS
from jax import lax

from .._geometry import normalize, project, sphere_exp, tangent_basis
from .._inertia import AbstractConstantInertiaLagrangian
from .._lagrangian import AbstractLagrangianSystem, AngularLagrangian
from .._linalg import from_tangent, reduced_matrix, to_tangent
from .._system import AbstractSystem


class LagrangianView(eqx.Module):
    """A Lagrangian system seen in `(q, qdot)`: form-1 systems as they are, an
    `AngularLagrangian` through `omega = q x qdot`. The state `(q, v)` stays the
    system's own (`v` is `qdot` or `omega`)."""

    system: AbstractSystem
    angular: bool = eqx.field(static=True)

    def lagrangian(self, t, q, qdot, args):
        if self.angular:
            return self.system.L(t, q, jnp.cross(q, qdot), args)
        return self.system.lagrangian(t, q, qdot, args)

    def force(self, t, q, qdot, args):
        """The generalized force at a tangent `qdot`, or `None` (nothing compiled)."""
        return self.system.generalized_force(t, q, self.from_qdot(q, qdot), args)

    def to_qdot(self, q, v):
        return jnp.cross(v, q) if self.angular else v

    def from_qdot(self, q, qdot):
        return jnp.cross(q, qdot) if self.angular else qdot

    def qddot(self, q, v, rates):
        """`qddot` from the system's rates `(qdot, vdot)` at the state `(q, v)`."""
        if self.angular:
            return jnp.cross(rates[1], q) + jnp.cross(v, rates[0])
        return rates[1]

    def momentum(self, t, q, qdot, args):
        return project(q, jax.grad(lambda v: self.lagrangian(t, q, v, args))(qdot))

    @property
    def quadratic(self) -> bool:
        return bool(getattr(self.system, "quadratic_in_velocity", False))


def lagrangian_view(system) -> LagrangianView:
    """The view of `system`, or a `ValueError` naming what the integrator accepts."""
    if isinstance(system, AbstractLagrangianSystem):
        return LagrangianView(system, angular=False)
    if isinstance(system, AngularLagrangian):
        return LagrangianView(system, angular=True)
    raise ValueError(
        "The variational integrator needs a Lagrangian system (Lagrangian, "
        "AngularLagrangian, ConstantInertiaLagrangian, ChainPendulum, a scene, ...): the "
        f"discrete action is built from L. Got {type(system).__name__}; simulate the "
        "Lagrangian form of the system, or use another solver for a Hamiltonian."
    )


def _newton(tol):
    # Cauchy termination: the last Newton correction is below `tol` (relative, with
    # `tol` absolute floor) and the residual, divided by the size of the terms it is
    # made of (so that its rounding floor is about eps), is below `tol`. Quadratic
    # convergence then leaves an error at the level of rounding.
    return optx.Newton(rtol=tol, atol=tol, linear_solver=lx.LU())


def _scale(*terms):
    """The size of the largest of `terms`: what a residual built from them rounds at."""
    size = sum(jnp.max(jnp.abs(x)) for x in terms)
    return jnp.maximum(size, jnp.finfo(size.dtype).tiny)


def velocity_from_momentum(view, t, q, mu, guess, args, tol, max_steps):
    """The tangent `qdot` with `P dL/dqdot(t, q, qdot) = mu`, and a result code.

    Exact for constant inertia (one Cholesky solve); one linear solve around `guess` for
    `L` quadratic in the velocity; otherwise refined by Newton (optimistix, implicit
    differentiation, failures reported, never thrown)."""
    if isinstance(view.system, AbstractConstantInertiaLagrangian):
        return view.system.velocity_from_momentum(t, q, mu, args), RESULTS.successful
    T = tangent_basis(q)
    dL_dv = lambda v: jax.grad(lambda v_: view.lagrangian(t, q, v_, args))(v)
    p_guess, hvp = jax.linearize(dL_dv, guess)
    a = to_tangent(T, guess) + jnp.linalg.solve(
        reduced_matrix(hvp, T), to_tangent(T, mu - p_guess)
    )
    if view.quadratic:
        return from_tangent(T, a), RESULTS.successful
    scale = lax.stop_gradient(_scale(p_guess, mu))
    residual = lambda a_, _: to_tangent(T, dL_dv(from_tangent(T, a_)) - mu) / scale
    sol = optx.root_find(residual, _newton(tol), a, max_steps=max_steps, throw=False)
    return from_tangent(T, sol.value), RESULTS.promote(sol.result)


def discrete_lagrangian(view, t0, h, q0, q1, args):
    """The trapezoidal `L_d(q0, q1) = h/2 [L(t0, q0, P0 c) + L(t0 + h, q1, P1 c)]`.

    The chord velocity `c` is projected on each tangent plane, so `L` is only ever
    evaluated on the tangent bundle: the discrete flow does not depend on how `L` is
    written off it (e.g. `|q x qdot|^2` or `|qdot|^2`), and forms 1 and 2 step alike."""
    c = (q1 - q0) / h
    L0 = view.lagrangian(t0, q0, project(q0, c), args)
    L1 = view.lagrangian(t0 + h, q1, project(q1, c), args)
    return 0.5 * h * (L0 + L1)


def discrete_forces(view, t0, h, q0, q1, args):
    """`(f0, f1) = h/2 (f(t0, q0, P(q0) c), f(t1, q1, P(q1) c))`, or `None`."""
    if not view.system.has_forces:
        return None
    c = (q1 - q0) / h
    f0 = view.force(t0, q0, project(q0, c), args)
    f1 = view.force(t0 + h, q1, project(q1, c), args)
    return 0.5 * h * f0, 0.5 * h * f1


def position_residual(view, t0, h, q0, mu0, scale, args):
    """The map `a -> T0^T [mu0 + D1 L_d(q0, q1(a)) + f0] / scale`, with
    `q1(a) = exp_q0(h T0 a)` on the spheres (so `|q1_i| = 1` holds by construction)."""
    T0 = tangent_basis(q0)

    def position(a):
        return sphere_exp(q0, h * from_tangent(T0, a))

    def residual(a, _):
        q1 = position(a)
        d1 = jax.grad(discrete_lagrangian, argnums=3)(view, t0, h, q0, q1, args)
        forces = discrete_forces(view, t0, h, q0, q1, args)
        if forces is not None:
            d1 = d1 + forces[0]
        return to_tangent(T0, mu0 + d1) / scale

    return T0, position, residual


def substep(view, t0, h, q0, v0, rates0, args, tol, max_steps):
    """One step of size `h` (any sign) from the state `(q0, v0)` with rates `rates0`.

    Returns the new state, the system's rates there, and a result code."""
    qdot0 = view.to_qdot(q0, v0)
    dL_dq, dL_dv = jax.grad(view.lagrangian, argnums=(1, 2))(t0, q0, qdot0, args)
    mu0 = project(q0, dL_dv)
    # The residual is a sum of momenta (dL/dqdot) and impulses (h dL/dq): its rounding
    # floor is eps times this scale, which makes the Newton tolerance relative.
    scale = lax.stop_gradient(_scale(dL_dv, h * dL_dq))
    T0, position, residual = position_residual(view, t0, h, q0, mu0, scale, args)
    # Predictor: the geodesic with velocity qdot0 + h/2 P qddot0 matches the Taylor
    # expansion of q(t0 + h) to O(h^3); Newton then needs about two iterations.
    guess = to_tangent(T0, qdot0 + 0.5 * h * view.qddot(q0, v0, rates0))
    sol = optx.root_find(residual, _newton(tol), guess, max_steps=max_steps, throw=False)
    # exp keeps |q1_i| = 1 to rounding; renormalizing stops rounding errors from
    # accumulating over millions of steps (a change far below the Newton tolerance).
    q1 = normalize(position(sol.value))
    d2 = jax.grad(discrete_lagrangian, argnums=4)(view, t0, h, q0, q1, args)
    forces = discrete_forces(view, t0, h, q0, q1, args)
    if forces is not None:
        d2 = d2 + forces[1]
    t1 = t0 + h
    chord = project(q1, (q1 - q0) / h)
    qdot1, vel_result = velocity_from_momentum(
        view, t1, q1, project(q1, d2), chord, args, tol, max_steps
    )
    y1 = (q1, view.from_qdot(q1, qdot1))
    result = RESULTS.where(
        sol.result == optx.RESULTS.successful, vel_result, RESULTS.promote(sol.result)
    )
    return y1, view.system.rates(t1, y1, args), result
