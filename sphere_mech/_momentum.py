"""The inverse Legendre map of a general Lagrangian: the tangent velocity `v` with
`P dL/dv(t, q, v) = p`, solved in tangent coordinates (one linear solve, then Newton)."""

import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from diffrax import RESULTS
from jax import lax

from ._checks import check_scalar
from ._geometry import tangent_basis
from ._linalg import from_tangent, reduced_matrix, to_tangent


def newton_tolerance(dtype) -> float:
    """The default tolerance of every Newton solve: `eps ** 0.75` of the dtype."""
    return float(jnp.finfo(dtype).eps) ** 0.75


def newton(tol) -> optx.Newton:
    """Newton's method with Cauchy termination: it stops when the last correction and the
    residual (made relative by the callers) are below `tol`."""
    return optx.Newton(rtol=tol, atol=tol, linear_solver=lx.LU())


def residual_scale(*terms) -> jax.Array:
    """The size of the largest of `terms`: what a residual built from them rounds at."""
    size = sum(jnp.max(jnp.abs(x)) for x in terms)
    return jnp.maximum(size, jnp.finfo(size.dtype).tiny)


def invert_momentum(L, t, q, p, args, *, guess, quadratic: bool, tol, max_steps: int):
    """The tangent `v` with `P dL/dv(t, q, v) = p`, and a result code.

    One linear solve around `guess` (exact when `L` is quadratic in `v`), then, unless
    `quadratic`, Newton's method (optimistix, implicit differentiation, failures
    reported as diffrax's codes, never raised; `singular` for a singular linear solve).
    Solved in a tangent basis, so `v` stays tangent as
    `q` varies."""
    T = tangent_basis(q)

    def dL_dv(v):
        return jax.grad(lambda v_: check_scalar(L(t, q, v_, args), "L(t, q, v, args)"))(v)

    p_guess, hvp = jax.linearize(dL_dv, guess)
    a = to_tangent(T, guess) + jnp.linalg.solve(
        reduced_matrix(hvp, T), to_tangent(T, p - p_guess)
    )
    finite = jnp.all(jnp.isfinite(a))
    result = RESULTS.successful
    if not quadratic:
        scale = lax.stop_gradient(residual_scale(p_guess, p))
        residual = lambda a_, _: to_tangent(T, dL_dv(from_tangent(T, a_)) - p) / scale
        sol = optx.root_find(residual, newton(tol), a, max_steps=max_steps, throw=False)
        a, result = sol.value, RESULTS.promote(sol.result)
    return from_tangent(T, a), RESULTS.where(finite, result, RESULTS.singular)
