"""`fit`: least squares of parameters (and initial states) against observed trajectories,
through `simulate`, with `optimistix.least_squares` and optional multiple shooting."""

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

from .._batch import batch_devices, batch_mesh, one_device
from .._misc import as_arrays, check_integer, check_positive, tree_add
from .._results import gathered
from .._solve import initial_states, state_pair
from .._spaces import AbstractSpace
from .shooting import (
    Residuals,
    check_data,
    map_flagged,
    model_output,
    over_states,
    own_options,
    simulate_at,
    split_segments,
    with_first,
)


class FitResult(eqx.Module):
    """What `fit` returns.

    **Attributes:**
    - `params`: the fitted parameters, same structure as `params0`.
    - `loss`, `initial_loss`: the loss `1/2 sum r^2` (observation and continuity
      residuals) at the solution and at `params0` with the initial segment states.
    - `num_steps`, `result`, `converged`: the least-squares solver's iterations, its
      `optimistix.RESULTS` code, and `result == optimistix.RESULTS.successful`. The fit
      stops at the solver's test on an accepted step (changes of the unknowns and of the
      residuals within its `rtol`, `atol`), or where, after a rejected step, the next step
      it proposes changes the unknowns by less than that tolerance (MINPACK's `xtol`
      test: the minimum as far as the residuals' own accuracy resolves it).
    - `segment_states`: the fitted initial states `(q, v)` of the segments, leading axes
      `([B,] K)` (segment 0 is `y0` unless `fit_initial_state=True`).

    Uncertainties, linearizing the residuals at the solution (Gauss-Newton, as
    `scipy.optimize.least_squares` and lmfit):
    - `jacobian`: `(m_rows, p)`, the Jacobian of the residuals at the solution. Rows: the
      raveled observation residuals `(B, K, W, ...)` (zero on a segment's padding), then
      the weighted continuity jumps of `q` and of `v` (`(B, K - 1, n, 3)` each on
      (S^2)^n). Columns: the fitted parameters as fitted (floating-point leaves of
      `params` raveled by `jax.flatten_util.ravel_pytree`, `log(p)` if `positive`), then
      the fitted segment states `(B, K', 2, d)` raveled: the `d` tangent coordinates of
      `dq`, then of `dv`, in the space's tangent basis at `q` (`d = 2n` on (S^2)^n, in
      `sm.tangent_basis(q)`; on a mixed space the factors' coordinates in key order).
    - `covariance`: `(p_params, p_params)`, the parameter block of
      `residual_variance * (J^T J)^{-1}` (segment states marginalized out), ordered as
      `jacobian`'s first columns. A parameter the data do not identify (`J` has a zero
      singular value, to `eps max(J.shape)`, that moves it) gets variance `inf` and NaN
      covariances; the others' are those of the identified directions.
    - `stderr`: standard errors in the structure of `params` (`None` at leaves not fitted),
      in the parameters' own units (`se(p) = p * se(log p)` for `positive` ones).
    - `residual_variance`: `s^2 = |r|^2 / dof`, the estimated noise variance.
    - `dof`: `m - p`: `m` counts the observation residuals and `2d` per continuity
      junction (to first order the jumps lie in the tangent space of the tangent
      bundle), `p` the fitted parameters and `2d` per fitted segment state: as for single
      shooting, the observed values minus the parameters (and `2d` per fitted `y0`).

    These assume a model nearly linear over the errors' size and independent Gaussian noise
    of one variance on every observed value and continuity penalty (weight `observe` and
    `observations` if levels differ; large `continuity`: the single-shooting covariance).
    """

    params: PyTree
    loss: Array
    initial_loss: Array
    num_steps: Array
    converged: Array
    segment_states: tuple[Array, Array]
    result: optx.RESULTS
    jacobian: Array
    covariance: Array
    stderr: PyTree
    residual_variance: Array
    dof: int = eqx.field(static=True)


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


