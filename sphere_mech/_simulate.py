"""`simulate`: integrate any system on (S^2)^n with diffrax."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from ._checks import check_shapes, check_state
from ._geometry import retract
from ._solvers.projected import Projected
from ._system import AbstractSystem

DEFAULT_MAX_STEPS = 100_000
DEFAULT_TOLERANCES = {np.dtype("float64"): (1e-8, 1e-10), np.dtype("float32"): (1e-5, 1e-6)}
"""Default `(rtol, atol)` of the adaptive step-size controller, by dtype of `q`."""

_RESULTS = diffrax.RESULTS
_NEWTON_FAILURES = (
    _RESULTS.nonlinear_max_steps_reached,
    _RESULTS.nonlinear_divergence,
    _RESULTS.singular,
)


def default_solver() -> diffrax.AbstractSolver:
    """The solver `simulate` uses when none is given: `Projected(diffrax.Tsit5())`."""
    return Projected(diffrax.Tsit5())


def _vector_field(t, y, system_and_args):
    system, args = system_and_args
    return system.rates(t, y, args)


def initial_state(system: AbstractSystem, y0):
    """Check an initial state `(q0, v0)` and put it exactly on the tangent bundle.

    States within `unit_tolerance(dtype)` of the spheres (and of tangency) are accepted
    and corrected (`q_i / |q_i|`, normal part of `v_i` removed); farther ones raise."""
    if not (isinstance(y0, tuple | list) and len(y0) == 2):
        raise ValueError("y0 must be a pair (q0, v0) of (n, 3) arrays.")
    q0, v0 = (jnp.asarray(x) for x in y0)
    check_shapes(q0, v0, system.state_name)
    dtype = jnp.result_type(q0, v0)  # one floating dtype for the whole state
    q0, v0 = q0.astype(dtype), v0.astype(dtype)
    q0, v0 = retract(*check_state(q0, v0, system.state_name))
    return q0, v0


def _check_rates(system, t0, y0, args):
    """Tie to `q0` a run-time check that the vector field is finite at the initial state."""
    rates = system.rates(t0, y0, args)
    finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(r)) for r in rates]))
    message = (
        "the equations of motion are not finite at the initial state: singular reduced "
        "mass matrix (degenerate Lagrangian, e.g. a zero mass or length) or NaN parameters"
    )
    return eqx.error_if(y0[0], ~finite, message), y0[1]


def _controller(solver, stepsize_controller, rtol, atol, dt0, dtype):
    if stepsize_controller is not None:
        if rtol is not None or atol is not None:
            raise ValueError("Give rtol/atol either to simulate or to stepsize_controller, "
                             "not both.")
        controller = stepsize_controller
    elif isinstance(solver, diffrax.AbstractAdaptiveSolver):
        default_rtol, default_atol = DEFAULT_TOLERANCES.get(np.dtype(dtype), (1e-5, 1e-6))
        controller = diffrax.PIDController(
            rtol=default_rtol if rtol is None else rtol,
            atol=default_atol if atol is None else atol,
        )
    else:
        if rtol is not None or atol is not None:
            raise ValueError(
                f"{type(solver).__name__} has no error estimate, so it takes fixed steps "
                "(dt0) and rtol/atol would be ignored: drop them, or use an adaptive "
                "solver such as Projected(diffrax.Tsit5()) or LieRK4()."
            )
        controller = diffrax.ConstantStepSize()
    adaptive = isinstance(controller, diffrax.AbstractAdaptiveStepSizeController)
    if adaptive and not isinstance(solver, diffrax.AbstractAdaptiveSolver):
        raise ValueError(
            f"{type(solver).__name__} has no error estimate and cannot be used with the "
            f"adaptive {type(controller).__name__}: use diffrax.ConstantStepSize() with a "
            "dt0, or an adaptive solver (Projected(diffrax.Tsit5()), LieRK4(), ...)."
        )
    if isinstance(controller, diffrax.ConstantStepSize) and dt0 is None:
        raise ValueError(
            f"{type(solver).__name__} with fixed steps needs a step size: pass dt0=..."
        )
    return controller


@eqx.filter_jit
def _solve(system, y0, t0, t1, args, solver, dt0, controller, saveat, max_steps, meter,
           adjoint):
    y0 = _check_rates(system, t0, y0, args)
    return diffrax.diffeqsolve(
        diffrax.ODETerm(_vector_field),
        solver,
        t0,
        t1,
        dt0,
        y0,
        args=(system, args),
        saveat=saveat,
        stepsize_controller=controller,
        max_steps=max_steps,
        progress_meter=meter,
        adjoint=adjoint,
        throw=False,
    )


def simulate(
    system: AbstractSystem,
    y0,
    t1,
    *,
    t0=0.0,
    args=None,
    solver: diffrax.AbstractSolver | None = None,
    dt0=None,
    rtol=None,
    atol=None,
    stepsize_controller: diffrax.AbstractStepSizeController | None = None,
    saveat: diffrax.SaveAt | None = None,
    max_steps: int | None = DEFAULT_MAX_STEPS,
    progress: bool = False,
    adjoint: diffrax.AbstractAdjoint | None = None,
    throw: bool = True,
) -> diffrax.Solution:
    """Integrate `system` from `y0 = (q0, v0)` at `t0` to `t1`.

    **Arguments:**
    - `system`: any sphere_mech system (`Lagrangian`, `AngularLagrangian`, `Hamiltonian`,
      `AngularHamiltonian`, `ChainPendulum`, a scene, ...).
    - `y0`: `(q0, v0)`, `(n, 3)` arrays; `v0` is the system's second state variable.
      A state within `unit_tolerance(dtype)` of the tangent bundle is normalized;
      farther ones raise.
    - `t1`, `t0`: end and start times (any floats or scalar arrays; changing their values
      does not recompile).
    - `solver`: any diffrax solver; default `Projected(diffrax.Tsit5())`. Solvers that do
      not keep `|q_i| = 1` themselves should be wrapped in `Projected`; `LieRK4()` keeps
      it by construction.
    - `dt0`: initial (adaptive) or fixed step size; required for fixed-step solvers.
    - `rtol`, `atol`: tolerances of the default `diffrax.PIDController`; defaults
      `1e-8, 1e-10` in float64 and `1e-5, 1e-6` in float32.
    - `stepsize_controller`: any diffrax controller instead (e.g.
      `diffrax.ConstantStepSize()` with `dt0`); fixed-step solvers (`RK4`,
      `Projected(RK4())`, ...) get `ConstantStepSize` automatically.
    - `saveat`: a `diffrax.SaveAt`; default: the final state only. Saved states are put
      back on the tangent bundle (dense output between steps is a polynomial that
      leaves the spheres by the local error).
    - `max_steps`: maximum number of steps (default 100 000).
    - `progress`: show a tqdm progress bar (diffrax's `TqdmProgressMeter`).
    - `adjoint`: a diffrax adjoint for gradients (default: checkpointed reverse mode).
    - `throw`: raise on failure (default). The error names the cause: `max_steps`
      reached, Newton iterations of an implicit solver not converging, or a state that
      became NaN. With `throw=False` nothing is raised: `sol.result` holds the
      `diffrax.RESULTS` code (`RESULTS.nonfinite` for NaN) and `sol.ys` the
      trajectory up to the failure (later `SaveAt(ts=...)` entries are `inf`).

    **Returns:** a `diffrax.Solution` whose `ys` is `(q, v)` with a leading time axis.
    """
    y0 = initial_state(system, y0)
    solver = default_solver() if solver is None else solver
    controller = _controller(solver, stepsize_controller, rtol, atol, dt0, y0[0].dtype)
    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()
    saveat = diffrax.SaveAt(t1=True) if saveat is None else saveat
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    dtype = y0[0].dtype
    t0, t1 = _as_time(t0, dtype), _as_time(t1, dtype)
    dt0 = None if dt0 is None else _as_time(dt0, dtype)
    sol = _solve(system, y0, t0, t1, args, solver, dt0, controller, saveat, max_steps,
                 meter, adjoint)
    sol = _flag_nonfinite(sol)
    if throw:
        sol = _raise_on_failure(sol, max_steps)
    return _retract_saved(sol, saveat)


def _as_time(t, dtype):
    """Times as arrays of the state's dtype, so that a new value of `t0`, `t1` or `dt0`
    does not trigger a new compilation (and float64 times do not promote a float32
    state)."""
    return jnp.asarray(t, dtype=dtype)


def _flag_nonfinite(sol: diffrax.Solution) -> diffrax.Solution:
    """A run that stepped into NaN without any solver noticing (fixed steps of a solver
    that does not check) is reported as `RESULTS.nonfinite`. Unreached save times are
    `inf` in diffrax, never NaN, so only NaN is looked for."""
    has_nan = jnp.array(False)
    for leaf in jtu.tree_leaves(sol.ys):
        has_nan = has_nan | jnp.any(jnp.isnan(leaf))
    ok = sol.result == _RESULTS.successful
    result = _RESULTS.where(ok & has_nan, _RESULTS.nonfinite, sol.result)
    return eqx.tree_at(lambda s: s.result, sol, result)


def _failure_messages(max_steps):
    hint = "; pass throw=False to get sol.result and the trajectory up to the failure"
    return [
        "",
        f"simulate: the solver took max_steps={max_steps} steps without reaching t1. "
        "Increase max_steps or loosen rtol/atol; if most steps were rejected "
        "(sol.stats['num_rejected_steps'] with throw=False) the step size collapsed, which "
        "happens when the vector field is NaN or singular near the state reached" + hint,
        "simulate: the Newton iterations of the implicit solver did not converge (or met a "
        "singular Jacobian) in a fixed step. Use a smaller dt0, an adaptive step-size "
        "controller (it retries a failed step with a smaller one), or a root finder with "
        "more iterations" + hint,
        "simulate: the state became NaN (the step diverged or the vector field is not "
        "defined there: a singular mass matrix, NaN parameters or forces). Use a smaller "
        "dt0 or an adaptive step-size controller" + hint,
        "simulate: the solver failed (see diffrax.RESULTS for the code in sol.result)" + hint,
    ]


def _failure_index(result):
    index = jnp.where(result == _RESULTS.successful, 0, 4)
    index = jnp.where(result == _RESULTS.max_steps_reached, 1, index)
    for code in _NEWTON_FAILURES:
        index = jnp.where(result == code, 2, index)
    return jnp.where(result == _RESULTS.nonfinite, 3, index)


def _raise_on_failure(sol: diffrax.Solution, max_steps) -> diffrax.Solution:
    """Raise a clear error when the run failed: a Python `RuntimeError` (with the time
    reached and step counts) when called eagerly, an `eqx.branched_error_if` check when
    traced (inside `jax.jit`, `jax.vmap`, `jax.grad`)."""
    index = _failure_index(sol.result)
    messages = _failure_messages(max_steps)
    if isinstance(index, jax.core.Tracer):
        ys = eqx.branched_error_if(sol.ys, index > 0, index, messages)
        return eqx.tree_at(lambda s: s.ys, sol, ys, is_leaf=lambda x: x is None)
    index = int(index)
    if index == 0:
        return sol
    # With `SaveAt(subs=[...])`, `sol.ts` is a list of arrays of different lengths.
    ts = [np.ravel(np.asarray(t)) for t in jtu.tree_leaves(sol.ts)]
    ts = np.concatenate(ts) if ts else np.zeros(0)
    reached = ts[np.isfinite(ts)]
    where = f" Last saved time: t = {reached.max():.6g}." if reached.size else ""
    stats = {k: int(sol.stats[k]) for k in ("num_steps", "num_accepted_steps",
                                           "num_rejected_steps") if k in sol.stats}
    detail = f" diffrax: {_RESULTS[sol.result]!r}. Steps: {stats}." if index == 4 else (
        f" Steps: {stats}.")
    raise RuntimeError(messages[index] + "." + where + detail)


_DEFAULT_SAVE_FN = diffrax.SubSaveAt(t1=True).fn


def _retract_saved(sol: diffrax.Solution, saveat: diffrax.SaveAt) -> diffrax.Solution:
    """Dense output between steps (`SaveAt(ts=...)`) is a polynomial that leaves the
    spheres by the local error: put saved states back on the tangent bundle. Only
    states saved by diffrax's default `fn` are touched, and only finite entries (diffrax
    pads unreached save times with `inf`)."""
    subs, ys = saveat.subs, sol.ys
    if isinstance(subs, diffrax.SubSaveAt):
        ys = _retract_if_state(subs, ys)
    elif isinstance(subs, list | tuple) and isinstance(ys, list | tuple):
        ys = type(ys)(_retract_if_state(s, y) for s, y in zip(subs, ys, strict=True))
    return eqx.tree_at(lambda s: s.ys, sol, ys, is_leaf=lambda x: x is None)


def _retract_if_state(sub, ys):
    if not (isinstance(sub, diffrax.SubSaveAt) and sub.fn is _DEFAULT_SAVE_FN):
        return ys
    if not (isinstance(ys, tuple) and len(ys) == 2 and all(eqx.is_array(y) for y in ys)):
        return ys
    q, v = ys
    if q.shape != v.shape or q.shape[-1:] != (3,):
        return ys
    q_r, v_r = retract(q, v)
    finite = jnp.all(jnp.isfinite(q), axis=-1, keepdims=True)
    return jnp.where(finite, q_r, q), jnp.where(finite, v_r, v)
