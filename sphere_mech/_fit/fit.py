"""`fit`: least-squares fitting of parameters (and initial states) of a system to observed
trajectories, through `simulate`, with `optimistix.least_squares` and optional multiple
shooting."""

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optimistix as optx
from jaxtyping import Array, PyTree

from .._simulate import simulate
from .shooting import Residuals, map_flagged, model_output, split_segments


class FitResult(eqx.Module):
    """What `fit` returns.

    - `params`: the fitted parameters, same structure as `params0`.
    - `loss`: the loss `1/2 sum r^2` (observation and continuity residuals) at the
      solution.
    - `initial_loss`: the same loss at `params0` and the initial segment states.
    - `num_steps`: number of iterations of the least-squares solver.
    - `converged`: whether the solver met its tolerances within `max_steps`
      (`result == optimistix.RESULTS.successful`).
    - `segment_states`: the fitted initial states `(q, v)` of the shooting segments,
      `([B,] K, n, 3)` arrays (segment 0 is `y0` unless `fit_initial_state=True`).
    - `result`: the `optimistix.RESULTS` code of the least-squares solve.
    """

    params: PyTree
    loss: Array
    initial_loss: Array
    num_steps: Array
    converged: Array
    segment_states: tuple[Array, Array]
    result: optx.RESULTS


def _as_arrays(params):
    """Python and NumPy floats in `params` become JAX arrays (so they are fitted)."""
    is_float = lambda x: (
        isinstance(x, float | np.floating)
        or (isinstance(x, np.ndarray) and np.issubdtype(x.dtype, np.floating))
    )
    return jtu.tree_map(lambda x: jnp.asarray(x) if is_float(x) else x, params)


def _positive_flags(params0, positive) -> tuple[bool, ...]:
    """One flag per floating-point array leaf of `params0` (in `tree_leaves` order)."""
    if isinstance(positive, bool):
        positive = jtu.tree_map(lambda _: positive, params0)
    try:
        flags = jtu.tree_map(
            lambda p, f: bool(f) if eqx.is_inexact_array(p) else None, params0, positive
        )
    except (ValueError, TypeError) as e:
        raise ValueError(
            "positive must be a bool or a pytree of bools with the structure of params0."
        ) from e
    dynamic = eqx.filter(params0, eqx.is_inexact_array)
    for p, f in zip(jtu.tree_leaves(dynamic), jtu.tree_leaves(flags), strict=True):
        if f and not bool(jnp.all(p > 0)):
            raise ValueError(
                "a parameter flagged positive (fitted in log space) is not > 0 in params0."
            )
    return tuple(jtu.tree_leaves(flags))


def _as_batch(ts, observations, y0):
    """Bring `ts`, `observations`, `y0` to a leading batch axis of records; check shapes."""
    if not (isinstance(y0, tuple | list) and len(y0) == 2):
        raise ValueError("y0 must be a pair (q0, v0) of (n, 3) or (B, n, 3) arrays.")
    q0, v0 = (jnp.asarray(y) for y in y0)
    if q0.shape != v0.shape or q0.ndim not in (2, 3) or q0.shape[-1] != 3:
        raise ValueError(
            f"y0 must be (q0, v0) with equal shapes (n, 3) or (B, n, 3), got {q0.shape} "
            f"and {v0.shape}."
        )
    batched = q0.ndim == 3
    ts, observations = jnp.asarray(ts), jnp.asarray(observations)
    if not batched:
        q0, v0, observations = q0[None], v0[None], observations[None]
    num_records = q0.shape[0]
    if ts.ndim == 1:
        ts = jnp.broadcast_to(ts, (num_records,) + ts.shape)
    if ts.ndim != 2 or ts.shape[0] != num_records:
        raise ValueError(
            f"ts must have shape (T,) or (B, T) with B = {num_records} records (the leading "
            f"axis of y0), got {jnp.shape(ts)}."
        )
    if observations.ndim < 2 or observations.shape[:2] != ts.shape:
        expected = "(T, ...)" if not batched else "(B, T, ...)"
        got = observations.shape[1:] if not batched else observations.shape
        raise ValueError(
            f"observations must have shape {expected} with T = {ts.shape[1]} observation "
            f"times (and B = {num_records} records when y0 is batched), got {got}."
        )
    return ts, observations, (q0, v0), batched


