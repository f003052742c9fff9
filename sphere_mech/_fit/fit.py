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
import optimistix as optx
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, PyTree

from .._misc import as_arrays, tree_add, tree_dtype
from .._simulate import simulate
from .._solve import state_pair
from .._spaces import AbstractSpace
from .shooting import Residuals, map_flagged, model_output, over_states, split_segments


class FitResult(eqx.Module):
    """What `fit` returns.

    **Attributes:**
    - `params`: the fitted parameters, same structure as `params0`.
    - `loss`: the loss `1/2 sum r^2` (observation and continuity residuals) at the
      solution.
    - `initial_loss`: the same loss at `params0` and the initial segment states.
    - `num_steps`: number of iterations of the least-squares solver.
    - `converged`: whether the solver met its tolerances within `max_steps`
      (`result == optimistix.RESULTS.successful`).
    - `segment_states`: the fitted initial states `(q, v)` of the shooting segments,
      with leading axes `([B,] K)`: `([B,] K, n, 3)` arrays on (S^2)^n, dicts of them on
      a mixed space (segment 0 is `y0` unless `fit_initial_state=True`).
    - `result`: the `optimistix.RESULTS` code of the least-squares solve.

    Uncertainties, by linearizing the residuals at the solution (Gauss-Newton, as
    `scipy.optimize.least_squares` and lmfit report them):
    - `jacobian`: `(m_rows, p)`, the Jacobian of the residuals at the solution. Rows: the
      raveled residuals (observation residuals `(B, K, W, ...)`, zero on the padding of
      segments that own fewer than `W` observations, then the weighted continuity jumps
      of `q` and of `v`, `(B, K - 1, n, 3)` each on (S^2)^n, raveled leaf by leaf on a
      mixed space). Columns: the fitted parameters as fitted (the floating-point leaves
      of `params`, raveled in `tree_leaves` order by `jax.flatten_util.ravel_pytree`;
      `log(p)` for parameters flagged `positive`), then the fitted segment states,
      `(B, K', 2, d)` raveled: the `d` tangent coordinates of `dq`, then of `dv`, in the
      space's tangent basis at `q` (on (S^2)^n, `d = 2n`, two per sphere in the basis
      `sm.tangent_basis(q)` of its plane; on a mixed space, the factors' coordinates in
      the space's key order, a Euclidean factor's are its components).
    - `covariance`: `(p_params, p_params)`, the covariance of the fitted parameters (same
      order and space as the first columns of `jacobian`): the parameter block of
      `residual_variance * (J^T J)^{-1}`, i.e. with the segment states marginalized out.
      NaN or huge where the parameters are not identifiable from the data.
    - `stderr`: standard errors in the structure of `params` (`None` at leaves that are
      not fitted), in the parameters' own units: for `positive` ones by the delta method,
      `se(p) = p * se(log p)`.
    - `residual_variance`: `s^2 = |r|^2 / dof`, the estimated noise variance.
    - `dof`: the degrees of freedom `m - p`. `m` counts the observation residuals and,
      per continuity junction, `2d` (to first order the jumps of `(q, v)` lie in the
      `2d`-dimensional tangent space of the tangent bundle; `2d = 4n` on (S^2)^n); `p`
      counts the fitted parameters and `2d` per fitted segment state. So `dof` is the
      number of observed values minus the number of parameters (minus `2d` per record
      with `fit_initial_state`), as for single shooting.

    These assume independent Gaussian noise of one variance on every observed value and a
    model that is close to linear in the unknowns over the size of the errors; the
    continuity penalties count as residuals of the same variance (with a large
    `continuity` weight this tends to the single-shooting covariance). Weight the
    observations (e.g. divide by their noise level in `observe` and `observations`) if
    their noise levels differ.
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
    """Bring `ts`, `observations`, `y0` to a leading batch axis of records; check shapes
    (those of one state by the system's `space`)."""
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
    out = eqx.filter_eval_shape(observe, system, ts[0, 0], *jtu.tree_map(lambda y: y[0], y0))
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
    q = jtu.tree_map(lambda x, x0: jnp.where(jnp.isfinite(x), x, x0[:, None]), q, y0[0])
    return q, jtu.tree_map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), v)


