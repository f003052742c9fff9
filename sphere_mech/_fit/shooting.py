"""Multiple shooting for `fit` and `learn`: segments, residuals, each segment's Jacobian
built once (`fit`'s least squares) or plain reverse-mode autodiff (`learn`'s gradients)."""

from collections.abc import Callable

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.flatten_util import ravel_pytree
from jax.sharding import Mesh
from jaxtyping import Array, PyTree

from .._batch import map_on_devices
from .._misc import check_integer, fill_zeros, rows, tree_dtype
from .._results import RESULTS, describe_failures, gathered
from .._simulate import simulate
from .._solve import check_values, initial_states
from .._spaces import AbstractSpace
from .._system import AbstractSystem


def split_segments(ts: Array, observations: Array, segments: int) -> tuple[Array, ...]:
    """`ts (B, T)` and `observations (B, T, ...)` cut into `K` segments: `(ts, obs, t0, t1,
    mask)` with leading axes `(B, K)`. Segment `k` runs from observation `bounds[k]` to
    `bounds[k + 1]` and owns those before the next segment's first, padded (`mask` False)."""
    num_records, num_times = ts.shape
    check_integer(segments, "segments")
    if segments > num_times - 1:
        raise ValueError(
            f"segments={segments} needs at least {segments + 1} observation times, got {num_times}."
        )
    bounds = np.round(np.linspace(0, num_times - 1, segments + 1)).astype(int)
    ends = np.append(bounds[1:-1], num_times)
    index = bounds[:-1, None] + np.arange(np.max(ends - bounds[:-1]))
    mask = jnp.broadcast_to(index < ends[:, None], (num_records,) + index.shape)
    index = np.minimum(index, ends[:, None] - 1)
    return ts[:, index], observations[:, index], ts[:, bounds[:-1]], ts[:, bounds[1:]], mask


def check_data(system, ts, y0, observations, caller: str, record: str) -> None:
    """The one check of the data of `fit`, `learn` and `refine`, before any solve
    (`ValueError`): the observation times `ts` (`(T,)`, or `(B, T)` one row per record)
    finite and increasing, the records' initial states `y0` (a leading axis of records) as
    `simulate_batch` checks its initial states (`initial_states`, the same words), and the
    observations `(B, T, ...)` finite. Traced times and observations pass."""
    if not isinstance(ts, jax.core.Tracer):
        times = np.atleast_2d(gathered(ts))
        increasing = np.isfinite(times).all(1) & (np.diff(times, axis=1) > 0).all(1)
        bad = np.flatnonzero(~increasing)
        if bad.size:
            failed = f"{record}s have times that are not finite and increasing"
            where = describe_failures(bad, times.shape[0], failed, record)
            raise ValueError(
                f"{caller}:{where} ts must be finite and strictly increasing, got "
                f"{times[bad[0]][:10]}."
            )
    initial_states(system.state_space, system.state_name, y0, caller, True)
    if isinstance(observations, jax.core.Tracer):
        return
    values = gathered(observations)
    finite = np.isfinite(values.reshape(values.shape[:2] + (-1,))).all(-1)  # (B, T)
    bad = np.flatnonzero(~finite.all(1))
    if bad.size:
        failed = f"{record}s have a non-finite observation"
        where = describe_failures(bad, finite.shape[0], failed, record)
        index = np.flatnonzero(~finite[bad[0]])[0]
        raise ValueError(
            f"{caller}:{where} observation {index} is NaN or infinite (observations must "
            "be finite: drop or fill missing ones)."
        )


def model_output(model: Callable, params: PyTree) -> tuple[AbstractSystem, PyTree]:
    """`model(params)` as a pair `(system, args)`."""
    out = model(params)
    if isinstance(out, AbstractSystem):
        return out, None
    if isinstance(out, tuple) and len(out) == 2 and isinstance(out[0], AbstractSystem):
        return out
    raise ValueError(
        "model(params) must return a sphere_mech system or a pair (system, args), got "
        f"{type(out).__name__}."
    )


def simulate_at(system, args, state, t0, t1, ts, sim: dict):
    """`(q, v)` at `ts` and `(q, v)` at `t1` of `simulate` from `state` at `t0`, never
    raising. The end state is the solve's last (`SaveAt(t1=True)`), not one more time in
    `ts` (an interpolated save: the magnet task's training step took 34.7 ms with it against
    27.7 ms without, medians of 40 on this 2-core CPU). A solve that stops before `t1`
    (failed) gives `inf` there, as at the times in `ts` it did not reach."""
    saveat = diffrax.SaveAt(ts=ts, t1=True)
    sol = simulate(system, state, t1, t0=t0, args=args, saveat=saveat, throw=False, **sim)
    reached = sol.result == RESULTS.successful
    end = jtu.tree_map(lambda x: jnp.where(reached, x[-1], jnp.inf), sol.ys)
    # A solve that stopped early has its last state in the first slot of `ts` it did not
    # reach (diffrax), with its own time: a save is at `ts` only where its time is.
    saved = reached | (sol.ts[:-1] == jnp.asarray(ts, sol.ts.dtype))
    return jtu.tree_map(lambda x: jnp.where(rows(saved, x[:-1]), x[:-1], jnp.inf), sol.ys), end