def _as_batch(space: AbstractSpace, ts, observations, y0):
    """`ts`, `observations`, `y0` with a leading axis of records, shapes checked."""
    q0, v0 = state_pair(y0, "(n, 3) or (B, n, 3)")
    lead = space.batch_shape(q0)
    if len(lead) > 1 or space.batch_shape(v0) != lead:
        raise ValueError(
            "y0 must be (q0, v0), one state or a batch of states with one leading axis B "
            f"on every array, got shapes {jtu.tree_map(jnp.shape, (q0, v0))}."
        )
    batched = len(lead) == 1
    ts, observations = jnp.asarray(ts), jnp.asarray(observations)
    if not batched:
        (q0, v0), observations = jtu.tree_map(lambda y: y[None], (q0, v0)), observations[None]
    space.check_shapes(*jtu.tree_map(lambda y: y[0], (q0, v0)), "v0", "q0")
    num_records = lead[0] if batched else 1
    ts = jnp.broadcast_to(ts, (num_records,) + ts.shape) if ts.ndim == 1 else ts
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
    value = observe(system, ts[0, 0], *jtu.tree_map(lambda y: y[0], y0))  # evaluated once
    shape = value.shape if isinstance(value, jax.Array | np.ndarray) else type(value).__name__
    if shape != observations.shape[2:]:
        raise ValueError(
            f"observe(system, t, q, v) returns {shape} but each observation has shape "
            f"{observations.shape[2:]}."
        )
    if not (isinstance(value, jax.core.Tracer) or np.all(np.isfinite(gathered(value)))):
        raise ValueError(
            "observe(system, t, q, v) is NaN or infinite at the first record's initial state."
        )


def _guess_states(system, args, segment_t0, y0, sim):
    """States at the starts of segments 2..K simulated with `params0` (NaN: `y0` at rest)."""
    one = lambda t, q0, v0: simulate_at(system, args, (q0, v0), t[0], t[-1], t[1:], sim)[0]
    q, v = jax.vmap(one)(segment_t0, *y0)
    q = jtu.tree_map(lambda x, x0: jnp.where(jnp.isfinite(x), x, x0[:, None]), q, y0[0])
    return q, jtu.tree_map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), v)


def _initial_unknown_states(guess, system, args, segment_t0, y0, fit_initial_state, batched, sim):
    """`z0`: the starts of segments 2..K (and of segment 1 with `fit_initial_state`)."""
    num_segments = segment_t0.shape[1]
    if guess is None and num_segments > 1:
        guess = _guess_states(system, args, segment_t0, y0, sim)
    elif guess is not None:
        to_array = lambda g: jnp.asarray(g) if batched else jnp.asarray(g)[None]
        expected = [(y.shape[0], num_segments - 1) + y.shape[1:] for y in jtu.tree_leaves(y0)]
        valid = isinstance(guess, tuple | list) and len(guess) == 2
        if valid:
            guess = jtu.tree_map(to_array, tuple(guess))
            leaves, structure = jtu.tree_flatten(guess)
            valid = structure == jtu.tree_structure(y0) and [g.shape for g in leaves] == expected
        if not valid:
            raise ValueError(
                "segment_states must be (q, v) for the starts of segments 2..K: the "
                "structure of y0 with leading axes ([B,] K - 1), shapes (with the B axis) "
                f"{expected}, got {jtu.tree_map(jnp.shape, guess)}."
            )
        flat = jtu.tree_map(lambda g: g.reshape((-1, *g.shape[2:])), guess)  # (B (K - 1), ...)
        initial_states(system.state_space, system.state_name, flat, "fit: segment_states", True)
    return with_first(y0, guess) if fit_initial_state else guess


def _tangent_size(space: AbstractSpace, states):
    """`d`, the tangent coordinates of one point (`2n` on (S^2)^n), of states `(B, K, ...)`."""
    q, v = jtu.tree_map(lambda x: x[0, 0], states)
    return jax.eval_shape(lambda q, v: space.to_tangent(space.tangent_basis(q), v), q, v).shape[0]


def _degrees_of_freedom(space, observations, unknowns0, segments):
    """`m - p`, as `FitResult.dof` says."""
    u, z = unknowns0
    num_params = ravel_pytree(u)[0].size
    if z is None:
        return observations.size - num_params
    num_records, num_states = jtu.tree_leaves(z[0])[0].shape[:2]
    size = 2 * _tangent_size(space, z)
    return observations.size + size * num_records * (segments - 1 - num_states) - num_params


