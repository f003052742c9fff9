"""One step of the constrained variational (RATTLE-type) integrator on spheres, rotations
and Euclidean factors: with the trapezoidal `L_d` (`discrete_lagrangian`), `mu = P
dL/dqdot` and the discrete forces `f0, f1` (`discrete_forces`), the projected discrete
Euler-Lagrange equations

    P(q0) [mu0 + D1 L_d(q0, q1) + f0] = 0,   q1 = exp_q0(h v), v tangent   (solved for v)
    mu1 = P(q1) [D2 L_d(q0, q1) + f1]

`L_d` is symmetric: the map is time-reversible, of order 2 and, without forces,
symplectic on the cotangent bundle. Velocities come from momenta by the inverse Legendre
map. Everything is the space's: its projection `P` (Frobenius-orthogonal onto the tangent
space, so the multipliers of the constraints drop out), exponential, orthonormal tangent
basis and covectors. On `SO(3)` this is the Lie group variational integrator of Lee, Leok
and McClamroch: `q1 = R0 F`, `F = expm(h hat(v))`, the chord `R0 (F - I) / h` projected
on either end has body velocity `vee(F - F^T) / (2 h)`, so `L_d` is a function of `(R0,
F)` and the implicit equation for `F` is Newton's on its rotation vector `h v`.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from diffrax import RESULTS
from jax import lax

from .._anderson import Anderson
from .._inertia import AbstractFastPath
from .._misc import tree_add, tree_dtype, tree_max_abs, tree_scale
from .._momentum import newton, residual_scale
from .._system import AbstractLagrangianSystem, vector_field


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


def discrete_lagrangian(system, t0, h, q0, q1, args, step):
    """The trapezoidal `L_d(q0, q1) = h/2 [L(t0, q0, P0 c) + L(t0 + h, q1, P1 c)]`, `c` the
    chord velocity (its value from `step`: `chord`), `P` the space's projection (`I - q q^T`
    on a sphere, `R skew(R^T .)` on a rotation): `L` only on the tangent bundle, so forms 1
    and 2 step alike. On a mixed space Euclidean factors are not projected."""
    c = chord(q0, q1, h, step)
    L = lambda t, q: system.lagrangian_qdot(t, q, system.space.project(q, c), args)
    return 0.5 * h * (L(t0, q0) + L(t0 + h, q1))


def chord(q0, q1, h, step):
    """The chord velocity `(q1 - q0) / h`, its value `step / h`: `step` is `q1 - q0` without
    the rounding of the difference (`space.exp_step`), which `1 / h` would amplify into
    the momenta (in float32 at h = 1e-3 the chain's velocities drifted 6e-4 from float64's
    in 1 s); its derivatives are the difference's, `(dq1 - dq0) / h`."""

    def one(a, b, d):
        naive = (b - a) / h
        return naive + lax.stop_gradient(d / h - naive)

    return jax.tree.map(one, q0, q1, step)


def discrete_forces(system, t0, h, q0, q1, args, step):
    """`(f0, f1) = h/2 (f(t0, q0, P(q0) c), f(t1, q1, P(q1) c))`, or `None`."""
    if not system.has_forces:
        return None
    c = chord(q0, q1, h, step)

    def force(t, q):
        qdot = system.from_linear(q, system.space.project(q, c))
        return tree_scale(0.5 * h, system.generalized_force(t, q, qdot, args))

    return force(t0, q0), force(t0 + h, q1)


ROUNDING = 8.0
"""The difference `(q1 - q0) / h` rounds at about `eps |q| / h`; the solves accept `ROUNDING`
times that (a small step, a Euclidean factor far from its origin: Newton cannot get below it).
The chord's value comes from `exp_step` instead (`chord`), so the steps usually end well
inside this floor; it stays the solves' acceptance bound."""


