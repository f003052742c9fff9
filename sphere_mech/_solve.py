"""The one solve core: `simulate` and `simulate_batch` both run `prepare` and `solve`."""

import functools
import inspect
import math
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._adjoint import default_adjoint_run
from ._checks import check_function, is_real
from ._misc import (
    all_finite,
    as_arrays,
    check_bool,
    is_integer,
    rows,
    state_arrays,
    tree_dtype,
)
from ._results import RESULTS, describe_failures, gathered
from ._solvers.names import as_solver, solver_name
from ._solvers.projected import Projected
from ._system import check_system, vector_field
from ._term import MechanicsTerm

DEFAULT_MAX_STEPS = 100_000
"""Default `max_steps` of `simulate` and `simulate_batch` (past it: `max_steps_reached`)."""
MAX_STEPS = 2**31 - 1
"""The largest `max_steps`: diffrax counts steps in 32-bit integers without x64."""
DEFAULT_TOLERANCES = {np.dtype("float64"): (1e-8, 1e-10), np.dtype("float32"): (1e-5, 1e-6)}
"""Default `(rtol, atol)` of the adaptive step-size controller, by dtype of `q`."""


def tolerances(rtol, atol, dtype) -> tuple[float, float]:
    """`(rtol, atol)` with each `None` replaced by its default for `dtype`
    (`DEFAULT_TOLERANCES`; float32's for a dtype not in it)."""
    defaults = DEFAULT_TOLERANCES.get(np.dtype(dtype), (1e-5, 1e-6))
    return tuple(d if x is None else x for x, d in zip((rtol, atol), defaults, strict=True))


def default_solver() -> diffrax.AbstractSolver:
    """The solver `simulate` uses when none is given.

    **Returns:** `Projected(diffrax.Tsit5())`."""
    return Projected(diffrax.Tsit5())


class Options(eqx.Module):
    """How a run integrates: everything but the system, state, times and `args`."""

    solver: diffrax.AbstractSolver
    controller: diffrax.AbstractStepSizeController
    saveat: diffrax.SaveAt
    adjoint: diffrax.AbstractAdjoint | None  # None: `default_adjoint_run`
    meter: diffrax.AbstractProgressMeter
    event: diffrax.Event | None
    max_steps: int | None = eqx.field(static=True)
    batched: bool = eqx.field(static=True)  # one trajectory of `simulate_batch`'s vmap
    sharded: bool = eqx.field(static=True, default=False)  # ... over several devices


OBJECT_OPTIONS = {
    "stepsize_controller": (
        diffrax.AbstractStepSizeController,
        "a diffrax step-size controller, e.g. diffrax.PIDController(rtol=1e-8, atol=1e-10)",
    ),
    "saveat": (diffrax.SaveAt, "a diffrax.SaveAt, e.g. diffrax.SaveAt(ts=ts)"),
    "adjoint": (diffrax.AbstractAdjoint, "a diffrax adjoint, e.g. diffrax.ForwardMode()"),
    "event": (diffrax.Event, "a diffrax.Event, e.g. diffrax.Event(cond_fn)"),
}
"""The options that are diffrax objects: the class each must be, and what to pass."""


