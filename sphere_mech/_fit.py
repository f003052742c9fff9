"""`fit`: least-squares fitting of parameters (and initial states) of a system to observed
trajectories, by differentiating through `simulate`, with optional multiple shooting."""

from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, PyTree

from ._geometry import retract
from ._simulate import simulate
from ._system import AbstractSystem


class FitResult(eqx.Module):
    """What `fit` returns.

    - `params`: the fitted parameters, same structure as `params0`.
    - `loss`: the final loss `1/2 sum r^2` (data and continuity residuals).
    - `num_steps`: number of iterations of the least-squares solver.
    - `converged`: whether the solver met its tolerances within `max_steps`.
    - `losses`: the loss after each iteration, `(max_steps,)`, NaN after the last one.
    - `segment_states`: the fitted initial states `(q, v)` of the shooting segments,
      `([B,] K, n, 3)` arrays (segment 0 is `y0` unless `fit_initial_state=True`).
    - `result`: the optimistix `RESULTS` code.
    """

    params: PyTree
    loss: Array
    num_steps: Array
    converged: Array
    losses: Array
    segment_states: tuple[Array, Array]
    result: optx.RESULTS


# ----------------------------------------------------------------------------------------
# Positivity: parameters flagged `positive` are fitted as their logarithm.


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


def _map_flagged(fn, tree, flags):
    leaves, treedef = jtu.tree_flatten(tree)
    return jtu.tree_unflatten(
        treedef, [fn(x) if f else x for x, f in zip(leaves, flags, strict=True)]
    )


# ----------------------------------------------------------------------------------------
# Static layout of the shooting segments.


class _Layout(eqx.Module):
    """Segment k starts at observation `bounds[k]`, ends at `bounds[k + 1]`, and owns the
    observations `index[k]` (padded by repeating the last one, `mask` False there)."""

    bounds_: tuple = eqx.field(static=True)
    index_: tuple = eqx.field(static=True)
    mask_: tuple = eqx.field(static=True)

    @property
    def bounds(self):
        return np.array(self.bounds_)

    @property
    def index(self):
        return np.array(self.index_)

    @property
    def mask(self):
        return np.array(self.mask_)


def _layout(num_times: int, segments: int) -> _Layout:
    if not isinstance(segments, int) or segments < 1:
        raise ValueError(f"segments must be a positive integer, got {segments!r}.")
    if segments > num_times - 1:
        raise ValueError(
            f"segments={segments} needs at least {segments + 1} observation times, got {num_times}."
        )
    bounds = np.round(np.linspace(0, num_times - 1, segments + 1)).astype(int)
    owned = [np.arange(bounds[k], bounds[k + 1]) for k in range(segments)]
    owned[-1] = np.arange(bounds[-2], num_times)
    width = max(len(o) for o in owned)
    index = np.stack([np.pad(o, (0, width - len(o)), mode="edge") for o in owned])
    mask = np.stack([np.arange(width) < len(o) for o in owned])
    return _Layout(
        tuple(bounds.tolist()), tuple(map(tuple, index.tolist())), tuple(map(tuple, mask.tolist()))
    )


# ----------------------------------------------------------------------------------------
# The residual function.


def _system_and_args(model, params):
    out = model(params)
    if isinstance(out, AbstractSystem):
        return out, None
    if isinstance(out, tuple) and len(out) == 2 and isinstance(out[0], AbstractSystem):
        return out
    raise ValueError(
        "model(params) must return a sphere_mech system or a pair (system, args), got "
        f"{type(out).__name__}."
    )


def _segment_residual(system, args, observe, y_start, ts, t0, t1, obs, mask, sim):
    """Simulate one segment from `y_start` at `t0` to `t1`, saving at `ts`; return the
    masked observation residuals and the state at `t1`."""
    save = jnp.concatenate([ts, t1[None]])
    sol = simulate(
        system, y_start, t1, t0=t0, args=args, saveat=diffrax.SaveAt(ts=save), throw=False, **sim
    )
    q, v = sol.ys
    pred = jax.vmap(observe, in_axes=(None, 0, 0, 0))(system, ts, q[:-1], v[:-1])
    shape = (-1,) + (1,) * (pred.ndim - 1)
    return jnp.where(mask.reshape(shape), pred - obs, 0.0), (q[-1], v[-1])