def _chart_at(space: AbstractSpace, to_linear, x):
    """One state's chart around `x = (q, v)` on the space: tangent coordinates `w (2, d)`
    (`dq`, `dv` in the space's tangent basis at `q`, `dq` turned into a move of `q` by the
    system's `to_linear`) to the moved state."""
    q, v = x
    basis = space.tangent_basis(q)
    move_q = lambda dq: tree_add(q, to_linear(q, space.from_tangent(basis, dq)))
    return lambda w: (move_q(w[0]), tree_add(v, space.from_tangent(basis, w[1])))


def _lift_at(space: AbstractSpace, to_linear, z):
    """`L (a, 2 d)`: for the solver's raveled state `z` (`a` numbers, off the space in
    general), the moves `dz = L w` that `retract`'s derivative at `z` maps to the chart's
    moves at `retract(z)` (`_chart_at`, `w` raveled). The residuals depend on the states
    through `retract` alone, so the solver's Jacobian at `z` times `L` is the Jacobian in
    the chart: no solve is differentiated again. `L` is the pseudo-inverse of `retract`'s
    Jacobian (its null space: the moves `retract` takes back) applied to the chart's."""
    z_flat, unravel = ravel_pytree(z)
    retract = lambda flat: ravel_pytree(space.retract(*unravel(flat)))[0]
    chart = _chart_at(space, to_linear, space.retract(*z))
    size = _tangent_size(space, jtu.tree_map(lambda x: x[None, None], z))
    moves = jax.jacfwd(lambda w: retract(ravel_pytree(chart(w))[0]))(jnp.zeros((2, size)))
    return jnp.linalg.pinv(jax.jacfwd(retract)(z_flat)) @ moves.reshape(z_flat.size, -1)


def _half_sum_squares(residual) -> Array:
    """The loss `1/2 sum r^2` of a pytree of residuals."""
    return 0.5 * jnp.sum(ravel_pytree(residual)[0] ** 2)


def _linearize(residuals, unknowns, f_info, dof, to_linear):
    """The Jacobian, the parameters' covariance, `s^2` and the loss, as `FitResult`
    describes them, from the solver's own last linearization at its solution: its
    residuals, its parameters' columns, and its states' columns (multiple shooting) taken
    into the tangent chart by `_lift_at`. So `fit` compiles one Jacobian of the solves, not
    two (the first call of the test of `fit` through `LieRK`: 24 s against 35 s)."""
    u, z = unknowns
    u_flat, unravel_u = ravel_pytree(u)
    ravel = lambda tree: ravel_pytree(tree)[0]
    no_dz = jtu.tree_map(jnp.zeros_like, z)
    columns = [jax.jacfwd(lambda x: ravel(f_info.jac.mv((unravel_u(x), no_dz))))(u_flat)]
    if z is not None:
        lift = over_states(lambda *state: _lift_at(residuals.space, to_linear, state))(*z)
        unravel_z = ravel_pytree(jtu.tree_map(lambda x: x[0, 0], z))[1]
        move = over_states(lambda lift, w: unravel_z(lift @ w))
        no_du = jtu.tree_map(jnp.zeros_like, u)
        w0 = jnp.zeros(lift.shape[:2] + lift.shape[-1:], lift.dtype)
        states_columns = lambda w: ravel(f_info.jac.mv((no_du, move(lift, w.reshape(w0.shape)))))
        columns.append(jax.jacfwd(states_columns)(w0.reshape(-1)))
    jacobian = jnp.concatenate(columns, axis=1)
    loss = _half_sum_squares(f_info.residual)
    residual_variance = 2 * loss / dof if dof > 0 else jnp.full_like(loss, jnp.nan)
    covariance = residual_variance * _parameter_covariance(jacobian, u_flat.size)
    return loss, (jacobian, covariance, residual_variance)