def options(
    *,
    dtype,
    batched: bool = False,
    t0=0.0,
    t1=None,
    solver=None,
    dt0=None,
    rtol=None,
    atol=None,
    stepsize_controller=None,
    saveat=None,
    max_steps=DEFAULT_MAX_STEPS,
    progress=False,
    adjoint=None,
    event=None,
) -> "Options":
    """`simulate`'s options (`simulate_batch`'s if `batched`), checked and completed."""
    given = dict(
        stepsize_controller=stepsize_controller, saveat=saveat, adjoint=adjoint, event=event
    )
    for name, value in given.items():
        kind, expected = OBJECT_OPTIONS[name]
        if value is not None and not isinstance(value, kind):
            raise OptionError(name, f"{name} must be {expected} or None (got {value!r})")
    if event is not None:
        check_event(event)
    check_flag(progress, "progress")
    check_values(t0, t1, dt0, rtol, atol, max_steps, saveat, dtype)
    solver = default_solver() if solver is None else as_solver(solver)
    if stepsize_controller is not None:
        if rtol is not None or atol is not None:
            raise ValueError(
                "Give rtol/atol either to simulate or to stepsize_controller, not both."
            )
        controller = stepsize_controller
    elif isinstance(solver, diffrax.AbstractAdaptiveSolver):
        rtol, atol = tolerances(rtol, atol, dtype)
        controller = diffrax.PIDController(rtol=rtol, atol=atol)
    else:
        if rtol is not None or atol is not None:
            raise ValueError(
                f"{solver_name(solver)} has no error estimate, so it takes fixed steps "
                "(dt0) and rtol/atol would be ignored: drop them, or use an adaptive "
                "solver such as Projected(diffrax.Tsit5()) or LieRK4()."
            )
        controller = diffrax.ConstantStepSize()
    adaptive = isinstance(controller, diffrax.AbstractAdaptiveStepSizeController)
    if adaptive and not isinstance(solver, diffrax.AbstractAdaptiveSolver):
        raise ValueError(
            f"{solver_name(solver)} has no error estimate and cannot be used with the "
            f"adaptive {type(controller).__name__}: use diffrax.ConstantStepSize() with a "
            "dt0, or an adaptive solver (Projected(diffrax.Tsit5()), LieRK4(), ...)."
        )
    if isinstance(controller, diffrax.ConstantStepSize) and dt0 is None:
        raise ValueError(f"{solver_name(solver)} with fixed steps needs a step size: pass dt0=...")
    saveat = diffrax.SaveAt(t1=True) if saveat is None else saveat
    # in the state's dtype, as t0, t1 and dt0 (`times`): saved states and times keep it
    saveat = eqx.tree_at(_save_times, saveat, replace_fn=lambda ts: jnp.asarray(ts, dtype))
    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()
    max_steps = None if max_steps is None else int(max_steps)  # a NumPy integer: static
    return Options(solver, controller, saveat, adjoint, meter, event, max_steps, batched)


_EVENT_KWARGS = ("terms", "solver", "t0", "t1", "dt0", "saveat", "stepsize_controller", "max_steps")
"""The keywords diffrax passes an event's condition besides `t, y, args`."""


def check_event(event: diffrax.Event) -> None:
    """`event`'s conditions callables taking `(t, y, args, **kwargs)` (diffrax passes
    `_EVENT_KWARGS`) and its root finder an optimistix root finder or `None`, else an
    `OptionError`: diffrax checks neither before it runs them."""
    conditions = jax.tree.leaves(event.cond_fn, is_leaf=callable)
    if not conditions:
        raise OptionError("event", "event must have a condition: diffrax.Event(cond_fn)")
    for fn in conditions:
        check_function(
            fn,
            "event.cond_fn",
            "cond_fn(t, y, args, **kwargs) (or a pytree of them)",
            3,
            _EVENT_KWARGS,
            functools.partial(OptionError, "event"),
        )
    finder = event.root_finder
    if finder is not None and not isinstance(finder, optx.AbstractRootFinder):
        raise OptionError(
            "event",
            "event.root_finder must be an optimistix root finder or None, e.g. "
            f"optimistix.Newton(rtol=1e-12, atol=1e-12) (got {finder!r})",
        )


def check_flag(value, name: str) -> None:
    """The one check of a flag option (`progress`, `throw`): a bool, else an `OptionError`."""
    check_bool(value, name, functools.partial(OptionError, name))


class OptionError(ValueError):
    """A bad value of the option `field` of `simulate`, `simulate_batch`, `fit` or a scene file."""

    def __init__(self, field: str, message: str):
        self.field = field
        super().__init__(message)


def _concrete(x) -> float | None:
    """A concrete scalar as a float; `None` for `None`, a tracer or a non-scalar."""
    if x is None or isinstance(x, jax.core.Tracer) or np.ndim(x) != 0:
        return None
    try:
        return float(x)
    except OverflowError:  # a Python integer beyond float64: infinite, refused as such
        return math.inf if x > 0 else -math.inf