def solve_position(
    system,
    t0,
    h,
    q0,
    mu0,
    scale,
    unit,
    guess,
    args,
    tol,
    max_steps,
    fast_path=True,
    reuse_jacobian=False,
):
    """Solve `P(q0) [mu0 + D1 L_d(q0, q1) + f0] = 0` for `q1 = exp_q0(h T0 a)` (`|q1_i| = 1`
    by construction, `R1 = R0 expm(h hat(omega))` on rotations; on a mixed space `x1 = x0 +
    h a_x`), from the tangent velocity `guess`:
    Newton's method on `T0^T [...] / scale` (dense `2n x 2n` Jacobian; with
    `reuse_jacobian` the chord iteration, the Jacobian at `guess` factored once: it
    contracts linearly, at a rate about the predictor's distance from the solution), or
    for an
    `AbstractFastPath` (if `fast_path`), as `D1 L_d = -(P0 M P0) c` up to relative
    `h |qdot|`, the chord iteration `a <- a + T0^T x`, `P0 M x = P0 [mu0 + D1 L_d + f0]`,
    `q0 . x = 0` (the O(n) multiplier solve), Anderson-accelerated: same equations.
    `scale` (momentum) and `unit` (velocity, at least 1) are the residual's and `a`'s sizes
    at which the tolerance `tol` applies: they include the chord's rounding floor.
    Returns the map `a -> h T0 a` (the tangent vector whose exponential is the step) and
    the optimistix solution (implicit differentiation)."""
    space = system.space
    to_tangent, from_tangent = space.to_tangent, space.from_tangent
    T0 = space.tangent_basis(q0)
    a0 = to_tangent(T0, guess)

    def displacement(a):
        return tree_scale(h, from_tangent(T0, a))

    def momentum_residual(a):
        q1, step = _end(space, q0, displacement(a))
        d1 = jax.grad(discrete_lagrangian, argnums=3)(system, t0, h, q0, q1, args, step)
        forces = discrete_forces(system, t0, h, q0, q1, args, step)
        r = tree_add(mu0, d1)
        return r if forces is None else tree_add(r, forces[0])

    if fast_path and isinstance(system, AbstractFastPath):
        solve = system.multiplier_solver(q0, args)
        chord = lambda a, _: a + to_tangent(T0, solve(momentum_residual(a)))
        sol = optx.fixed_point(
            chord, Anderson(rtol=tol, atol=tol * unit), a0, max_steps=max_steps, throw=False
        )
    else:  # in units of `unit`: Newton's test on the step is then `tol`'s
        residual = lambda b, _: to_tangent(T0, momentum_residual(unit * b)) / scale
        finder = newton(tol, chord=reuse_jacobian)
        sol = optx.root_find(residual, finder, a0 / unit, max_steps=max_steps, throw=False)
        sol = eqx.tree_at(lambda s: s.value, sol, unit * sol.value)
    return displacement, sol


def _end(space, q0, w):
    """`(q1, step)`: the step's end `exp(q0, w)` as `q0 + step`, `step = space.exp_step(q0,
    w)` (one evaluation of Rodrigues' terms for both; the same `exp` on spheres and
    Euclidean factors, to rounding on rotations)."""
    step = space.exp_step(q0, w)
    return tree_add(q0, step), step


def substep(
    system, t0, h, q0, v0, rates0, args, tol, max_steps, fast_path=True, reuse_jacobian=False
):
    """One step of size `h` (any sign) from `(q0, v0)` with rates `rates0` (`fast_path`,
    `reuse_jacobian`: see `solve_position`): the new state, the system's rates there, and
    a result code."""
    space = system.space
    qdot0, qddot0 = jax.jvp(system.to_linear, (q0, v0), rates0)
    dL_dq, dL_dv = jax.grad(system.lagrangian_qdot, argnums=(1, 2))(t0, q0, qdot0, args)
    mu0 = space.project(q0, dL_dv)
    # The residual sums momenta and impulses (h dL/dq), and the momentum of the chord's
    # rounding (`ROUNDING eps |q| / h`, through the Hessian of L in qdot), which `tol` passes.
    eps = jnp.finfo(tree_dtype(q0)).eps
    floor = ROUNDING * eps * tree_max_abs(q0) / jnp.abs(h)
    momentum = lambda v: jax.grad(system.lagrangian_qdot, argnums=2)(t0, q0, v, args)
    chord_rounding = jax.tree.map(lambda q: jnp.full_like(q, floor / tol), q0)
    _, rounding = jax.jvp(momentum, (qdot0,), (chord_rounding,))
    scale = lax.stop_gradient(residual_scale(dL_dv, tree_scale(h, dL_dq), rounding))
    unit = lax.stop_gradient(jnp.maximum(floor / tol, 1.0))
    # Predictor: the geodesic with velocity qdot0 + h/2 P qddot0 matches q(t0 + h) to O(h^3).
    guess = tree_add(qdot0, tree_scale(0.5 * h, qddot0))
    displacement, sol = solve_position(
        system, t0, h, q0, mu0, scale, unit, guess, args, tol, max_steps, fast_path, reuse_jacobian
    )
    q1, step = _end(space, q0, displacement(sol.value))
    # Renormalizing stops rounding errors from accumulating over millions of steps.
    q1 = space.normalize(q1)
    d2 = jax.grad(discrete_lagrangian, argnums=4)(system, t0, h, q0, q1, args, step)
    forces = discrete_forces(system, t0, h, q0, q1, args, step)
    if forces is not None:
        d2 = tree_add(d2, forces[1])
    t1 = t0 + h
    c1 = space.project(q1, chord(q0, q1, h, step))
    # mu1 is a covector (it pairs with qdot): pi1 = 2 vee(R1^T mu1) on rotations, not vee.
    mu1, guess1 = system.from_covector(q1, space.project(q1, d2)), system.from_linear(q1, c1)
    v1, vel_result = system.velocity_from_momentum(
        t1, q1, mu1, args, guess=guess1, tol=tol, max_steps=max_steps
    )
    y1 = (q1, v1)
    result = RESULTS.where(
        sol.result == optx.RESULTS.successful, vel_result, RESULTS.promote(sol.result)
    )
    return y1, vector_field(system, t1, y1, args), result