class _Residuals(eqx.Module):
    model: Callable
    observe: Callable
    positive: tuple = eqx.field(static=True)
    static_params: PyTree
    layout: _Layout
    fit_initial_state: bool = eqx.field(static=True)
    continuity: float
    sim: dict
    jac: str = eqx.field(static=True)

    def states(self, z, y0):
        """Initial states of all segments, `(B, K, n, 3)` each, on the tangent bundle."""
        if self.fit_initial_state:
            return retract(*z)
        q0, v0 = (y[:, None] for y in y0)
        if z is None:
            return q0, v0
        q, v = retract(*z)
        return jnp.concatenate([q0, q], 1), jnp.concatenate([v0, v], 1)

    def params(self, u):
        return eqx.combine(_map_flagged(jnp.exp, u, self.positive), self.static_params)

    def segment(self, u, state, ts, obs, t0, t1, mask):
        """Residuals and final state of one segment."""
        system, args = _system_and_args(self.model, self.params(u))
        return _segment_residual(system, args, self.observe, state, ts, t0, t1, obs, mask, self.sim)

    def over_segments(self, fn, states, data):
        """Map `fn(state, ts, obs, t0, t1, mask)` over all records and segments:
        `(B, K, ...)` outputs (the mask is shared by the records)."""
        ts, obs, _ = data
        lay = self.layout
        per_segment = (
            ts[:, lay.index],
            obs[:, lay.index],
            ts[:, lay.bounds[:-1]],
            ts[:, lay.bounds[1:]],
        )
        fn = jax.vmap(jax.vmap(fn, in_axes=(0,) * 5 + (0,)), in_axes=(0,) * 5 + (None,))
        return fn(states, *per_segment, jnp.asarray(lay.mask))

    def segments(self, u, states, data):
        """`segment` over all records and segments: `(B, K, ...)` outputs."""
        return self.over_segments(lambda s, *d: self.segment(u, s, *d), states, data)

    def __call__(self, unknowns, data):
        u, z = unknowns
        qs, vs = self.states(z, data[2])
        res, (q_end, v_end) = _segments(u, (qs, vs), problem=self, data=data)
        weight = jnp.sqrt(jnp.asarray(self.continuity, res.dtype))
        jump = (weight * (q_end[:, :-1] - qs[:, 1:]), weight * (v_end[:, :-1] - vs[:, 1:]))
        return res, jump


@eqx.filter_custom_jvp
def _segments(u, states, *, problem, data):
    return problem.segments(u, states, data)


@_segments.def_jvp
def _segments_jvp(primals, tangents, *, problem, data):
    """Segment `k` depends only on the parameters and its own initial state: build each
    segment's Jacobian (`dim(u) + 6n` columns, forward mode; or its rows, reverse mode)
    once, then apply it to any tangent. This keeps the cost of the least-squares
    Jacobian independent of the number of segments."""
    u, states = primals
    du, dstates = tangents
    u_flat, unravel_u = ravel_pytree(u)
    s0 = jtu.tree_map(lambda x: x[0, 0], states)
    s_flat0, unravel_s = ravel_pytree(s0)

    def flat(u_flat_, s_flat_, *d):
        out = problem.segment(unravel_u(u_flat_), unravel_s(s_flat_), *d)
        out_flat = ravel_pytree(out)[0]
        return out_flat, out

    jacobian = jax.jacfwd if problem.jac == "fwd" else jax.jacrev
    block = jacobian(flat, argnums=(0, 1), has_aux=True)
    s_flat = jax.vmap(jax.vmap(lambda s: ravel_pytree(s)[0]))(states)
    (J_u, J_s), out = problem.over_segments(lambda s, *d: block(u_flat, s, *d), s_flat, data)
    t_out = jnp.zeros(J_u.shape[:-1], J_u.dtype)
    if du is not None:
        du_flat = ravel_pytree(_fill_zeros(du, u))[0]
        t_out = t_out + J_u @ du_flat
    if dstates is not None:
        ds = _fill_zeros(dstates, states)
        ds_flat = jax.vmap(jax.vmap(lambda s: ravel_pytree(s)[0]))(ds)
        t_out = t_out + jnp.einsum("bkrs,bks->bkr", J_s, ds_flat)
    unravel_out = ravel_pytree(jtu.tree_map(lambda x: x[0, 0], out))[1]
    return out, jax.vmap(jax.vmap(unravel_out))(t_out)


def _fill_zeros(tangents, primals):
    """Symbolic zero tangents (`None`) of array primals as arrays of zeros."""
    fill = lambda t, p: jnp.zeros_like(p) if t is None and p is not None else t
    return jtu.tree_map(fill, tangents, primals, is_leaf=lambda x: x is None)


# ----------------------------------------------------------------------------------------
# The least-squares loop (optimistix's iteration, keeping the loss of every step).


def _loss(residuals):
    return 0.5 * sum(jnp.sum(r**2) for r in jtu.tree_leaves(residuals))