def check_values(t0, t1, dt0, rtol, atol, max_steps, saveat=None, dtype=float) -> None:
    """The one check of concrete option values (traced ones pass): times and tolerances
    real numbers (no strings, bools or complex numbers) and scalars, finite times, a finite
    nonzero `dt0` with the sign of `t1 - t0`, finite `rtol`, `atol` > 0, an integer
    `max_steps` >= 1 or `None`, and `saveat`'s save times 1-D, in the state's `dtype` finite,
    between `t0` and `t1` and in the direction of integration (diffrax checks the last two
    only while running, and passes a NaN time, saving `inf`); else an `OptionError`."""
    named = dict(t0=t0, t1=t1, dt0=dt0, rtol=rtol, atol=atol)
    for name, x in named.items():
        if x is not None and not is_real(x):
            raise OptionError(name, f"{name} must be a real number (got {x!r})")
        if x is not None and jnp.ndim(x) != 0:
            raise OptionError(name, f"{name} must be a scalar (got shape {jnp.shape(x)})")
    t0, t1, dt0, rtol, atol = map(_concrete, named.values())
    for name, t in (("t0", t0), ("t1", t1)):
        if t is not None and not math.isfinite(t):
            raise OptionError(name, f"{name} must be a finite time (got {t:g})")
    if dt0 is not None:
        if not (math.isfinite(dt0) and dt0 != 0):
            raise OptionError("dt0", f"dt0 must be a finite, nonzero step (got {dt0:g})")
        if t0 is not None and t1 is not None and (t1 - t0) * dt0 < 0:
            raise OptionError(
                "dt0",
                f"dt0 must have the sign of t1 - t0, the direction of "
                f"integration (got {dt0:g} with t0 = {t0:g}, t1 = {t1:g})",
            )
    for name, tol in (("rtol", rtol), ("atol", atol)):
        if tol is not None and not (math.isfinite(tol) and tol > 0):
            raise OptionError(name, f"{name} must be a finite number > 0 (got {tol:g})")
    if max_steps is not None and not (is_integer(max_steps) and 1 <= max_steps <= MAX_STEPS):
        expected = f"an integer from 1 to {MAX_STEPS} or None"
        raise OptionError("max_steps", f"max_steps must be {expected} (got {max_steps!r})")
    for ts in [] if saveat is None else _save_times(saveat):
        if jnp.ndim(ts) != 1:
            raise OptionError(
                "saveat", f"saveat.ts must be a 1-D array of times (got shape {jnp.shape(ts)})"
            )
        if isinstance(ts, jax.core.Tracer):
            continue
        ts = np.asarray(ts, dtype=np.dtype(dtype)).ravel()
        if not np.all(np.isfinite(ts)):
            raise OptionError("saveat", f"saveat.ts must be finite times (got {ts[:10]})")
        if t0 is None or t1 is None or ts.size == 0:
            continue
        direction = 1.0 if t1 >= t0 else -1.0
        if np.any(np.diff(direction * ts) < 0):
            order = "increasing" if direction > 0 else "decreasing (t1 < t0)"
            raise OptionError("saveat", f"saveat.ts must be {order} (got {ts[:10]})")
        lo, hi = sorted(np.asarray([t0, t1], dtype=ts.dtype))
        if ts.min() < lo or ts.max() > hi:
            raise OptionError(
                "saveat",
                f"saveat.ts must lie between t0 = {t0:g} and t1 = {t1:g} (got "
                f"{ts.min():g} to {ts.max():g})",
            )


class Run(eqx.Module):
    """What `solve` runs, as `prepare` made it (initial states with a batch axis if batched)."""

    system: Any
    y0: Any
    args: Any
    t0: Any
    t1: Any
    dt0: Any
    opts: Options
    valid: Any  # which initial states are valid (one entry per member of a batch)
    throw: bool = eqx.field(static=True)