def _parameter_covariance(jacobian, p: int):
    """The first `p` rows and columns of `(J^T J)^+`, from the SVD `R = U S V^T` of `J = QR`
    (not squaring J's condition number), singular values below `s_max eps max(J.shape)`
    dropped as numpy's `matrix_rank` and scipy's `curve_fit` drop them. A parameter the
    dropped directions move (by more than `sqrt(eps)`) is not identified: its variance is
    `inf`, its covariances NaN; the others' are those of the identified directions, as
    if the unidentified parameters were held fixed."""
    rows = max(jacobian.shape[1] - jacobian.shape[0], 0)  # a wide J gets zero rows
    r = jnp.linalg.qr(jnp.pad(jacobian, ((0, rows), (0, 0))), mode="r")
    _, s, vt = jnp.linalg.svd(r)
    eps = jnp.finfo(r.dtype).eps
    kept = s > s[0] * eps * max(jacobian.shape)
    v = vt.T[:p]
    inverse = jnp.where(kept, 1 / jnp.where(kept, s, 1) ** 2, 0)
    free = jnp.sum(jnp.where(kept, 0, v**2), axis=1) > eps
    covariance = jnp.where(free[:, None] | free[None], jnp.nan, (v * inverse) @ v.T)
    return jnp.where(jnp.diag(free), jnp.inf, covariance)


def _stderr(covariance, u, positive):
    """Standard errors in the structure of `u`, mapped from log space for `positive`."""
    u_flat, unravel_u = ravel_pytree(u)
    se = unravel_u(jnp.sqrt(jnp.diag(covariance)).astype(u_flat.dtype))
    fitted = zip(jtu.tree_leaves(se), jtu.tree_leaves(u), positive, strict=True)
    leaves = [jnp.exp(x) * s if f else s for s, x, f in fitted]
    return jtu.tree_unflatten(jtu.tree_structure(se), leaves)


class _FitSolver(optx.AbstractLeastSquaresSolver):
    """A Gauss-Newton-type `solver` with two additions for `fit`.

    It keeps the loss at its first step: the residuals at the initial guess (optimistix's
    searches accept the first step). So `initial_loss` comes from the loop's own
    evaluation, not from one more solve in the program: the fit of notebook 08 (suite
    compile settings, this 2-core CPU, two runs each, taking turns) compiled in 19.0 to
    19.6 s against 30.7 to 37.0 s, its first call took 36 to 38 s against 51 to 56 s.

    It also stops where the solver can no longer move: after a rejected step, when the
    next step it proposes (its trust region shrunk) is within the tolerance on `y`,
    `|step| < atol + rtol |y|` (MINPACK's `xtol` test). At the minimum of residuals that
    come from adaptive solves, whose error (`simulate`'s `rtol`) exceeds the changes a
    step still predicts, every step is rejected: the Cauchy test (on an accepted step)
    never holds, and the fit ran to `max_steps` with the minimum found (one noise seed in
    60 in `test_fit_standard_errors_cover_the_truth`: 9 steps accepted, 91 rejected)."""

    solver: optx.AbstractGaussNewton

    @property
    def rtol(self):
        return self.solver.rtol

    @property
    def atol(self):
        return self.solver.atol

    @property
    def norm(self):
        return self.solver.norm

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        state = self.solver.init(fn, y, args, options, f_struct, aux_struct, tags)
        return state, jnp.zeros((), jnp.result_type(*jtu.tree_leaves(f_struct)))

    def step(self, fn, y, args, options, state, tags):
        inner, initial_loss = state
        y, new, aux = self.solver.step(fn, y, args, options, inner, tags)
        loss = _half_sum_squares(new.f_info.residual)
        return y, (new, jnp.where(inner.first_step, loss, initial_loss)), aux

    def terminate(self, fn, y, args, options, state, tags):
        inner = state[0]
        terminate, result = self.solver.terminate(fn, y, args, options, inner, tags)
        scaled = jtu.tree_map(
            lambda new, old: jnp.abs(new - old) / (self.atol + self.rtol * jnp.abs(old)),
            inner.y_eval,
            y,
        )
        stalled = (inner.num_steps_since_acceptance > 0) & (self.norm(scaled) < 1)
        return terminate | stalled, result

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.solver.postprocess(fn, y, aux, args, options, state[0], tags, result)