def _check_observe(observe, system, ts, observations, y0):
    out = eqx.filter_eval_shape(observe, system, ts[0, 0], y0[0][0], y0[1][0])
    shape = out.shape if isinstance(out, jax.ShapeDtypeStruct) else type(out).__name__
    if shape != observations.shape[2:]:
        raise ValueError(
            f"observe(system, t, q, v) returns {shape} but each observation has shape "
            f"{observations.shape[2:]}."
        )


def _guess_states(system, args, segment_t0, y0, sim):
    """States at the starts of segments 2..K from one simulation per record with
    `params0` (non-finite values, after a failed run, replaced by `y0` at rest)."""

    def one(t, q0, v0):
        saveat = diffrax.SaveAt(ts=t[1:])
        return simulate(
            system, (q0, v0), t[-1], t0=t[0], args=args, saveat=saveat, throw=False, **sim
        ).ys

    q, v = jax.vmap(one)(segment_t0, *y0)
    q = jnp.where(jnp.isfinite(q), q, y0[0][:, None])
    return q, jnp.where(jnp.isfinite(v), v, 0.0)


def _initial_unknown_states(guess, system, args, segment_t0, y0, fit_initial_state, batched, sim):
    """`z0`: the starts of segments 2..K (and of segment 1 with `fit_initial_state`)."""
    num_segments = segment_t0.shape[1]
    if guess is None:
        guess = _guess_states(system, args, segment_t0, y0, sim) if num_segments > 1 else None
    else:
        guess = tuple(jnp.asarray(g) if batched else jnp.asarray(g)[None] for g in guess)
        expected = (y0[0].shape[0], num_segments - 1) + y0[0].shape[1:]
        if len(guess) != 2 or any(g.shape != expected for g in guess):
            raise ValueError(
                f"segment_states must be (q, v) for the starts of segments 2..K, shape "
                f"{expected if batched else expected[1:]}, got {[g.shape for g in guess]}."
            )
    if not fit_initial_state:
        return guess
    q0, v0 = (y[:, None] for y in y0)
    if guess is None:
        return q0, v0
    return jnp.concatenate([q0, guess[0]], 1), jnp.concatenate([v0, guess[1]], 1)


@eqx.filter_jit
def _solve(residuals, solver, unknowns0, data, max_steps):
    sol = optx.least_squares(
        residuals, solver, unknowns0, data, {"jac": "fwd"}, max_steps=max_steps, throw=False
    )
    # the losses at the solution and at the start (`lax.map`: the residuals compiled once)
    both = jtu.tree_map(lambda a, b: jnp.stack([a, b]), sol.value, unknowns0)
    r = jax.lax.map(lambda y: residuals(y, data), both)
    loss, initial_loss = 0.5 * sum(
        jnp.sum(x**2, axis=tuple(range(1, x.ndim))) for x in jtu.tree_leaves(r)
    )
    return sol.value, loss, initial_loss, sol.stats["num_steps"], sol.result