def _leading(tree, size, what, alternative):
    """Check that every array leaf of `tree` has leading axis `size`."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree, is_leaf=eqx.is_array):
        if eqx.is_array(leaf) and (leaf.ndim == 0 or leaf.shape[0] != size):
            raise ValueError(
                f"{what}{jax.tree_util.keystr(path)} must have a leading batch axis of size "
                f"{size} (the batch size of y0), got shape {leaf.shape}; {alternative}."
            )


def prepare(
    system,
    y0,
    args=None,
    *,
    batched=False,
    batch_args=False,
    batch_system=False,
    throw=True,
    **options_,
):
    """The one prologue of `simulate`, `simulate_batch` and the command line: a `Run` with
    `y0` checked (`initial_states`, raising unless `batched` with `throw=False`), batched
    `args` and `system` checked for their leading axis, `options` completed, Python floats
    as arrays and times in the state's dtype."""
    what = "simulate_batch" if batched else "simulate"
    unknown = sorted(set(options_) - set(OPTION_NAMES))
    if unknown:
        raise TypeError(f"{what}() got unexpected keyword arguments {unknown}")
    check_system(system, what)
    check_flag(throw, "throw")
    q0, v0 = state_pair(y0, "(batch, n, 3)" if batched else "(n, 3)")
    if batched:
        leading = {jnp.shape(x)[:1] for x in jax.tree.leaves((q0, v0))}
        if len(leading) != 1 or leading == {()} or leading == {(0,)}:
            raise ValueError(
                "y0 must have a leading batch axis (batch >= 1), the same on every "
                f"array, got shapes {jax.tree.map(jnp.shape, (q0, v0))}."
            )
    else:
        q0, v0 = jax.tree.map(lambda x: x[None], (q0, v0))
    system, args = as_arrays((system, args))
    size = jax.tree.leaves(q0)[0].shape[0]
    if batch_system:
        alternative = "batch_system=False shares the system between trajectories"
        _leading(eqx.filter(system, eqx.is_array), size, "system", alternative)
    member = lambda: jax.tree.map(lambda x: x[0] if eqx.is_array(x) else x, system)
    space = (member() if batch_system else system).state_space
    try:
        space.check_shapes(*jax.tree.map(lambda x: x[0], (q0, v0)), system.state_name)
    except ValueError as e:
        if not batched:
            raise
        message = str(e).rstrip(".")
        raise ValueError(f"{message} (one member of y0: y0 has a leading batch axis).") from None
    if batch_args:
        _leading(args, size, "args", "batch_args=False shares args between trajectories")
    dtype = tree_dtype((q0, v0))
    opts = options(dtype=dtype, batched=batched, **options_)
    t0, t1, dt0 = times(dtype, options_.get("t0", 0.0), options_["t1"], options_.get("dt0"))
    y0 = jax.tree.map(lambda x: x.astype(dtype), (q0, v0))
    y0, valid = initial_states(space, system.state_name, y0, what, throw or not batched)
    y0 = y0 if batched else jax.tree.map(lambda x: x[0], y0)
    return Run(system, y0, args, t0, t1, dt0, opts, valid, throw)


OPTION_NAMES = ("t0", "t1", "solver", "dt0", "rtol", "atol", "stepsize_controller", "saveat")
OPTION_NAMES += ("max_steps", "progress", "adjoint", "event", "throw")
"""The options `simulate` and `simulate_batch` share, as `prepare` takes them."""


def run_options(scope: dict) -> dict:
    """The shared options among `simulate`'s `locals()`."""
    return {name: scope[name] for name in OPTION_NAMES}


def shared_signature(fn, like) -> inspect.Signature:
    """The signature of `fn(..., **options)` with `options` spelled out as `like`'s."""
    own = inspect.signature(fn).parameters
    options = [p for name, p in inspect.signature(like).parameters.items() if name in OPTION_NAMES]
    params = [p for p in own.values() if p.kind is not p.VAR_KEYWORD]
    params = params[:3] + [p for p in options if p.name not in own] + params[3:]
    return inspect.signature(fn).replace(parameters=params)


def times(dtype, *ts):
    """Times as arrays of the state's dtype (`None` stays): no recompiles, no promotion."""
    return tuple(None if t is None else jnp.asarray(t, dtype=dtype) for t in ts)


def state_pair(y0, shapes: str, name: str = "y0", pair: str = "(q0, v0)"):
    """`y0` (called `name`) as a pair `(q0, v0)` of arrays (or dicts of them); nested lists
    as float arrays."""
    if not (isinstance(y0, tuple | list) and len(y0) == 2):
        raise ValueError(
            f"{name} must be a pair {pair} of {shapes} arrays (dicts of arrays on a mixed space)."
        )
    return state_arrays(*y0)


def initial_states(space, state_name: str, y0, what: str, check: bool):
    """`(y0, valid)`: batched initial states retracted, invalid ones (`space.problems`)
    replaced by the first valid one; with `check` an invalid state raises."""
    y0, problem, messages = _initial_states(space, state_name, y0, check and _traced(y0))
    problem = problem if _traced(problem) else gathered(problem)
    if check and not _traced(problem):
        bad = np.flatnonzero(problem >= 0)
        if bad.size:
            where = describe_failures(
                bad, problem.size, "initial states are invalid", "initial state"
            )
            raise ValueError(f"{what}:{where} {messages[problem[bad[0]]]}")
    return y0, problem < 0


def _traced(tree) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


