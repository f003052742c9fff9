"""The inverse Legendre map of a general Lagrangian: the tangent velocity `v` with
`P dL/dv(t, q, v) = p`, solved in tangent coordinates (one linear solve, then Newton)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from diffrax import RESULTS
from jax import lax

from ._checks import check_scalar
from ._linalg import DenseLU, dense_solve
from ._misc import check_bool, check_integer, check_positive, tree_max_abs, tree_sub, tree_vdot


def newton_tolerance(dtype) -> float:
    """The default tolerance of every Newton solve: `eps ** 0.75` of the dtype."""
    return float(jnp.finfo(dtype).eps) ** 0.75


def check_inverse_options(p, *, guess, quadratic, tol, max_steps) -> None:
    """Static checks of `velocity_from_momentum`'s options (a `ValueError` naming the first
    bad one): `guess` `None` or of the momentum `p`'s shape, `quadratic` `None` or a bool,
    `tol` `None` or a finite number in (0, 1), `max_steps` a positive integer."""
    if guess is not None:
        shapes = jax.tree.map(jnp.shape, (guess, p))
        if shapes[0] != shapes[1]:
            raise ValueError(
                f"guess must have the shape of the momentum p (the state's), {shapes[1]}, "
                f"got {shapes[0]}."
            )
    if quadratic is not None:
        check_bool(quadratic, "quadratic")
    if tol is not None:
        check_positive(tol, "tol")
        if not isinstance(tol, jax.core.Tracer) and not float(tol) < 1:
            raise ValueError(f"tol must be a finite number in (0, 1) (relative), got {tol!r}.")
    check_integer(max_steps, "max_steps")


def newton(tol, *, chord: bool = False) -> optx.Newton | optx.Chord:
    """Newton's method, stopping when the last step and the (relative) residual are `< tol`;
    with `chord`, its chord variant (the Jacobian of the first iterate, factored once)."""
    return (optx.Chord if chord else optx.Newton)(rtol=tol, atol=tol, linear_solver=DenseLU())


def residual_scale(*terms) -> jax.Array:
    """The size of the largest of `terms`: what a residual built from them rounds at."""
    size = sum(tree_max_abs(x) for x in terms)
    return jnp.maximum(size, jnp.finfo(size.dtype).tiny)


@eqx.filter_jit
def invert_momentum(L, space, t, q, p, args, *, guess, quadratic: bool, tol, max_steps: int):
    """The tangent `v` with `P dL/dv(t, q, v) = p` and a result code (`singular`, never
    raised): one linear solve around `guess`, then unless `quadratic` Newton; where Newton
    fails (e.g. `L` defined for `|v| < 1` only), BFGS with a line search minimizes
    `L - p . v` (strictly convex `L`) from `guess`, and Newton finishes."""
    T = space.tangent_basis(q)
    to_tangent, from_tangent = space.to_tangent, space.from_tangent

    dL_dv = jax.grad(lambda v_: check_scalar(L(t, q, v_, args), "L(t, q, v, args)"))
    p_guess, hvp = jax.linearize(dL_dv, guess)
    a = to_tangent(T, guess) + dense_solve(
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
    # Under `vmap` both branches run: converged elements start the fallback at their solution.
    start = jnp.where(ok, a, to_tangent(T, guess))
    a, ok = lax.cond(ok, lambda: (a, ok), lambda: globalized(start))
    return from_tangent(T, a), RESULTS.where(ok, RESULTS.successful, RESULTS.singular)
