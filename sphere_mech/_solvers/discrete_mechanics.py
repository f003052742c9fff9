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

import jax
import optimistix as optx
from diffrax import RESULTS
from jax import lax

from .._anderson import Anderson
from .._inertia import AbstractFastPath
from .._misc import tree_add, tree_scale
from .._momentum import newton, residual_scale
from .._system import AbstractLagrangianSystem


def check_lagrangian(system) -> AbstractLagrangianSystem:
    """`system`, or a `ValueError` naming what the integrator accepts."""
    if not isinstance(system, AbstractLagrangianSystem):
        raise ValueError(
            "The variational integrator needs a Lagrangian system (Lagrangian, "
            "AngularLagrangian, ConstantInertiaLagrangian, a Scene, ...): the discrete "
            f"action is built from L. Got {type(system).__name__}; simulate the Lagrangian "
            "form of the system, or use another solver for a Hamiltonian."
        )
    return system


def discrete_lagrangian(system, t0, h, q0, q1, args):
    """The trapezoidal `L_d(q0, q1) = h/2 [L(t0, q0, P0 c) + L(t0 + h, q1, P1 c)]`.

    The chord velocity `c` is projected on each tangent plane, so `L` is only ever
    evaluated on the tangent bundle: the discrete flow does not depend on how `L` is
    written off it (e.g. `|q x qdot|^2` or `|qdot|^2`), and forms 1 and 2 step alike.
    On a mixed space only the sphere factors are projected."""
    c = chord(q0, q1, h)
    L0 = system.lagrangian_qdot(t0, q0, system.space.project(q0, c), args)
    L1 = system.lagrangian_qdot(t0 + h, q1, system.space.project(q1, c), args)
    return 0.5 * h * (L0 + L1)


def chord(q0, q1, h):
    """The chord velocity `(q1 - q0) / h`."""
    return jax.tree.map(lambda a, b: (b - a) / h, q0, q1)


def _force(system, t, q, qdot, args):
    return system.generalized_force(t, q, system.from_linear(q, qdot), args)


def discrete_forces(system, t0, h, q0, q1, args):
    """`(f0, f1) = h/2 (f(t0, q0, P(q0) c), f(t1, q1, P(q1) c))`, or `None`."""
    if not system.has_forces:
        return None
    c, project = chord(q0, q1, h), system.space.project
    f0 = _force(system, t0, q0, project(q0, c), args)
    f1 = _force(system, t0 + h, q1, project(q1, c), args)
    return tree_scale(0.5 * h, f0), tree_scale(0.5 * h, f1)


def solve_position(system, t0, h, q0, mu0, scale, guess, args, tol, max_steps, fast_path=True):
    """Solve `P(q0) [mu0 + D1 L_d(q0, q1) + f0] = 0` for `q1 = exp_q0(h T0 a)` (so
    `|q1_i| = 1` holds by construction), starting from the velocity `guess` (tangent).

    General systems: Newton's method on the `2n` equations `T0^T [...] / scale` (its
    Jacobian is dense: `2n` Jacobian-vector products and a `2n x 2n` LU per iteration).
    Constant-inertia systems (`AbstractFastPath`, unless `fast_path`
    is false): `D1 L_d` is
    `-(P0 M P0) c` up to terms of relative size `h |qdot|` (`c` the chord velocity), so
    the Newton step is taken with the Jacobian `-T0^T (M kron I) T0`, whose inverse is
    the fast path's multiplier solve at `q0` (O(n) for a chain): a chord iteration
    `a <- a + T0^T x`, `P0 M x = P0 [mu0 + D1 L_d + f0]`, `q0 . x = 0`, converging
    linearly at a rate of about the angle a sphere turns in one step, amplified by the
    spread of `M`'s eigenvalues; Anderson acceleration takes care of the few slow
    directions. It solves the same equations, so the step is the same to the
    tolerance; steps too coarse for it to converge are reported like a failed Newton.

    On a mixed space `q1 = (x0 + h a_x, exp_q0(h T0 a_q))`: the multipliers act on the
    sphere factors only.

    Returns the map `a -> q1` and the optimistix solution (implicit differentiation)."""
    space = system.space
    to_tangent, from_tangent = space.to_tangent, space.from_tangent
    T0 = space.tangent_basis(q0)
    a0 = to_tangent(T0, guess)

    def position(a):
        return space.exp(q0, tree_scale(h, from_tangent(T0, a)))

    def momentum_residual(a):
        q1 = position(a)
        d1 = jax.grad(discrete_lagrangian, argnums=3)(system, t0, h, q0, q1, args)
        forces = discrete_forces(system, t0, h, q0, q1, args)
        r = tree_add(mu0, d1)
        return r if forces is None else tree_add(r, forces[0])

    if fast_path and isinstance(system, AbstractFastPath):
        solve = system.multiplier_solver(q0, args)
        chord = lambda a, _: a + to_tangent(T0, solve(momentum_residual(a)))
        sol = optx.fixed_point(
            chord, Anderson(rtol=tol, atol=tol), a0, max_steps=max_steps, throw=False
        )
    else:
        residual = lambda a, _: to_tangent(T0, momentum_residual(a)) / scale
        sol = optx.root_find(residual, newton(tol), a0, max_steps=max_steps, throw=False)
    return position, sol


def substep(system, t0, h, q0, v0, rates0, args, tol, max_steps, fast_path=True):
    """One step of size `h` (any sign) from the state `(q0, v0)` with rates `rates0`
    (`fast_path`: see `solve_position`).

    Returns the new state, the system's rates there, and a result code."""
    space = system.space
    qdot0, qddot0 = jax.jvp(system.to_linear, (q0, v0), rates0)
    dL_dq, dL_dv = jax.grad(system.lagrangian_qdot, argnums=(1, 2))(t0, q0, qdot0, args)
    mu0 = space.project(q0, dL_dv)
    # The residual is a sum of momenta (dL/dqdot) and impulses (h dL/dq): its rounding
    # floor is eps times this scale, which makes the Newton tolerance relative.
    scale = lax.stop_gradient(residual_scale(dL_dv, tree_scale(h, dL_dq)))
    # Predictor: the geodesic with velocity qdot0 + h/2 P qddot0 matches the Taylor
    # expansion of q(t0 + h) to O(h^3); Newton then needs about two iterations.
    guess = tree_add(qdot0, tree_scale(0.5 * h, qddot0))
    position, sol = solve_position(
        system, t0, h, q0, mu0, scale, guess, args, tol, max_steps, fast_path
    )
    # exp keeps |q1_i| = 1 to rounding; renormalizing stops rounding errors from
    # accumulating over millions of steps (a change far below the Newton tolerance).
    q1 = space.normalize(position(sol.value))
    d2 = jax.grad(discrete_lagrangian, argnums=4)(system, t0, h, q0, q1, args)
    forces = discrete_forces(system, t0, h, q0, q1, args)
    if forces is not None:
        d2 = tree_add(d2, forces[1])
    t1 = t0 + h
    c1 = space.project(q1, chord(q0, q1, h))
    v1, vel_result = system.velocity_from_momentum(
        t1,
        q1,
        system.from_linear(q1, space.project(q1, d2)),
        args,
        guess=system.from_linear(q1, c1),
        tol=tol,
        max_steps=max_steps,
    )
    y1 = (q1, v1)
    result = RESULTS.where(
        sol.result == optx.RESULTS.successful, vel_result, RESULTS.promote(sol.result)
    )
    return y1, system.rates(t1, y1, args), result