@eqx.filter_jit
def _solve(residuals, solver, unknowns0, data, max_steps, dof, to_linear):
    solver = _FitSolver(solver)
    sol = optx.least_squares(
        residuals, solver, unknowns0, data, {"jac": "fwd"}, max_steps=max_steps, throw=False
    )
    state, initial_loss = sol.state
    loss, linear = _linearize(residuals, sol.value, state.f_info, dof, to_linear)
    return sol.value, loss, initial_loss, sol.stats["num_steps"], sol.result, linear


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
    solver: optx.AbstractGaussNewton | None = None,
    max_steps: int = 100,
    jac: str = "fwd",
    adjoint: diffrax.AbstractAdjoint | None = None,
    simulate_options: dict | None = None,
    devices=None,
) -> FitResult:
    """Fit parameters of a system to observed trajectories by least squares through
    `simulate`: minimizes `1/2 sum_{b, j} |observe(system, t_j, q_bj, v_bj) -
    observations_bj|^2` (plus continuity penalties with multiple shooting) with
    `optimistix.least_squares`.

    **Arguments:**
    - `model`: `model(params) -> system` or `(system, args)`; any sphere_mech system.
    - `params0`: initial parameters, any pytree (dict, equinox Module such as an
      `eqx.nn.MLP`, ...); its floating-point array leaves are fitted, the others kept.
    - `ts`: increasing observation times `(T,)` (or `(B, T)`, one row per record); the
      simulation starts at `ts[0]`.
    - `observations`: `(T, ...)`, or `(B, T, ...)` for a batch of `B` records, finite
      (checked before any solve, as `y0` is, the way `simulate_batch` checks initial
      states: a `ValueError` naming the record and observation).
    - `observe`: `observe(system, t, q, v) -> array` of the shape of one observation
      (e.g. the tip position), of one state (dicts on a mixed space).
    - `y0`: initial state `(q0, v0)` at `ts[0]`, `(n, 3)` arrays, or `(B, n, 3)` for a
      batch of records (on a mixed space, dicts of arrays, such as `{"cart": (1,), "bob":
      (1, 3)}`, with a leading axis `B` on every array for a batch).
    - `segments`: number of shooting segments `K` (1: single shooting). Each segment
      after the first starts from its own state (the space's `retract` of an ambient
      `(a, b)`, fitted too), tied to the previous one's end by a penalty
      `continuity * |y_end(k) - y_start(k + 1)|^2`.
    - `segment_states`: initial guesses `(q, v)` for the starts of segments 2..K, leading
      axes `([B,] K - 1)`; default: a simulation of `model(params0)` from `y0`.
    - `fit_initial_state`: also fit `y0` (taken then as the initial guess).
    - `positive`: `True`, or a pytree of bools matching `params0`: those parameters
      (`> 0` in `params0`) are fitted as `log(p)`, so they stay positive.
    - `continuity`: weight (finite, > 0) of the continuity penalties.
    - `solver`: an optimistix Gauss-Newton-type least-squares solver
      (`optx.AbstractGaussNewton`: `GaussNewton`, `LevenbergMarquardt`,
      `IndirectLevenbergMarquardt`, `Dogleg`); default `optx.LevenbergMarquardt(rtol=1e-6,
      atol=1e-9)`. Its last linearization gives `jacobian` and the covariance.
    - `max_steps`: maximum number of solver iterations.
    - `jac`: each segment's Jacobian (in the parameters and its initial state) by
      `"fwd"` (default: `jax.jacfwd`, `diffrax.ForwardMode()`) or `"bwd"` (`jax.jacrev`,
      `diffrax.RecursiveCheckpointAdjoint()`). Forward mode is faster whenever a segment
      has fewer unknowns than residuals (5.7x in `benchmarks/fit_adjoint.py`).
    - `adjoint`: override the diffrax adjoint chosen from `jac`.
    - `simulate_options`: keyword arguments for `simulate` (`solver`, `rtol`, `atol`,
      `dt0`, `stepsize_controller`, `max_steps`).
    - `devices`: devices to split the `B K` segment solves over, as `simulate_batch` does
      (default: all of JAX's default backend, of every process after
      `jax.distributed.initialize`; at most one per segment); the fit is that of one
      device (docs/distributed.md). Every process passes the same arguments. On several
      devices `jac` must be `"fwd"`.

    **Returns:** a `FitResult` with the uncertainties of the fit. Failures of the solve
    (e.g. `max_steps` reached) are reported in `result` and `converged`, never raised.
    """
    if jac not in ("fwd", "bwd"):
        raise ValueError(f"jac must be 'fwd' or 'bwd', got {jac!r}.")
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9) if solver is None else solver
    if not isinstance(solver, optx.AbstractGaussNewton):
        raise TypeError(
            "fit: solver must be a Gauss-Newton-type optimistix solver (optx.GaussNewton, "
            "LevenbergMarquardt, IndirectLevenbergMarquardt, Dogleg): the Jacobian and the "
            f"covariance are its last linearization; got {type(solver).__name__}."
        )
    check_integer(max_steps, "max_steps")
    check_positive(continuity, "continuity")
    sim = own_options(simulate_options, "fit", ts)
    default = diffrax.ForwardMode() if jac == "fwd" else diffrax.RecursiveCheckpointAdjoint()
    sim["adjoint"] = default if adjoint is None else adjoint
    params0 = as_arrays(params0)
    for path, x in jtu.tree_flatten_with_path(eqx.filter(params0, eqx.is_inexact_array))[0]:
        value = None if isinstance(x, jax.core.Tracer) else gathered(x)
        if value is not None and not np.all(np.isfinite(value)):
            raise ValueError(f"fit: params0{jtu.keystr(path)} is not finite: {value}.")
    flags = _positive_flags(params0, positive)
    dynamic, static = eqx.partition(params0, eqx.is_inexact_array)
    system0, args0 = model_output(model, params0)
    space = system0.state_space
    ts, observations, y0, batched = _as_batch(space, ts, observations, y0)
    check_data(system0, ts, y0, observations, "fit", "record")
    segment_data = split_segments(ts, observations, segments)
    _check_observe(observe, system0, ts, observations, y0)
    z0 = _initial_unknown_states(
        segment_states, system0, args0, segment_data[2], y0, fit_initial_state, batched, sim
    )
    devices = batch_devices(devices, segment_data[2].size)
    mesh = batch_mesh(devices)
    if mesh is not None and jac == "bwd":
        raise ValueError(
            "fit: jac='bwd' (reverse mode) fails through a solve split over several devices "
            "(diffrax #765); use jac='fwd' (default) or devices=jax.devices()[:1]."
        )
    unknowns0 = (map_flagged(jnp.log, dynamic, flags), z0)
    residuals = Residuals(
        model,
        space,
        observe,
        flags,
        static,
        fit_initial_state,
        jnp.asarray(continuity),
        sim,
        jtu.tree_map(jnp.result_type, unknowns0),
        jac,
        mesh,
    )
    dof = _degrees_of_freedom(space, observations, unknowns0, segments)
    # the least squares in JAX's default float (`Residuals.own`)
    wide = jax.dtypes.canonicalize_dtype(jnp.float64)
    wide_unknowns0 = jtu.tree_map(lambda x: x.astype(jnp.promote_types(x.dtype, wide)), unknowns0)
    with one_device(devices):
        unknowns, loss, initial_loss, num_steps, result, linear = _solve(
            residuals, solver, wide_unknowns0, (segment_data, y0), max_steps, dof, system0.to_linear
        )
    u, z = residuals.own(unknowns)
    jacobian, covariance, variance = linear
    states = jtu.tree_map(lambda s: s if batched else s[0], residuals.states(z, y0))
    converged = result == optx.RESULTS.successful
    fitted = (residuals.params(u), loss, initial_loss, num_steps, converged, states, result)
    return FitResult(*fitted, jacobian, covariance, _stderr(covariance, u, flags), variance, dof)