def own_options(simulate_options, caller: str, ts) -> dict:
    """A copy of the caller's `simulate_options`, refusing those the caller sets itself;
    their values checked as `simulate` checks them (the observation times `ts` the
    direction of integration), before anything is traced: inside the caller's program the
    times are traced and only diffrax would refuse, after compiling."""
    sim = dict(simulate_options or {})
    for key in ("saveat", "t0", "args", "adjoint", "throw"):
        if key in sim:
            raise ValueError(f"simulate_options may not set {key!r}; {caller} sets it.")
    if not isinstance(ts, jax.core.Tracer):  # the caller's own check names bad times
        times = np.asarray(ts, dtype=float)
        times = times[np.isfinite(times)]
        ends = (times.min(), times.max()) if times.size else (None, None)
        check_values(*ends, *(sim.get(k) for k in ("dt0", "rtol", "atol", "max_steps")))
    return sim


def map_flagged(fn: Callable, tree: PyTree, flags: tuple[bool, ...]) -> PyTree:
    """`fn` applied to the leaves of `tree` whose flag is True."""
    leaves, treedef = jtu.tree_flatten(tree)
    mapped = [fn(x) if f else x for x, f in zip(leaves, flags, strict=True)]
    return jtu.tree_unflatten(treedef, mapped)


def over_states(fn: Callable, mesh: Mesh | None = None) -> Callable:
    """`fn` of one state mapped over the leading axes `(B, K)` (records, segments), the
    `B K` calls split over the devices of `mesh` if one is given. One `vmap` over the `B K`
    calls, not one per axis: each `vmap` transforms the solver's loops again (the fit of
    notebook 08 traced in 10.0 to 11.9 s against 12.3 to 13.8 s, suite compile settings)."""

    def mapped(*trees):
        B, K = jtu.tree_leaves(trees)[0].shape[:2]
        flat = jtu.tree_map(lambda x: x.reshape((B * K,) + x.shape[2:]), trees)
        out = jax.vmap(fn)(*flat) if mesh is None else map_on_devices(fn, mesh, *flat)
        return jtu.tree_map(lambda x: x.reshape((B, K) + x.shape[1:]), out)

    return mapped


def with_first(y0, rest):
    """`y0` as segment 0 before `rest` (leading axes `(B, K - 1)`, or `None`)."""
    first = jtu.tree_map(lambda y: y[:, None], y0)
    if rest is None:
        return first
    return jtu.tree_map(lambda a, b: jnp.concatenate([a, b], 1), first, rest)