def _initial_unknown_states(guess, system, args, segment_t0, y0, fit_initial_state, batched, sim):
    """`z0`: the starts of segments 2..K (and of segment 1 with `fit_initial_state`)."""
    num_segments = segment_t0.shape[1]
    if guess is None:
        guess = _guess_states(system, args, segment_t0, y0, sim) if num_segments > 1 else None
    else:
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
    if not fit_initial_state:
        return guess
    first = jtu.tree_map(lambda y: y[:, None], y0)
    if guess is None:
        return first
    return jtu.tree_map(lambda a, b: jnp.concatenate([a, b], 1), first, guess)


def _tangent_size(space: AbstractSpace, state_tree):
    """`d`, the number of tangent coordinates of one point (`2n` on (S^2)^n), from the
    first of a tree of states with leading axes `(B, K)` (shapes only)."""
    q = jtu.tree_map(lambda x: x[0, 0], state_tree)
    return jax.eval_shape(lambda q: space.to_tangent(space.tangent_basis(q), q), q).shape[0]


def _degrees_of_freedom(space, observations, unknowns0, segments):
    """`m - p`: observed values (and `2d` per continuity junction) minus the parameters
    (and `2d` per fitted segment state); see `FitResult`."""
    u, z = unknowns0
    num_params = ravel_pytree(u)[0].size
    if z is None:
        return observations.size - num_params
    num_records, num_states = jtu.tree_leaves(z[0])[0].shape[:2]
    junctions = num_records * (segments - 1)
    size = 2 * _tangent_size(space, z[0])
    return observations.size + size * (junctions - num_records * num_states) - num_params


def _tangent_chart(space: AbstractSpace, z):
    """The fitted segment states as a function of tangent coordinates `w` `(B, K, 2, d)`
    (`dq`, `dv` in the space's tangent basis at `q`) around the retracted states, `w = 0`
    there."""
    if z is None:
        return jnp.zeros((0,)), lambda w: None
    q, v = over_states(space.retract)(*z)
    basis = over_states(space.tangent_basis)(q)
    move = over_states(lambda T, x, dx: tree_add(x, space.from_tangent(T, dx)))
    chart = lambda w: (move(basis, q, w[..., 0, :]), move(basis, v, w[..., 1, :]))
    shape = jtu.tree_leaves(q)[0].shape[:2] + (2, _tangent_size(space, q))
    return jnp.zeros(shape, tree_dtype(q)), chart


def _linearize(residuals, unknowns, data, loss, dof):
    """The Jacobian of the residuals at `unknowns` (columns: the parameters as fitted, then
    the tangent coordinates of the segment states), the parameters' covariance and `s^2`.

    `jax.jacfwd` goes through the per-segment custom JVP of `Residuals`, so each segment's
    Jacobian is built once."""
    u, z = unknowns
    u_flat, unravel_u = ravel_pytree(u)
    w0, chart = _tangent_chart(residuals.space, z)
    w_flat, unravel_w = ravel_pytree(w0)

    def flat_residuals(x):
        u_, w_ = unravel_u(x[: u_flat.size]), unravel_w(x[u_flat.size :])
        return ravel_pytree(residuals((u_, chart(w_)), data))[0]

    jacobian = jax.jacfwd(flat_residuals)(jnp.concatenate([u_flat, w_flat]))
    # (J^T J)^{-1} = R^{-1} R^{-T} from J = QR, without squaring J's condition number
    # (zero rows added if J is wide: R is then singular and the covariance not finite)
    rows = max(jacobian.shape[1] - jacobian.shape[0], 0)
    r = jnp.linalg.qr(jnp.pad(jacobian, ((0, rows), (0, 0))), mode="r")
    r_inv = jax.scipy.linalg.solve_triangular(r, jnp.eye(r.shape[1], dtype=r.dtype), lower=False)
    residual_variance = 2 * loss / dof if dof > 0 else jnp.full_like(loss, jnp.nan)
    r_params = r_inv[: u_flat.size]
    return jacobian, residual_variance * (r_params @ r_params.T), residual_variance


def _stderr(covariance, u, positive):
    """Standard errors in the structure of `u`, mapped from log space for `positive`."""
    u_flat, unravel_u = ravel_pytree(u)
    se = unravel_u(jnp.sqrt(jnp.diag(covariance)).astype(u_flat.dtype))
    leaves, treedef = jtu.tree_flatten(se)
    fitted = jtu.tree_leaves(u)
    leaves = [jnp.exp(x) * s if f else s for s, x, f in zip(leaves, fitted, positive, strict=True)]
    return jtu.tree_unflatten(treedef, leaves)


