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
    - `system`: any sphere_mech system (`Lagrangian`, `AngularLagrangian`, `Hamiltonian`,
      `AngularHamiltonian`, `ConstantInertiaLagrangian`, a `Scene`, ...).
    - `y0`: `(q0, v0)`, `(n, 3)` arrays (on a mixed space, dicts with the keys of
      `system.space`, one array per factor); `v0` is the system's second state variable.
      A state within `unit_tolerance(dtype)` of the tangent bundle is normalized;
      farther ones raise.
    - `t1`, `t0`: end and start times (any finite floats or scalar arrays; changing their
      values does not recompile). `t1 < t0` integrates backwards.
    - `args`: passed to the system's functions. Python floats in `args` and in the
      system's fields become arrays, so new values do not recompile.
    - `solver`: any diffrax solver; default `Projected(diffrax.Tsit5())`. Also a solver
      class that needs no arguments (`diffrax.Tsit5`) or a name as scene files spell it
      (`"Tsit5"`, `"Projected(Dopri8)"`). Solvers that do
      not keep `|q_i| = 1` themselves should be wrapped in `Projected`; `LieRK(...)`,
      `LieRK4()` and `Variational()` keep it by construction.
    - `dt0`: initial (adaptive) or fixed step size, nonzero with the sign of `t1 - t0`;
      required for fixed-step solvers.
    - `rtol`, `atol`: tolerances (> 0) of the default `diffrax.PIDController`; defaults
      `1e-8, 1e-10` in float64 and `1e-5, 1e-6` in float32.
    - `stepsize_controller`: any diffrax controller instead (e.g.
      `diffrax.ConstantStepSize()` with `dt0`); fixed-step solvers (`RK4`,
      `Projected(RK4())`, `Variational()`, ...) get `ConstantStepSize` automatically.
    - `saveat`: a `diffrax.SaveAt`; default: the final state only. Saved states are put
      back on the tangent bundle: the dense output of `Projected` and plain diffrax
      solvers between steps is a polynomial that leaves the spheres by the local error
      (`LieRK`'s lies on them: the group action of its algebra polynomial).
    - `max_steps`: maximum number of steps (default 100 000).
    - `progress`: show a tqdm progress bar (diffrax's `TqdmProgressMeter`).
    - `adjoint`: a diffrax adjoint for derivatives. Default (`None`): reverse mode
      (`jax.grad`, `jax.value_and_grad`) chosen per derivative from the number of
      differentiated scalars (parameters, state entries, times): at most 8 (e.g. the
      lengths of a chain of up to 8 links), their Jacobian computed during the run in
      forward mode (memory independent of the number of steps); more,
      `diffrax.RecursiveCheckpointAdjoint()` (memory: about `sqrt(2 max_steps)` copies
      of the solver's state, 447 for the default `max_steps`). For `jax.jvp` and
      `jax.jacfwd` pass `diffrax.ForwardMode()`. Costs: `benchmarks/gradients.py`.
    - `event`: a `diffrax.Event` that stops the run, e.g. `diffrax.Event(lambda t, y,
      args, **kw: y[0][0, 1], root_finder=optimistix.Newton(1e-12, 1e-12))` stops where
      the first point crosses the plane `y = 0` (located to the root finder's tolerance
      on the dense output; without a root finder, at the end of the step). Then
      `sol.result` is `RESULTS.event_occurred` (no failure: nothing raises),
      `sol.ts[-1]`/`sol.ys` hold the event time and state with `SaveAt(t1=True)`, and
      `sol.event_mask` says which event fired.
    - `throw`: what to do when the run fails (`max_steps` reached, Newton iterations of
      an implicit solver not converging, a state that became NaN, equations of motion
      not finite at the initial state). `True` (default): raise a `RuntimeError` whose
      message names the cause (inside `jax.jit`, an equinox runtime error with the same
      message). `False`: never raise for such a failure; `sol.result` holds the
      `sm.RESULTS` code and `sol.ys` the trajectory up to the failure (later
      `SaveAt(ts=...)` entries are `inf`). Invalid input (shapes, a `q0` off the
      spheres, bad options) raises in both cases: a `ValueError` naming the argument
      before anything is traced when its value is concrete.

    **Returns:** a `diffrax.Solution` whose `ys` is `(q, v)` (dicts of arrays on a mixed
    space) with a leading time axis
    and whose `result` is an `sm.RESULTS` code.
    """
    run = prepare(system, y0, args, **run_options(locals()))
    with forward_mode_hint():
        sol = _solve(*run.inputs, run.opts)
    return raise_on_failure(sol, max_steps, "simulate") if throw else sol
