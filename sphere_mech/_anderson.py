"""Anderson acceleration of a fixed-point iteration, as an optimistix solver."""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax.flatten_util import ravel_pytree

from ._linalg import spd_solve


class _AndersonState(eqx.Module):
    dx: jax.Array  # (depth, N): the last differences of iterates
    df: jax.Array  # (depth, N): the last differences of residuals g(y) - y
    y_prev: jax.Array
    f_prev: jax.Array
    count: jax.Array
    relative_error: jax.Array


class Anderson(optx.AbstractFixedPointSolver):
    """Anderson acceleration ("type II", Walker & Ni 2011) of the iteration
    `y <- g(y)`: each step evaluates `g` once and moves to the combination of the last
    `depth + 1` iterates whose residuals `g(y) - y` have the least norm. For a linear
    contraction it is GMRES in disguise: it converges where the plain iteration
    converges slowly or diverges along a few directions, for the price of a
    `depth x depth` least-squares problem per step (O(N depth^2) for `N` unknowns).

    Stops when the last residual is below `atol + rtol |g(y)|` (in `norm`), as
    `optimistix.FixedPointIteration` does, and then returns `g(y)`. Works with
    `optimistix.fixed_point` and its implicit differentiation.

    **Arguments:**
    - `rtol`, `atol`: relative and absolute tolerance on `g(y) - y`.
    - `depth`: how many previous steps are combined (default 3).
    - `norm`: the norm of the termination test (default `optimistix.max_norm`).
    """

    rtol: float
    atol: float
    depth: int = eqx.field(default=3, static=True)
    norm: Callable = optx.max_norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags) -> _AndersonState:
        flat, _ = ravel_pytree(y)
        history = jnp.zeros((self.depth, flat.size), dtype=flat.dtype)
        return _AndersonState(history, history, flat, jnp.zeros_like(flat),
                              jnp.array(0), jnp.array(jnp.inf, dtype=flat.dtype))

    def step(self, fn, y, args, options, state: _AndersonState, tags):
        g, aux = fn(y, args)
        flat, unravel = ravel_pytree(y)
        g_flat, _ = ravel_pytree(g)
        f = g_flat - flat
        error = self.norm(f / (self.atol + self.rtol * jnp.abs(g_flat)))
        # The newest differences replace the oldest ones (none before the second step).
        slot = state.count % self.depth
        first = state.count == 0
        dx = state.dx.at[slot].set(jnp.where(first, 0.0, flat - state.y_prev))
        df = state.df.at[slot].set(jnp.where(first, 0.0, f - state.f_prev))
        used = jnp.arange(self.depth) < jnp.minimum(state.count, self.depth)
        # min_gamma |f - df^T gamma| by the normal equations; unused slots and a tiny
        # relative ridge keep them positive definite when differences are degenerate.
        gram = df @ df.T
        ridge = 1e-12 * jnp.max(jnp.diag(gram)) + jnp.finfo(f.dtype).tiny
        gram = gram + jnp.diag(jnp.where(used, ridge, 1.0))
        gamma = jnp.where(used, spd_solve(gram, df @ f), 0.0)
        accelerated = g_flat - (dx + df).T @ gamma
        # Converged: return g(y) itself (the extrapolation would only add rounding).
        new = jnp.where(error < 1, g_flat, accelerated)
        new_state = _AndersonState(dx, df, flat, f, state.count + 1, error)
        return unravel(new), new_state, aux

    def terminate(self, fn, y, args, options, state: _AndersonState, tags):
        return state.relative_error < 1, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result
                    ) -> tuple[Any, Any, dict[str, Any]]:
        return y, aux, {}
