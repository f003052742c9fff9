"""A scene run's energy bookkeeping (the library's side of `sphere-mech run`): the energy
error `E(t) - E(0)`, or with forces the work-energy balance `E(t) - E(0) - W(t)`, `W` summed
during the integration (`WithWork`) over the solver's own steps."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._geometry import constraint_error
from ._program import build, fixed_steps_taken
from ._scene_files import check_extent, checked_end
from ._solve import tolerances
from ._solvers.work import power_and_rate, work_step
from ._spaces import BASE, chain_parts


@eqx.filter_jit
def _energy_and_power(system, ts, q, v, args):
    energy = jax.vmap(system.energy, (0, 0, 0, None))(ts, q, v, args)
    P, dP = jax.vmap(lambda t, a, b: power_and_rate(system, t, a, b, args))(ts, q, v)
    return energy, P, dP


def work_energy_balance(system, ts, q, v, args=None):
    """The work-energy balance of a forced trajectory: `E(t) - E(0) - W(t)`.

    `W = int P dt` (`P = system.power`) is integrated over the given times by the
    end-corrected trapezoidal rule `h/2 (P_k + P_{k+1}) + h^2/12 (P'_k - P'_{k+1})` (fourth
    order; `P' = dP/dt` along the flow by `jax.jvp`), so on the solver's own steps
    (`SaveAt(steps=True)`) the balance measures the integrator alone.

    **Arguments:**
    - `system`: a Lagrangian system in `(q, qdot)` (a `Scene`, `Lagrangian`, ...).
    - `ts`, `args`: the times `(T,)`, increasing, and the system's `args`.
    - `q`, `v`: the states at `ts`, `(T, n, 3)` each (dicts of such arrays with a leading
      `T` axis where the system's state is a dict).

    **Returns:** `(E, W, E - E(0) - W)`, three numpy arrays of shape `(T,)`.
    """
    energy, P, dP = (np.asarray(a) for a in _energy_and_power(system, jnp.asarray(ts), q, v, args))
    W = np.concatenate([[0.0], np.cumsum(work_step(np.diff(ts), P[:-1], dP[:-1], P[1:], dP[1:]))])
    return energy, W, energy - energy[0] - W


@dataclasses.dataclass
class SceneResult:
    """Arrays of a scene run (numpy) and its summary: what `sphere-mech run` writes.

    **Attributes:**
    - `t`, `energy`, `potential`: the saved times `(T,)`, and `E` and `U` at `t`.
    - `q`, `v`: the saved states, `(T, n, 3)` each (with a `Base`, dicts of arrays with a
      leading `T` axis, as `sm.chain_space`).
    - `x`: the points drawn at `t`, `scene.drawn_points(q)` (with a base, its point first;
      with a `RigidBase`, its joint and the ends of its arms last).
    - `error_t`: the times of `error`: `t`, or with forces the start and the end of every
      segment (steps of the solver, where the work is known).
    - `error`: `E - E(0)` divided by the run's largest `|T| + |V|` (kinetic and potential
      energies at `t`; `|E(0)|` would be no scale for a run that starts at `E = 0`), or
      with forces `E - E(0) - W` divided by the larger of `max |E|`, `max |W|` (not
      divided where the scale is zero; the summary then says `null`).
    - `constraint`: `max_i | |q_i| - 1 |` over `scene.spheres(q)` at `t`.
    - `summary`: what `summary.json` holds (solver, tolerances or step, steps, wall time,
      largest errors; with a `Base`, its final coordinates), strict JSON: what could not be
      computed is `None`, with the reason in `"not_computed"`.
    - `work`, `step_energy`: with forces, `W` and `E` at `error_t`.
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    x: np.ndarray
    energy: np.ndarray
    error_t: np.ndarray
    error: np.ndarray
    constraint: np.ndarray
    summary: dict
    potential: np.ndarray | None = None
    work: np.ndarray | None = None
    step_energy: np.ndarray | None = None


def run_scene(spec, *, t1=None, progress=False) -> SceneResult:
    """Simulate a scene file's scene and report its energy bookkeeping, as the command
    line does: segment by segment with one compiled program (see `sphere_mech._program`),
    each segment `simulate`'s core with the file's solver and tolerances; a failure raises
    a `RuntimeError` with `simulate`'s message.

    **Arguments:**
    - `spec`, `t1`, `progress`: a `SceneSpec` (from `load_scene`), another end time (s)
      instead of the file's (checked as the command line's `--t1`, with the same words),
      and whether to show a progress bar.

    **Returns:** a `SceneResult`.
    """
    if t1 is not None:
        t1 = checked_end(spec.path, spec.t0, t1, "t1")
        check_extent(spec, t1)
    return scene_result(spec, build(spec, t1)[0].integrate(progress), t1)