@eqx.filter_jit
def _initial_states(space, state_name, y0, raise_traced: bool):
    def one(y):
        found, messages = zip(*space.problems(*y, state_name), strict=True)
        found = jnp.stack(found)
        problem = jnp.where(jnp.any(found), jnp.argmax(found), -1)
        if raise_traced:
            y = eqx.branched_error_if(y, jnp.any(found), jnp.argmax(found), messages)
        return space.retract(*y), problem, messages

    messages = one(jax.tree.map(lambda x: x[0], y0))[2]
    y0, problem = jax.vmap(lambda y: one(y)[:2])(y0)
    # Not the invalid state itself: a NaN run stuck on its first step makes diffrax redo every
    # member's first stage (`unvmap_any(first_step)`), which moves the others with `Projected`.
    stand_in = jax.tree.map(lambda x: x[jnp.argmax(problem < 0)], y0)
    y0 = jax.tree.map(lambda x, s: jnp.where(rows(problem < 0, x), x, s), y0, stand_in)
    return y0, problem, messages


def solve(system, y0, t0, t1, dt0, args, opts: Options) -> diffrax.Solution:
    """`solve_with` the adjoint of `opts`, or `default_adjoint_run` when it is `None`."""
    if opts.adjoint is None:
        return default_adjoint_run(solve_with, (system, y0, t0, t1, dt0, args, opts))
    return solve_with(opts.adjoint, system, y0, t0, t1, dt0, args, opts)


def solve_with(adjoint, system, y0, t0, t1, dt0, args, opts: Options) -> diffrax.Solution:
    """One trajectory, never raising: `sol.result` is a `RESULTS` code."""
    ok = all_finite(vector_field(system, t0, y0, args))
    saveat = opts.saveat
    fixed = not isinstance(opts.controller, diffrax.AbstractAdaptiveStepSizeController)
    if not fixed:
        # Not finite at the start: no step over [t0, t0], not NaN steps rejected until
        # max_steps. Fixed steps keep t1, so under vmap their loop stays unbatched.
        saveat = eqx.tree_at(_save_times, saveat, replace_fn=lambda ts: jnp.where(ok, ts, t0))
        t1 = jnp.where(ok, t1, t0)
    else:  # fixed steps accept a NaN step: the last state, saved beside the caller's, tells
        saveat = eqx.tree_at(lambda s: s.subs, saveat, (saveat.subs, diffrax.SubSaveAt(t1=True)))
    # diffrax integrates in -t backwards (t0 > t1, and t0 == t1 too): its sign of time
    direction = jnp.where(t0 < t1, 1, -1).astype(jnp.result_type(t0))
    sol = diffrax.diffeqsolve(
        MechanicsTerm(system),
        opts.solver,
        t0,
        t1,
        dt0,
        y0,
        args=args,
        saveat=saveat,
        stepsize_controller=opts.controller,
        max_steps=opts.max_steps,
        progress_meter=opts.meter,
        adjoint=adjoint,
        event=_physical_event(
            opts.event,
            direction,
            (t0, y0, args),
            dict(
                terms=MechanicsTerm(system),
                solver=opts.solver,
                t0=t0,
                t1=t1,
                dt0=dt0,
                saveat=saveat,
                stepsize_controller=opts.controller,
                max_steps=opts.max_steps,
            ),
        ),
        throw=False,
    )
    has_nan = functools.reduce(
        jnp.logical_or, [jnp.any(jnp.isnan(y)) for y in jax.tree.leaves(sol.ys)], jnp.array(False)
    )
    if fixed:
        sol = eqx.tree_at(lambda s: (s.ts, s.ys), sol, (sol.ts[0], sol.ys[0]))
    result = RESULTS.promote(sol.result)
    if opts.event is not None:
        # diffrax finds the event's root only once the event fired (its step succeeded): a
        # nonlinear failure then is the root finder's; before, an implicit step's.
        fired = functools.reduce(jnp.logical_or, jax.tree.leaves(sol.event_mask))
        root = [RESULTS.nonlinear_max_steps_reached, RESULTS.nonlinear_divergence, RESULTS.singular]
        failed_root = fired & functools.reduce(jnp.logical_or, [result == r for r in root])
        result = RESULTS.where(failed_root, RESULTS.event_root_failed, result)
    # A NaN state (fixed steps accept it) is `nonfinite`, also where it fired the event
    # (`_PhysicalCondition`'s `inf`) or fed the event's root finder (lineax's code).
    nan_codes = [RESULTS.successful, RESULTS.event_occurred, RESULTS.nonfinite_input]
    nan_code = functools.reduce(jnp.logical_or, [result == r for r in nan_codes])
    result = RESULTS.where(nan_code & has_nan, RESULTS.nonfinite, result)
    result = RESULTS.where(ok, result, RESULTS.nonfinite_initial)
    # Unreached save times are `inf`, never NaN: so are saves of a NaN state and their times.
    ts, ys = _unsave_nonfinite(opts.saveat, sol.ts, sol.ys)
    ts, ys = jax.tree.map(
        lambda x: jnp.where(ok, x, jnp.inf),
        (ts, _retract_saved(system.state_space, opts.saveat, ys)),
    )
    event_mask = sol.event_mask
    if opts.event is not None:  # a NaN state's "event" is a failure, not an event
        nan = (result == RESULTS.nonfinite) | (result == RESULTS.nonfinite_initial)
        event_mask = jax.tree.map(lambda m: m & jnp.logical_not(nan), event_mask)
    fields = lambda s: (s.result, s.ts, s.ys, s.event_mask)
    return eqx.tree_at(fields, sol, (result, ts, ys, event_mask), is_leaf=lambda x: x is None)