class Residuals(eqx.Module):
    """The residuals `((u, z), (segment data, y0)) -> (observation residuals (B, K, W, ...),
    continuity jumps (dq, dv) with leading axes (B, K - 1))`: `u` the fitted parameters
    (`positive` ones as logarithms), `z` the ambient pairs `(a, b)` that `space.retract`
    makes the starts of segments 2..K (1..K with `fit_initial_state`), or `None`. `jac`:
    `"fwd"` or `"bwd"`, each segment's Jacobian built once by `jax.jacfwd` / `jax.jacrev`
    for any tangent (least squares); `"grad"`, the segments differentiated as written
    (reverse mode through the solver: the gradient of a scalar loss for `learn`).

    The data's times `(ts, t0, t1)` are each segment's, leading axes `(B, K)`, or one
    segment's, `(W,)`, `()`, `()`, shared by every record (`learn` on chunks observed at
    the same times, one segment each): those stay unbatched under the `vmap` over records,
    and so does the solver's time stepping (the magnet task's training step in a bare
    harness, float32, 100 chunks: 24.0 ms against 28.6 ms with the times batched, medians
    of 20 on this 2-core CPU)."""

    model: Callable
    space: AbstractSpace
    observe: Callable
    positive: tuple[bool, ...] = eqx.field(static=True)
    static_params: PyTree
    fit_initial_state: bool = eqx.field(static=True)
    continuity: Array
    sim: dict
    dtypes: PyTree  # the unknowns' own: `jtu.tree_map(jnp.result_type, (u, z))`
    jac: str = eqx.field(static=True)
    mesh: Mesh | None = eqx.field(static=True, default=None)

    def own(self, unknowns):
        """`(u, z)` in their own dtypes. `fit`'s least squares runs in JAX's default float
        (float64 with x64 on) on float32 parameters and states too: optimistix's
        Levenberg-Marquardt adds its float64 damping to the unknowns, which float32
        unknowns cannot match (a lineax structure error, before)."""
        return jtu.tree_map(lambda x, dtype: x.astype(dtype), unknowns, self.dtypes)

    def params(self, u):
        return eqx.combine(map_flagged(jnp.exp, u, self.positive), self.static_params)

    def states(self, z, y0):
        """Initial states of all segments, leading axes `(B, K)`."""
        retract = over_states(self.space.retract)
        if self.fit_initial_state:
            return retract(*z)
        return with_first(y0, None if z is None else retract(*z))

    def segment(self, u, state, ts, obs, t0, t1, mask):
        """Masked observation residuals of one segment and its state at `t1`."""
        system, args = model_output(self.model, self.params(u))
        (q_obs, v_obs), end = simulate_at(system, args, state, t0, t1, ts, self.sim)
        pred = jax.vmap(self.observe, in_axes=(None, 0, 0, 0))(system, ts, q_obs, v_obs)
        mask = mask.reshape(mask.shape + (1,) * (pred.ndim - 1))
        return jnp.where(mask, pred - obs, 0.0), end

    def over_segments(self, fn: Callable, states, data):
        """`fn(state, ts, obs, t0, t1, mask)` over the segments, leading axes `(B, K)`."""
        ts, obs, t0, t1, mask = data
        if ts.ndim != 1:  # each segment's own times
            return over_states(fn, self.mesh)(states, *data)
        one = lambda s, o, m: fn(s, ts, o, t0, t1, m)
        return over_states(one, self.mesh)(states, obs, mask)

    def __call__(self, unknowns, data):
        """The residuals in the dtype of `unknowns` as given, computed in their own."""
        (u, z), (segment_data, y0) = self.own(unknowns), data
        states = self.states(z, y0)
        segments = _direct_segments if self.jac == "grad" else _segments
        res, ends = segments(u, states, problem=self, data=segment_data)
        w = jnp.sqrt(self.continuity).astype(res.dtype)
        out = res, jtu.tree_map(lambda e, s: w * (e[:, :-1] - s[:, 1:]), ends, states)
        dtype = tree_dtype(unknowns)
        return jtu.tree_map(lambda x: x.astype(dtype), out)


def _direct_segments(u, states, *, problem, data):
    return problem.over_segments(lambda s, *d: problem.segment(u, s, *d), states, data)


_segments = eqx.filter_custom_jvp(_direct_segments)


@_segments.def_jvp
def _segments_jvp(primals, tangents, *, problem, data):
    """Segment `k` depends only on `u` and its own initial state: its Jacobian (`dim(u)`
    columns, plus `6n` on (S^2)^n when the states are unknowns, by `jac`) is built once
    from the primals and applied to any tangent, so the `vmap` over basis tangents costs the
    same for any number of segments. An argument with a symbolic zero tangent gets no
    columns: fixed states (single shooting from `y0`; the cable quadrotor of notebook 08: 2
    columns instead of 44), or fixed parameters (`fit`'s states' columns)."""
    (u, states), (du, dstates) = primals, tangents
    moving = tuple(i for i, t in enumerate(tangents) if jtu.tree_leaves(t))
    u_flat, unravel_u = ravel_pytree(u)
    s_flat, unravel_s = _ravel_segments(states)

    def flat(u_, s_, *d):
        out = problem.segment(unravel_u(u_), unravel_s(s_), *d)
        return ravel_pytree(out)[0], out

    jacobian = jax.jacfwd if problem.jac == "fwd" else jax.jacrev
    block = jacobian(flat, argnums=moving, has_aux=True)
    blocks, out = problem.over_segments(lambda s, *d: block(u_flat, s, *d), s_flat, data)
    blocks = dict(zip(moving, blocks, strict=True))
    t_out = 0.0
    if 0 in blocks:  # the parameters' tangent, shared by the segments
        t_out = t_out + blocks[0] @ ravel_pytree(fill_zeros(du, u))[0]
    if 1 in blocks:  # each segment's own state's
        ds_flat = _ravel_segments(fill_zeros(dstates, states))[0]
        t_out = t_out + jnp.einsum("bkrs,bks->bkr", blocks[1], ds_flat)
    return out, over_states(_ravel_segments(out)[1])(t_out)


def _ravel_segments(tree):
    """`(B, K, ...)` arrays as `(B, K, m)`, and the unravel of one segment."""
    flat = over_states(lambda x: ravel_pytree(x)[0])(tree)
    return flat, ravel_pytree(jtu.tree_map(lambda x: x[0, 0], tree))[1]