@eqx.filter_jit
def _solve(residuals, solver, unknowns0, data, max_steps, dof):
    sol = optx.least_squares(
        residuals, solver, unknowns0, data, {"jac": "fwd"}, max_steps=max_steps, throw=False
    )
    # the losses at the solution and at the start (`lax.map`: the residuals compiled once)
    both = jtu.tree_map(lambda a, b: jnp.stack([a, b]), sol.value, unknowns0)
    r = jax.lax.map(lambda y: residuals(y, data), both)
    loss, initial_loss = 0.5 * sum(
        jnp.sum(x**2, axis=tuple(range(1, x.ndim))) for x in jtu.tree_leaves(r)
    )
    linear = _linearize(residuals, sol.value, data, loss, dof)
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
    - `model`: `model(params) -> system` or `(system, args)`; any sphere_mech system,
      on (S^2)^n or on a mixed space (`space=`, states dicts of arrays).
    - `params0`: initial parameters, any pytree (dict, tuple, equinox Module such as an
      `eqx.nn.MLP`); its floating-point array leaves are fitted, other leaves kept.
    - `ts`: observation times `(T,)` (or `(B, T)`, one row per record), increasing;
      the simulation starts at `ts[0]`.
    - `observations`: `(T, ...)`, or `(B, T, ...)` for a batch of `B` records.
    - `observe`: `observe(system, t, q, v) -> array` of the shape of one observation
      (e.g. the tip position); `q`, `v` are one state (dicts on a mixed space).
    - `y0`: initial state `(q0, v0)` at `ts[0]`, `(n, 3)` arrays, or `(B, n, 3)` for a
      batch of records (the batch is given by `y0`); on a mixed space, dicts of arrays
      (`{"cart": (1,), "bob": (1, 3)}`), with a leading axis `B` on every array for a
      batch.
    - `segments`: number of shooting segments `K` (1: single shooting). Each segment
      after the first starts from its own state, fitted as an extra unknown and kept
      on the tangent bundle by the space's `retract` of an ambient `(a, b)`; a penalty
      `continuity * |y_end(k) - y_start(k + 1)|^2` ties the segments together.
    - `segment_states`: initial guesses `(q, v)` for the starts of segments 2..K,
      `([B,] K - 1, n, 3)` (dicts of arrays with leading axes `([B,] K - 1)` on a mixed
      space; e.g. estimated from the data); default: a simulation of
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

    **Returns:** a `FitResult`, with the uncertainties of the fit (the Jacobian at the
    solution, the Gauss-Newton covariance and standard errors; see `FitResult` for what
    they assume). Failures of the solve (e.g. `max_steps` reached) are reported in
    `result` and `converged`, never raised.
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
    params0 = as_arrays(params0)
    flags = _positive_flags(params0, positive)
    dynamic, static = eqx.partition(params0, eqx.is_inexact_array)
    system0, args0 = model_output(model, params0)
    ts, observations, y0, batched = _as_batch(system0.space, ts, observations, y0)
    segment_data = split_segments(ts, observations, segments)
    _check_observe(observe, system0, ts, observations, y0)
    z0 = _initial_unknown_states(
        segment_states, system0, args0, segment_data[2], y0, fit_initial_state, batched, sim
    )
    residuals = Residuals(
        model,
        system0.space,
        observe,
        flags,
        static,
        fit_initial_state,
        jnp.asarray(continuity),
        sim,
        jac,
    )
    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9) if solver is None else solver
    unknowns0 = (map_flagged(jnp.log, dynamic, flags), z0)
    dof = _degrees_of_freedom(system0.space, observations, unknowns0, segments)
    (u, z), loss, initial_loss, num_steps, result, linear = _solve(
        residuals, solver, unknowns0, (segment_data, y0), max_steps, dof
    )
    jacobian, covariance, residual_variance = linear
    states = residuals.states(z, y0)
    if not batched:
        states = jtu.tree_map(lambda s: s[0], states)
    converged = result == optx.RESULTS.successful
    fitted = (residuals.params(u), loss, initial_loss, num_steps, converged, states, result)
    stderr = _stderr(covariance, u, flags)
    return FitResult(*fitted, jacobian, covariance, stderr, residual_variance, dof)