def fit(
    model: Callable[[PyTree], Any],
    params0: PyTree,
    ts,
    observations,
    observe: Callable,
    *,
    y0,
    segments: int = 1,
    segment_states=None,
    fit_initial_state: bool = False,
    positive: bool | PyTree = False,
    continuity: float = 1.0,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 100,
    jac: str = "fwd",
    adjoint: diffrax.AbstractAdjoint | None = None,
    simulate_options: dict | None = None,
) -> FitResult:
    """Fit parameters of a system to observed trajectories by least squares, through
    `simulate`.

    Minimizes `1/2 sum_{b, j} |observe(system, t_j, q_bj, v_bj) - observations_bj|^2`
    (plus continuity penalties with multiple shooting) with `optimistix.least_squares`
    (Levenberg-Marquardt by default).

    **Arguments:**
    - `model`: `model(params) -> system` or `(system, args)`; any sphere_mech system.
    - `params0`: initial parameters, any pytree (dict, tuple, equinox Module such as an
      `eqx.nn.MLP`); its floating-point array leaves are fitted, other leaves kept.
    - `ts`: observation times `(T,)` (or `(B, T)`, one row per record), increasing;
      the simulation starts at `ts[0]`.
    - `observations`: `(T, ...)`, or `(B, T, ...)` for a batch of `B` records.
    - `observe`: `observe(system, t, q, v) -> array` of the shape of one observation
      (e.g. the tip position).
    - `y0`: initial state `(q0, v0)` at `ts[0]`, `(n, 3)` arrays, or `(B, n, 3)` for a
      batch of records (the batch is given by `y0`).
    - `segments`: number of shooting segments `K` (1: single shooting). Each segment
      after the first starts from its own state, fitted as an extra unknown and kept
      on the tangent bundle by `retract` of an ambient `(a, b)`; a penalty
      `continuity * |y_end(k) - y_start(k + 1)|^2` ties the segments together.
    - `segment_states`: initial guesses `(q, v)` for the starts of segments 2..K,
      `([B,] K - 1, n, 3)` (e.g. estimated from the data); default: a simulation of
      `model(params0)` from `y0`.
    - `fit_initial_state`: also fit `y0` (taken then as the initial guess).
    - `positive`: `True`, or a pytree of bools matching `params0`: those parameters are
      fitted as `log(p)` (so they stay positive); they must be `> 0` in `params0`.
    - `continuity`: weight of the continuity penalties.
    - `solver`: an optimistix least-squares solver; default
      `optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9)`.
    - `max_steps`: maximum number of solver iterations.
    - `jac`: how each segment's Jacobian (columns: the parameters and the segment's own
      initial state) is computed: `"fwd"` (default) by `jax.jacfwd` through `simulate`
      with `diffrax.ForwardMode()`, or `"bwd"` by `jax.jacrev` with
      `diffrax.RecursiveCheckpointAdjoint()`. Forward mode is faster whenever there are
      fewer unknowns per segment than residuals (5.7x on the 5 s double-pendulum fit of
      `benchmarks/fit_adjoint.py`).
    - `adjoint`: override the diffrax adjoint chosen from `jac`.
    - `simulate_options`: keyword arguments for `simulate` (`solver`, `rtol`, `atol`,
      `dt0`, `stepsize_controller`, `max_steps`).

    **Returns:** a `FitResult`. Failures of the solve (e.g. `max_steps` reached) are
    reported in `result` and `converged`, never raised.
    """
    if jac not in ("fwd", "bwd"):
        raise ValueError(f"jac must be 'fwd' or 'bwd', got {jac!r}.")
    if adjoint is None:
        adjoint = diffrax.ForwardMode() if jac == "fwd" else diffrax.RecursiveCheckpointAdjoint()
    sim = dict(simulate_options or {})
    for key in ("saveat", "t0", "args", "adjoint", "throw"):
        if key in sim:
            raise ValueError(f"simulate_options may not set {key!r}; fit sets it.")
    sim["adjoint"] = adjoint
    ts, observations, y0, batched = _as_batch(ts, observations, y0)
    segment_data = split_segments(ts, observations, segments)

    params0 = _as_arrays(params0)
    flags = _positive_flags(params0, positive)
    dynamic, static = eqx.partition(params0, eqx.is_inexact_array)
    system0, args0 = model_output(model, params0)
    _check_observe(observe, system0, ts, observations, y0)
    z0 = _initial_unknown_states(
        segment_states, system0, args0, segment_data[2], y0, fit_initial_state, batched, sim
    )
    residuals = Residuals(
        model, observe, flags, static, fit_initial_state, jnp.asarray(continuity), sim, jac
    )
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9) if solver is None else solver
    unknowns0 = (map_flagged(jnp.log, dynamic, flags), z0)
    (u, z), loss, initial_loss, num_steps, result = _solve(
        residuals, solver, unknowns0, (segment_data, y0), max_steps
    )
    states = residuals.states(z, y0)
    if not batched:
        states = tuple(s[0] for s in states)
    converged = result == optx.RESULTS.successful
    return FitResult(residuals.params(u), loss, initial_loss, num_steps, converged, states, result)