@eqx.filter_jit
def _least_squares(fn, solver, y0, data, max_steps, options):
    y0 = jtu.tree_map(lambda x: jnp.asarray(x, dtype=jnp.result_type(x, float)), y0)
    fn = eqx.filter_closure_convert(lambda y, a: (fn(y, a), None), y0, data)
    f_struct, aux_struct = fn.out_struct
    tags = frozenset()
    state = solver.init(fn, y0, data, options, f_struct, aux_struct, tags)
    dynamic, static = eqx.partition(state, eqx.is_array)
    dtype = jtu.tree_leaves(f_struct)[0].dtype
    losses = jnp.full(max_steps, jnp.nan, dtype=dtype)
    carry = (y0, jnp.array(0), dynamic, jnp.array(False), optx.RESULTS.successful, losses)

    def cond(carry):
        _, i, _, terminate, result, _ = carry
        return ~terminate & (result == optx.RESULTS.successful) & (i < max_steps)

    def body(carry):
        y, i, dynamic, _, _, losses = carry
        state = eqx.combine(static, dynamic)
        y, state, _ = solver.step(fn, y, data, options, state, tags)
        terminate, result = solver.terminate(fn, y, data, options, state, tags)
        f_info = getattr(state, "f_info", None)
        residual = f_info.residual if hasattr(f_info, "residual") else fn(y, data)[0]
        losses = losses.at[i].set(_loss(residual))
        return y, i + 1, eqx.filter(state, eqx.is_array), terminate, result, losses

    y, steps, _, terminate, result, losses = jax.lax.while_loop(cond, body, carry)
    result = optx.RESULTS.where(
        (result == optx.RESULTS.successful) & ~terminate,
        optx.RESULTS.nonlinear_max_steps_reached,
        result,
    )
    return (
        y,
        _loss(fn(y, data)[0]),
        steps,
        terminate & (result == optx.RESULTS.successful),
        losses,
        result,
    )


# ----------------------------------------------------------------------------------------
# Input handling.


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
    if not hasattr(out, "shape") or out.shape != observations.shape[2:]:
        raise ValueError(
            f"observe(system, t, q, v) returns shape {getattr(out, 'shape', type(out))} but "
            f"each observation has shape {observations.shape[2:]}."
        )


def _guess_states(system, args, ts, y0, layout, sim):
    """States at the segment starts (after the first) from one simulation with `params0`."""
    times = ts[:, layout.bounds[1:-1]]

    def one(t_b, q_b, v_b):
        sol = simulate(
            system,
            (q_b, v_b),
            t_b[-1],
            t0=ts[0, 0],
            args=args,
            saveat=diffrax.SaveAt(ts=t_b),
            throw=False,
            **sim,
        )
        return sol.ys

    q, v = jax.vmap(one)(times, *y0)
    q = jnp.where(jnp.isfinite(q), q, y0[0][:, None])
    return q, jnp.where(jnp.isfinite(v), v, 0.0)


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
    (plus continuity penalties with multiple shooting) with an optimistix least-squares
    solver (Levenberg-Marquardt by default).

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
      fewer unknowns per segment than residuals (5.5x on the 5 s double-pendulum fit of
      `benchmarks/fit_adjoint.py`).
    - `adjoint`: override the diffrax adjoint chosen from `jac`.
    - `simulate_options`: keyword arguments for `simulate` (`solver`, `rtol`, `atol`,
      `dt0`, `stepsize_controller`, `max_steps`).

    **Returns:** a `FitResult`.
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
    layout = _layout(ts.shape[1], segments)

    params0 = _as_arrays(params0)
    flags = _positive_flags(params0, positive)
    dynamic, static = eqx.partition(params0, eqx.is_inexact_array)
    u0 = _map_flagged(jnp.log, dynamic, flags)
    system0, args0 = _system_and_args(model, params0)
    _check_observe(observe, system0, ts, observations, y0)
    z0 = _initial_unknown_states(
        system0, args0, ts, y0, layout, segment_states, fit_initial_state, batched, sim
    )
    residuals = _Residuals(
        model, observe, flags, static, layout, fit_initial_state, continuity, sim, jac
    )
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9) if solver is None else solver
    (u, z), loss, steps, converged, losses, result = _least_squares(
        residuals, solver, (u0, z0), (ts, observations, y0), max_steps, {"jac": "fwd"}
    )
    states = residuals.states(z, y0)
    if not batched:
        states = tuple(s[0] for s in states)
    return FitResult(residuals.params(u), loss, steps, converged, losses, states, result)


def _initial_unknown_states(system, args, ts, y0, layout, guess, fit_initial_state, batched, sim):
    num_segments = len(layout.bounds) - 1
    if guess is None:
        guess = _guess_states(system, args, ts, y0, layout, sim) if num_segments > 1 else None
    else:
        guess = tuple(jnp.asarray(g) for g in guess)
        if not batched:
            guess = tuple(g[None] for g in guess)
        expected = (y0[0].shape[0], num_segments - 1) + y0[0].shape[1:]
        if len(guess) != 2 or any(g.shape != expected for g in guess):
            shape = expected[1:] if not batched else expected
            raise ValueError(
                f"segment_states must be (q, v) for the starts of segments 2..K, shape "
                f"{shape}, got {[g.shape for g in guess]}."
            )
    if fit_initial_state:
        q0, v0 = (y[:, None] for y in y0)
        if guess is None:
            return q0, v0
        return jnp.concatenate([q0, guess[0]], 1), jnp.concatenate([v0, guess[1]], 1)
    return guess
