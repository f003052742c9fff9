"""Anderson acceleration of a fixed-point iteration, as an optimistix solver."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jax import lax
from jax.flatten_util import ravel_pytree

from ._linalg import spd_solve


class _AndersonState(eqx.Module):
    dx: jax.Array  # (depth, N): the last differences of iterates
    df: jax.Array  # (depth, N): the last differences of residuals g(y) - y
    y_prev: jax.Array
    f_prev: jax.Array
    count: jax.Array
    first_error: jax.Array  # of the first step, to estimate the contraction rate
    rate: jax.Array  # estimated contraction rate of the plain iteration
    relative_error: jax.Array  # of the returned iterate


class Anderson(optx.AbstractFixedPointSolver):
    """Anderson acceleration ("type II", Walker & Ni 2011) of `y <- g(y)`: one `g` per step,
    moving to the combination of the last `depth + 1` iterates whose residuals `g(y) - y`
    have the least norm (GMRES in disguise for a linear contraction). Returns `g(y)` once
    its estimated error (the residual, or `rho / (1 - rho)` times it for a contraction rate
    `rho < 1/2` estimated from the first two, plain, steps) is below `atol + rtol |g(y)|`.

    **Arguments:**
    - `rtol`, `atol`: relative and absolute tolerance on `g(y) - y`.
    - `depth`: how many previous steps are combined (default 3).
    - `plain_rate`: below this estimated contraction rate (default 0.1) no acceleration
      is computed.
    - `norm`: the norm of the termination test (default `optimistix.max_norm`)."""

    rtol: float
    atol: float
    depth: int = eqx.field(default=3, static=True)
    plain_rate: float = eqx.field(default=0.1, static=True)
    norm: Callable = optx.max_norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags) -> _AndersonState:
        flat, _ = ravel_pytree(y)
        history = jnp.zeros((self.depth, flat.size), dtype=flat.dtype)
        inf = jnp.array(jnp.inf, dtype=flat.dtype)
        return _AndersonState(
            history, history, flat, jnp.zeros_like(flat), jnp.array(0), inf, jnp.ones_like(inf), inf
        )

    def step(self, fn, y, args, options, state: _AndersonState, tags):
        g, aux = fn(y, args)
        flat, unravel = ravel_pytree(y)
        g_flat, _ = ravel_pytree(g)
        f = g_flat - flat
        residual = self.norm(f / (self.atol + self.rtol * jnp.abs(g_flat)))
        first = state.count == 0
        rate = jnp.where(state.count == 1, residual / state.first_error, state.rate)
        first_error = jnp.where(first, residual, state.first_error)
        error = jnp.minimum(jnp.where(rate < 0.5, residual * rate / (1 - rate), residual), residual)
        # The newest differences replace the oldest (none before the second step).
        dx = jnp.concatenate([state.dx[1:], jnp.where(first, 0.0, flat - state.y_prev)[None]])
        df = jnp.concatenate([state.df[1:], jnp.where(first, 0.0, f - state.f_prev)[None]])
        used = jnp.arange(self.depth) >= self.depth - jnp.minimum(state.count, self.depth)

        def accelerated():
            # min |f - df^T gamma| by the normal equations, kept SPD by a tiny ridge.
            gram = df @ df.T
            ridge = 1e-12 * jnp.max(jnp.diag(gram)) + jnp.finfo(f.dtype).tiny
            gram = gram + jnp.diag(jnp.where(used, ridge, 1.0))
            gamma = jnp.where(used, spd_solve(gram, df @ f), 0.0)
            return g_flat - (dx + df).T @ gamma

        # Converged or contracting fast: g(y) itself.
        plain = (error < 1) | (rate < self.plain_rate)
        new = lax.cond(plain, lambda: g_flat, accelerated)
        new_state = _AndersonState(dx, df, flat, f, state.count + 1, first_error, rate, error)
        return unravel(new), new_state, aux

    def terminate(self, fn, y, args, options, state: _AndersonState, tags):
        return state.relative_error < 1, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {}
