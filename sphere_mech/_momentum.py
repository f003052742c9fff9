"""The inverse Legendre map of a general Lagrangian: the tangent velocity `v` with
`P dL/dv(t, q, v) = p`, solved in tangent coordinates (one linear solve, then Newton)."""

import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from diffrax import RESULTS
from jax import lax

from ._checks import check_scalar
from ._misc import tree_max_abs, tree_sub, tree_vdot


def newton_tolerance(dtype) -> float:
    """The default tolerance of every Newton solve: `eps ** 0.75` of the dtype."""
    return float(jnp.finfo(dtype).eps) ** 0.75


def newton(tol) -> optx.Newton:
    """Newton's method with Cauchy termination: it stops when the last correction and the
    residual (made relative by the callers) are below `tol`."""
    return optx.Newton(rtol=tol, atol=tol, linear_solver=lx.LU())


def residual_scale(*terms) -> jax.Array:
    """The size of the largest of `terms`: what a residual built from them rounds at."""
    size = sum(tree_max_abs(x) for x in terms)
    return jnp.maximum(size, jnp.finfo(size.dtype).tiny)


def invert_momentum(L, space, t, q, p, args, *, guess, quadratic: bool, tol, max_steps: int):
    """The tangent `v` with `P dL/dv(t, q, v) = p`, and a result code.

    One linear solve around `guess` (exact when `L` is quadratic in `v`), then, unless
    `quadratic`, Newton's method (optimistix, implicit differentiation). Where Newton
    fails, typically because `L` is defined on a bounded set of velocities only (a
    relativistic particle: `|v| < 1`) and the linear guess lands outside it, the
    solve is globalized: for strictly convex `L` the velocity minimizes
    `L(t, q, v) - p . v`, which BFGS with a backtracking line search (it rejects steps
    where `L` is not finite) approaches from `guess`, and Newton then finishes. Failures
    are reported as diffrax's codes, never raised (`singular` for a singular linear
    solve). Solved in a tangent basis, so `v` stays tangent as `q` varies."""
    T = space.tangent_basis(q)
    to_tangent = space.to_tangent
    from_tangent = space.from_tangent

    def dL_dv(v):
        return jax.grad(lambda v_: check_scalar(L(t, q, v_, args), "L(t, q, v, args)"))(v)

    p_guess, hvp = jax.linearize(dL_dv, guess)
    a = to_tangent(T, guess) + jnp.linalg.solve(
        space.reduced_matrix(hvp, T), to_tangent(T, tree_sub(p, p_guess))
    )
    finite = jnp.all(jnp.isfinite(a))
    if quadratic:
        return from_tangent(T, a), RESULTS.where(finite, RESULTS.successful, RESULTS.singular)
    scale = lax.stop_gradient(residual_scale(p_guess, p))
    residual = lambda a_, _: to_tangent(T, tree_sub(dL_dv(from_tangent(T, a_)), p)) / scale

    def polish(a0):
        sol = optx.root_find(residual, newton(tol), a0, max_steps=max_steps, throw=False)
        ok = (sol.result == optx.RESULTS.successful) & jnp.all(jnp.isfinite(sol.value))
        return sol.value, ok

    def globalized(start):
        def objective(a_, _):
            v = from_tangent(T, a_)
            return (L(t, q, v, args) - tree_vdot(p, v)) / scale

        bfgs = optx.BFGS(rtol=tol, atol=tol)
        sol = optx.minimise(objective, bfgs, start, max_steps=8 * max_steps, throw=False)
        return polish(sol.value)

    a, ok = polish(jnp.where(finite, a, to_tangent(T, guess)))
    # Under `vmap` both branches run for every element: converged elements then start the
    # fallback at their solution, so a batch with no failure leaves it after a step.
    start = jnp.where(ok, a, to_tangent(T, guess))
    a, ok = lax.cond(ok, lambda: (a, ok), lambda: globalized(start))
    return from_tangent(T, a), RESULTS.where(ok, RESULTS.successful, RESULTS.singular)