class _PhysicalCondition(eqx.Module):
    """An event's condition `fn` called with the physical times: diffrax passes its own,
    `-t` (and `-t0`, `-t1`, `-dt0`) backwards. A float condition is returned in JAX's
    default float dtype, that of diffrax's `lambda: 0.0` beside it in its root find (float64
    under x64, for a float32 state too), and `+inf` at a state that is not finite (NaN
    there is the condition's own: `_FiniteStart` tells them apart)."""

    fn: Any
    direction: Any

    def __call__(self, t, y, args, **kwargs):
        for name in ("t0", "t1", "dt0"):
            if kwargs.get(name) is not None:
                kwargs[name] = self.direction * kwargs[name]
        value = self.fn(self.direction * t, y, args, **kwargs)
        if jnp.issubdtype(jnp.result_type(value), jnp.floating):
            value = jnp.where(all_finite(y), value, jnp.inf).astype(jnp.result_type(float))
        return value


class _FiniteStart(optx.AbstractRootFinder):
    """An event's root `finder`, telling a condition not finite at a finite state (NaN:
    the finder's iterates or the step's end left its domain; `nonlinear_divergence`, so
    `event_root_failed`) from a state that is not finite where the finder starts, at the
    end of the step (`+inf` from `_PhysicalCondition`; lineax's `nonfinite_input` kept,
    then `nonfinite`)."""

    finder: optx.AbstractRootFinder
    rtol = property(lambda self: self.finder.rtol)
    atol = property(lambda self: self.finder.atol)
    norm = property(lambda self: self.finder.norm)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        state = self.finder.init(fn, y, args, options, f_struct, aux_struct, tags)
        state_finite = jnp.logical_not(_any_inf(fn(y, args)[0]))
        return state, state_finite

    def step(self, fn, y, args, options, state, tags):
        y, inner, aux = self.finder.step(fn, y, args, options, state[0], tags)
        return y, (inner, state[1]), aux

    def terminate(self, fn, y, args, options, state, tags):
        done, result = self.finder.terminate(fn, y, args, options, state[0], tags)
        inside = state[1] & (result == optx.RESULTS.nonfinite_input)
        return done, optx.RESULTS.where(inside, optx.RESULTS.nonlinear_divergence, result)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return self.finder.postprocess(fn, y, aux, args, options, state[0], tags, result)


def _any_inf(tree) -> jax.Array:
    """Whether a leaf of `tree` has an infinite entry."""
    leaves = [jnp.any(jnp.isinf(x)) for x in jax.tree.leaves(tree)]
    return functools.reduce(jnp.logical_or, leaves, jnp.array(False))