def strict_json(summary: dict, reasons: dict) -> dict:
    """`summary`, non-finite numbers as `None`; `"not_computed"`: those and `reasons`' fields."""
    reasons = dict(reasons)

    def finite(key, x):
        if isinstance(x, list):
            return [finite(key, a) for a in x]
        if isinstance(x, float) and not np.isfinite(x):
            reasons.setdefault(key, f"not finite ({x}): the run overflowed")
            return None
        return x

    out = {k: finite(k, x) for k, x in summary.items()}
    return out | ({"not_computed": reasons} if reasons else {})


def _relative(deviation, scale, key, what, reasons):
    """`deviation / scale` and its largest magnitude (the summary's `key`); where `scale`
    is 0, `deviation` itself and `None`, with the reason recorded in `reasons[key]`."""
    if scale > 0:
        relative = deviation / scale
        return relative, float(np.max(np.abs(relative)))
    reasons[key] = f"{what} are zero throughout: no scale to divide by"
    return deviation, None


def scene_result(spec, run, t1=None) -> SceneResult:
    """The `SceneResult` of `run` (from `Program.integrate`) of `spec` up to `t1`."""
    scene, args, forced = spec.scene, None, spec.scene.has_forces
    ts = jnp.asarray(run.t)
    q, v = jax.vmap(scene.space.retract)(run.q, run.v) if forced else (run.q, run.v)
    energy = np.asarray(jax.vmap(scene.energy, (0, 0, 0, None))(ts, q, v, args))
    potential = np.asarray(jax.vmap(scene.potential, (0, 0, None))(ts, q, args))
    t = np.asarray(ts)
    e_s, W, reasons = None, None, {}
    if forced:  # at the start and the end of every segment: the solver's own steps
        e_s, W, error_t = energy[run.work_index], run.work, t[run.work_index]
        scale = max(np.max(np.abs(e_s)), np.max(np.abs(W)))
        key = "max_relative_work_energy_balance"
        error, worst = _relative(e_s - e_s[0] - W, scale, key, "the energy and the work", reasons)
        report = {
            "energy_report": "work-energy balance E(t) - E(0) - W(t)",
            key: worst,
            "balance_scale_J": float(scale),
            "work_done_J": float(W[-1]),
        }
    else:
        # Over the largest |T| + |V|, not |E(0)|: a run that starts at E = 0 (a pendulum
        # released level with its pivot) has an energy scale all the same.
        scale = np.max(np.abs(energy - potential) + np.abs(potential))
        key, what = "max_relative_energy_error", "the kinetic and potential energies"
        error_t = t
        error, worst = _relative(energy - energy[0], scale, key, what, reasons)
        report = {
            "energy_report": "energy error (E(t) - E(0)) / max(|T| + |V|)",
            key: worst,
            "energy_scale_J": float(scale),
        }
    q, v = jax.tree.map(np.asarray, (q, v))
    constraint = np.asarray(jax.vmap(constraint_error)(scene.spheres(q)))
    x = np.asarray(jax.vmap(scene.drawn_points)(q))
    base = {} if scene.base is None else {BASE: chain_parts(q)[0][-1].tolist()}
    adaptive = not spec.fixed_steps  # as the run decided (`build`)
    # the tolerances the run used (simulate's defaults for the state's dtype if unset)
    rtol, atol = tolerances(spec.rtol, spec.atol, constraint.dtype)
    end = float(spec.t1 if t1 is None else t1)
    step = None if adaptive else fixed_steps_taken(spec.t0, end, spec.save_dt, spec.dt0)[1]
    summary = {
        "scene": spec.name,
        "file": str(spec.path),
        "solver": spec.solver_name,
        **({"rtol": rtol, "atol": atol} if adaptive else {"dt0": spec.dt0, "max_step": step}),
        "n_spheres": scene.n,
        "effects": [type(e).__name__ for e in scene.effects],
        "t0": spec.t0,
        "t1": end,
        "steps": run.steps,
        "rejected_steps": run.rejected_steps,
        "wall_time_s": run.wall_time_s,
        "max_constraint_error": float(constraint.max()),
        **report,
        **base,
    }
    summary = strict_json(summary, reasons)
    return SceneResult(t, q, v, x, energy, error_t, error, constraint, summary, potential, W, e_s)
