"""`simulate`: integrate any system on (S^2)^n with diffrax."""

import diffrax
import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._checks import check_shapes, check_state
from ._geometry import retract
from ._solvers.projected import Projected
from ._system import AbstractSystem

DEFAULT_MAX_STEPS = 100_000
DEFAULT_TOLERANCES = {np.dtype("float64"): (1e-8, 1e-10), np.dtype("float32"): (1e-5, 1e-6)}
"""Default `(rtol, atol)` of the adaptive step-size controller, by dtype of `q`."""


def default_solver() -> diffrax.AbstractSolver:
    """The solver `simulate` uses when none is given: `Projected(diffrax.Tsit5())`."""
    return Projected(diffrax.Tsit5())


def _vector_field(t, y, system_and_args):
    system, args = system_and_args
    return system.rates(t, y, args)


def initial_state(system: AbstractSystem, y0):
    """Check an initial state `(q0, v0)` and put it exactly on the tangent bundle.

    States within `unit_tolerance(dtype)` of the spheres (and of tangency) are accepted
    and corrected (`q_i / |q_i|`, normal part of `v_i` removed); farther ones raise.
    Also raises if the equations of motion are not finite there (degenerate system)."""
    if not (isinstance(y0, tuple | list) and len(y0) == 2):
        raise ValueError("y0 must be a pair (q0, v0) of (n, 3) arrays.")
    q0, v0 = (jnp.asarray(x) for x in y0)
    check_shapes(q0, v0, system.state_name)
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
        controller = diffrax.ConstantStepSize()
    if isinstance(controller, diffrax.ConstantStepSize) and dt0 is None:
        raise ValueError(
            f"{type(solver).__name__} with fixed steps needs a step size: pass dt0=..."
        )
    return controller


@eqx.filter_jit
def _solve(system, y0, t0, t1, args, solver, dt0, controller, saveat, max_steps, meter,
           adjoint, throw):
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
        throw=throw,
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
    - `solver`: any diffrax solver; default `Projected(diffrax.Tsit5())`. Solvers that do
      not keep `|q_i| = 1` themselves should be wrapped in `Projected`.
    - `dt0`: initial (adaptive) or fixed step size; required for fixed-step solvers.
    - `rtol`, `atol`: tolerances of the default `diffrax.PIDController`; defaults
      `1e-8, 1e-10` in float64 and `1e-5, 1e-6` in float32.
    - `stepsize_controller`: any diffrax controller instead (e.g.
      `diffrax.ConstantStepSize()` with `dt0`); fixed-step solvers get
      `ConstantStepSize` automatically.
    - `saveat`: a `diffrax.SaveAt`; default: the final state only.
    - `max_steps`: maximum number of steps (default 100 000).
    - `progress`: show a tqdm progress bar (diffrax's `TqdmProgressMeter`).
    - `adjoint`: a diffrax adjoint for gradients (default: checkpointed reverse mode).
    - `throw`: raise on failure (default). With `throw=False` the solution's `result`
      tells what went wrong and `ys` holds the trajectory up to the failure.

    **Returns:** a `diffrax.Solution` whose `ys` is `(q, v)` with a leading time axis.
    """
    y0 = initial_state(system, y0)
    solver = default_solver() if solver is None else solver
    controller = _controller(solver, stepsize_controller, rtol, atol, dt0, y0[0].dtype)
    meter = diffrax.TqdmProgressMeter() if progress else diffrax.NoProgressMeter()
    saveat = diffrax.SaveAt(t1=True) if saveat is None else saveat
    adjoint = diffrax.RecursiveCheckpointAdjoint() if adjoint is None else adjoint
    sol = _solve(system, y0, t0, t1, args, solver, dt0, controller, saveat, max_steps,
                 meter, adjoint, throw)
    return _retract_saved(sol)


def _retract_saved(sol: diffrax.Solution) -> diffrax.Solution:
    """Dense output between steps (`SaveAt(ts=...)`) is a polynomial that leaves the
    spheres by the local error: put saved states back on the tangent bundle."""
    ys = sol.ys
    if isinstance(ys, tuple) and len(ys) == 2 and jnp.shape(ys[0])[-1:] == (3,):
        sol = eqx.tree_at(lambda s: s.ys, sol, retract(*ys))
    return sol
