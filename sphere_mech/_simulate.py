"""`simulate`: integrate any system on (S^2)^n with diffrax."""

import diffrax
import equinox as eqx

from ._adjoint import forward_mode_hint
from ._results import raise_on_failure
from ._solve import DEFAULT_MAX_STEPS, prepare, run_options, solve
from ._system import AbstractSystem

_solve = eqx.filter_jit(solve)


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
    event: diffrax.Event | None = None,
    throw: bool = True,
) -> diffrax.Solution:
    """Integrate `system` from `y0 = (q0, v0)` at `t0` to `t1`.

    **Arguments:**
    - `system`: any sphere_mech system (`Lagrangian`, `Hamiltonian`, a `Scene`, ...).
    - `y0`: `(q0, v0)`, `(n, 3)` arrays (on a mixed space, dicts with the keys of
      `system.space`); `v0` is the system's second state variable. A state within
      `unit_tolerance(dtype)` of the tangent bundle is normalized; farther ones raise.
    - `t1`, `t0`: end and start times; `t1 < t0` integrates backwards.
    - `args`: passed to the system's functions. Python floats in `args` and in the
      system's fields become arrays: new values (of times too) do not recompile.
    - `solver`: a diffrax solver (default `Projected(diffrax.Tsit5())`), a solver class, or
      a name as scene files spell it (`"Projected(Dopri8)"`). Wrap solvers that do not
      keep `|q_i| = 1` in `Projected` (`LieRK`, `LieRK4`, `Variational` keep it).
    - `dt0`: initial (adaptive) or fixed step size, nonzero with the sign of `t1 - t0`;
      required for fixed-step solvers, which get `diffrax.ConstantStepSize()`. Solvers
      with an error estimate (`Projected(diffrax.Tsit5())`, `LieRK4()`, ...) adapt their
      steps from `dt0`; for fixed steps with them, pass
      `stepsize_controller=diffrax.ConstantStepSize()` too. Fixed steps of a `dt0` that
      does not divide `t1 - t0`: diffrax ends the first at `t0 + dt0`, the others at
      `t0 + k (t1 - t0) / N`, `N = ceil((t1 - t0) / dt0)`, so none is longer than `dt0`
      (`dt0=0.3` to `t1=1`: steps of 0.3, 0.2, 0.25, 0.25).
    - `rtol`, `atol`: tolerances (> 0) of the default `diffrax.PIDController`; defaults
      `1e-8, 1e-10` in float64 and `1e-5, 1e-6` in float32.
    - `stepsize_controller`: any diffrax step-size controller instead.
    - `saveat`: a `diffrax.SaveAt` (default: the final state), saved states put back on
      the tangent bundle (dense output leaves the spheres by the local error).
    - `max_steps`: maximum number of steps (default 100 000).
    - `progress`: show a tqdm progress bar (diffrax's `TqdmProgressMeter`).
    - `adjoint`: a diffrax adjoint. Default (`None`): reverse mode through the Jacobian
      computed during the run in forward mode for at most 8 differentiated scalars (memory
      independent of the steps), else `diffrax.RecursiveCheckpointAdjoint()` (about
      `sqrt(2 max_steps)` solver states); see `benchmarks/gradients.py`. For `jax.jvp`
      and `jax.jacfwd` pass `diffrax.ForwardMode()`; second derivatives: `jax.hessian`
      (forward over reverse), not `jax.grad` of `jax.grad`. The default differentiates through
      `system`'s array fields, `y0`, `args`, the times `t0`, `t1`, `dt0`, the save times
      and the values that the functions close over (a parameter captured by `L`, by the
      forces or by an event's condition).
    - `event`: a `diffrax.Event` that stops the run, e.g. `diffrax.Event(lambda t, y,
      args, **kw: y[0][0, 1], root_finder=optimistix.Newton(1e-12, 1e-12))` where the
      first point crosses `y = 0`; `sol.result` is then `RESULTS.event_occurred` (nothing
      raises) and `sol.event_mask` says which event fired. The condition gets the
      physical time, backwards too (diffrax passes `-t`). With `SaveAt(ts=...,
      t1=True)` the state where it stopped follows the last save time reached (diffrax
      writes it into the first unreached slot, its time in `sol.ts`), and the rest are
      `inf`: find it by `sol.ts`, not as `sol.ys[-1]`.
    - `throw`: on a run-time failure (`max_steps` reached, Newton iterations not
      converging, a NaN state, rates not finite at the start) `True` raises a
      `RuntimeError` naming the cause (in `jax.jit`, an equinox runtime error); `False`
      never raises: `sol.result` holds the `sm.RESULTS` code and `sol.ys` the trajectory
      up to the failure (`inf` after). Invalid input (shapes, `q0` off the spheres, bad
      options) raises either way, a `ValueError` where concrete.

    **Returns:** a `diffrax.Solution` whose `ys` is `(q, v)` (dicts of arrays on a mixed
    space) with a leading time axis and whose `result` is an `sm.RESULTS` code.
    """
    run = prepare(system, y0, args, **run_options(locals()))
    with forward_mode_hint(run.opts.adjoint):
        sol = _solve(run.system, run.y0, run.t0, run.t1, run.dt0, run.args, run.opts)
    return raise_on_failure(sol, max_steps, "simulate") if throw else sol