def _physical_event(event: diffrax.Event | None, direction, start, kwargs) -> diffrax.Event | None:
    """`event` with every condition a `_PhysicalCondition`, its root finder `_FiniteStart`.
    Where every condition is boolean the root finder is dropped: diffrax puts a boolean
    event at the end of its step either way, and its root find would fail on times not in
    JAX's default float dtype (a float32 state under x64). `start`, `kwargs`: a
    condition's arguments `(t0, y0, args)` and keywords, to read what it returns."""
    if event is None:
        return None
    conditions = jax.tree.leaves(event.cond_fn, is_leaf=callable)
    values = [jax.eval_shape(lambda fn=fn: fn(*start, **kwargs)) for fn in conditions]
    boolean = [jnp.issubdtype(jnp.result_type(v), jnp.bool_) for v in values]
    finder = event.root_finder
    if all(boolean):
        finder = None
    elif any(boolean) and finder is not None and jnp.result_type(start[0]) != jnp.dtype(float):
        raise OptionError(
            "event",
            "event: boolean and float conditions together with a root finder need the state "
            f"in JAX's default float dtype ({jnp.dtype(float)}), got "
            f"{jnp.result_type(start[0])}: cast the state, or make every condition float",
        )
    wrap = lambda fn: _PhysicalCondition(fn, direction)
    finder = None if finder is None else _FiniteStart(finder)
    return eqx.tree_at(
        lambda e: (e.cond_fn, e.root_finder),
        event,
        (jax.tree.map(wrap, event.cond_fn, is_leaf=callable), finder),
        is_leaf=lambda x: x is None,
    )


_is_sub = lambda x: isinstance(x, diffrax.SubSaveAt)


def _per_sub(fn, saveat: diffrax.SaveAt, *outputs) -> tuple:
    """`fn(sub, *parts)` for each `SubSaveAt` in `saveat.subs` (any PyTree of them, as
    diffrax allows: one, a list, a dict, nested) and its parts of `outputs` (PyTrees that
    follow `saveat.subs`: `sol.ts`, `sol.ys`). `fn` returns the new parts, one per output;
    the result is the new outputs (as they are if nothing is saved: dense output only)."""
    structure = jax.tree.structure(saveat.subs, is_leaf=_is_sub)
    if not structure.num_leaves:
        return outputs
    parts = [structure.flatten_up_to(tree) for tree in (saveat.subs, *outputs)]
    results = [fn(*row) for row in zip(*parts, strict=True)]
    return tuple(structure.unflatten(list(r)) for r in zip(*results, strict=True))


def _unsave_nonfinite(saveat: diffrax.SaveAt, ts, ys):
    """Saved entries with a NaN (or a NaN time) as unreached ones: `inf`, their time too
    (`+inf` backwards as well, as diffrax's unreached times)."""

    def one(_, ts, ys):
        floats = [y for y in jax.tree.leaves(ys) if jnp.issubdtype(y.dtype, jnp.inexact)]
        per_time = [jnp.any(jnp.isnan(y).reshape(y.shape[0], -1), axis=1) for y in floats]
        bad = functools.reduce(jnp.logical_or, per_time, jnp.isnan(ts))
        fill = lambda y, fill: jnp.where(bad.reshape(bad.shape + (1,) * (y.ndim - 1)), fill, y)
        ys = jax.tree.map(
            lambda y: fill(y, jnp.inf) if jnp.issubdtype(y.dtype, jnp.inexact) else y, ys
        )
        return fill(ts, jnp.inf), ys

    return _per_sub(one, saveat, ts, ys)


def _save_times(saveat: diffrax.SaveAt) -> list:
    subs = jax.tree.leaves(saveat.subs, is_leaf=_is_sub)
    return [sub.ts for sub in subs if _is_sub(sub) and sub.ts is not None]


_DEFAULT_SAVE_FN = diffrax.SubSaveAt(t1=True).fn


def _retract_saved(space, saveat: diffrax.SaveAt, ys):
    """Saved states (diffrax's default `fn`, finite entries) put back on the tangent bundle,
    in every `SubSaveAt` of `saveat.subs`, whatever PyTree holds them."""
    return _per_sub(lambda sub, ys: (_retract_if_state(space, sub, ys),), saveat, ys)[0]


def _retract_if_state(space, sub, ys):
    if sub.fn is not _DEFAULT_SAVE_FN:
        return ys
    q, v = ys
    q_r, v_r = space.retract(q, v)
    per_time = [
        jnp.all(jnp.isfinite(x).reshape(x.shape[0], -1), axis=1) for x in jax.tree.leaves(q)
    ]
    finite = functools.reduce(jnp.logical_and, per_time)
    keep = lambda new, old: jnp.where(
        finite.reshape(finite.shape + (1,) * (new.ndim - 1)), new, old
    )
    return jax.tree.map(keep, q_r, q), jax.tree.map(keep, v_r, v)
