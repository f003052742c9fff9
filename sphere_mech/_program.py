"""The integration program of `sphere-mech run`, and where it is kept.

A run integrates the scene segment by segment (at most `SEGMENTS`, each a whole number of
save intervals) with one compiled program that calls nothing back in Python: the
progress bar moves between segments, and a failure comes back as a result code that is
raised after the run with `simulate`'s message. It is traced in every run and compiled
through JAX's persistent compilation cache where the command line turned it on (a later
run of the same scene compiles nothing: JAX loads the executable it stored, keyed by the
traced program, so editing a comment or the `name` of a file does not recompile).

Each segment is `simulate`'s core (`_solve.solve`) from the state the previous one
reached. Adaptive solvers choose the segment's first step afresh, so their steps differ
from one `simulate` call's at the segment ends (the error per step is controlled as
there). Fixed steps divide each segment equally into as many steps as `dt0` fits: one
`simulate` call's steps when a segment holds whole steps (`save_dt` a multiple of `dt0`),
else steps slightly shorter than `dt0`.
"""

import dataclasses
import math
import time
from collections.abc import Callable

import jax
import numpy as np

SEGMENTS = 100
"""The most segments a run is cut into: the steps of the progress bar."""
_BAR = "{percentage:.2f}%|{bar}| [{elapsed}<{remaining}, {rate_fmt}{postfix}]"  # diffrax's


@dataclasses.dataclass
class Integrated:
    """What a run returns: the saved trajectory (numpy) and the solver's counts.

    **Attributes:**
    - `t`, `q`, `v`: the save times `(T,)` and states `(T, n, 3)` (where the scene's state
      is a dict (`sm.chain_space`), dicts of such arrays with a leading `T` axis).
    - `steps`, `rejected_steps`: the solver's steps (all segments).
    - `wall_time_s`: the time the segments took.
    - `work_index`, `work`: with forces (else `None`), the indices into `t` of the start
      and of every segment's end, `(segments + 1,)`, and the work of the forces done from
      the start to those times (`WithWork`: summed over the solver's own steps).
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    steps: int
    rejected_steps: int
    wall_time_s: float
    work_index: np.ndarray | None = None
    work: np.ndarray | None = None


@dataclasses.dataclass
class Program:
    """A compiled segment program and its inputs.

    `call(t_start, ts, q, v, params)` integrates from `(q, v)` at `t_start = ts[0]` to
    `ts[-1]`, saving at `ts`, and returns `(q_saved, v_saved, failed, code, steps,
    rejected)` plus, with forces, the work of the forces over the segment (states
    structured as the scene's: arrays, or dicts of arrays).

    **Attributes:**
    - `call`: the compiled program.
    - `ts`: the save times of each segment, `(segments, m + 1)`, padded with its end.
    - `count`: how many save times each row holds before the padding.
    - `q0`, `v0`: the initial state (arrays, or dicts of arrays); `params`: the scene's
      arrays.
    - `max_steps`: `[simulate] max_steps`, for all segments together, and
      `max_steps_code`, the result code of exceeding it.
    """

    call: Callable
    ts: np.ndarray
    count: np.ndarray
    q0: np.ndarray
    v0: np.ndarray
    params: list
    max_steps: int
    max_steps_code: int
    forced: bool

    def integrate(self, progress: bool = False) -> Integrated:
        """Run every segment (a progress bar on stderr with `progress`); raises a
        `RuntimeError` with `simulate`'s message if the run fails."""
        bar = _bar() if progress else None
        start, (t0, t1) = time.perf_counter(), (self.ts[0, 0], self.ts[-1, -1])
        q, v, parts, steps, rejected, code = self.q0, self.v0, [], 0, 0, None
        work = [0.0]
        for k, (ts, count) in enumerate(zip(self.ts, self.count, strict=True)):
            out = jax.tree.map(np.asarray, self.call(ts[0], ts, q, v, self.params))
            steps, rejected = steps + int(out[4]), rejected + int(out[5])
            if out[2] or steps > self.max_steps:
                code = int(out[3]) if out[2] else self.max_steps_code
                break
            first = 0 if k == 0 else 1  # a segment starts where the last one saved
            parts.append(_take(list(out[:2]), slice(first, count)))
            work += [work[-1] + float(out[6])] if self.forced else []
            q, v = _take(out[:2], count - 1)
            if bar is not None:
                bar.n = round(100 * float((ts[-1] - t0) / (t1 - t0)), 2)
                bar.refresh()
        if bar is not None:
            bar.close()
        if code is not None:
            from ._results import raise_on_codes

            raise_on_codes(np.array([code]), self.max_steps, "simulate")
        t = np.concatenate(
            [ts[(k > 0) : c] for k, (ts, c) in enumerate(zip(self.ts, self.count, strict=True))]
        )
        joined = jax.tree.map(lambda *x: np.concatenate(x), *parts)
        ends = np.concatenate([[0], np.cumsum(self.count - 1)]) if self.forced else None
        return Integrated(
            t,
            *joined,
            steps,
            rejected,
            time.perf_counter() - start,
            ends,
            np.array(work) if self.forced else None,
        )


def _take(tree, index):
    """`x[index]` for every array of `tree`."""
    return jax.tree.map(lambda x: x[index], tree)


def _bar():
    import tqdm

    return tqdm.tqdm(total=100, unit="%", bar_format=_BAR)


def segment_times(t0: float, t1: float, save_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The save times `linspace(t0, t1, T)` (`T - 1` intervals of about `save_dt`, at
    least one) cut into at most `SEGMENTS` rows of `m + 1` (a row starts where the
    previous one ends; the last is padded with `t1`), and the count of each row."""
    import jax.numpy as jnp

    n_out = max(2, int(round((t1 - t0) / save_dt)) + 1)
    ts = np.asarray(jnp.linspace(t0, t1, n_out))
    m = math.ceil((n_out - 1) / SEGMENTS)
    starts = range(0, n_out - 1, m)
    rows = [np.pad(ts[s : s + m + 1], (0, max(0, s + m + 1 - n_out)), mode="edge") for s in starts]
    return np.stack(rows), np.array([min(m + 1, n_out - s) for s in starts])


def build(spec, t1=None) -> tuple[Program, jax.stages.Compiled]:
    """Trace and compile the segment program of a scene file (`load_scene`'s
    `SceneSpec`), optionally up to another end time `t1`.

    **Returns:** the `Program` and the compiled program.
    """
    import diffrax
    import equinox as eqx
    import jax.numpy as jnp

    from ._misc import tree_dtype
    from ._results import RESULTS, code, failed
    from ._solve import prepare, solve, times
    from ._solvers.work import WithWork, work_done

    ts, count = segment_times(spec.t0, float(spec.t1 if t1 is None else t1), spec.save_dt)
    run = prepare(
        spec.scene,
        spec.y0,
        t0=spec.t0,
        t1=ts[-1, -1],
        solver=spec.solver,
        dt0=spec.dt0,
        rtol=spec.rtol,
        atol=spec.atol,
        max_steps=spec.max_steps,
    )
    scene, (q0, v0), opts = run.system, run.y0, run.opts
    dynamic, static = eqx.partition(scene, eqx.is_array)
    params, treedef = jax.tree.flatten(dynamic)

    def segment(t_start, ts, q, v, params):
        system = eqx.combine(jax.tree.unflatten(treedef, params), static)
        forced = system.has_forces  # the work of the forces, summed over the steps
        solver = WithWork(opts.solver) if forced else opts.solver
        saveat = diffrax.SaveAt(ts=ts, solver_state=forced)
        t_start, t_end, dt0 = times(tree_dtype((q, v)), t_start, ts[-1], spec.dt0)
        if isinstance(opts.controller, diffrax.ConstantStepSize):  # diffrax divides a
            # segment into equal steps: as many as dt0 fits, the save times' rounding aside
            dt0 = (t_end - t_start) / jnp.ceil((t_end - t_start) / dt0 * (1 - 1e-12))
        sol = solve(
            system,
            (q, v),
            t_start,
            t_end,
            dt0,
            None,
            eqx.tree_at(lambda o: (o.saveat, o.solver), opts, (saveat, solver)),
        )
        result = code(sol.result)
        work = (work_done(sol.solver_state),) if forced else ()
        return (
            *sol.ys,
            failed(result),
            result,
            sol.stats["num_steps"],
            sol.stats["num_rejected_steps"],
            *work,
        )

    inputs = (ts[0, 0], ts[0], *jax.tree.map(np.asarray, (q0, v0)), [np.asarray(p) for p in params])
    compiled = jax.jit(segment).lower(*inputs).compile()
    program = Program(
        compiled,
        ts,
        count,
        *inputs[2:],
        spec.max_steps,
        int(code(RESULTS.max_steps_reached)),
        scene.has_forces,
    )
    return program, compiled


def flat(name: str, tree) -> dict[str, np.ndarray]:
    """The arrays of a state named for an `.npz` file: `{name: x}` for an array, and
    `{"name.key": x[key]}` for a dict of arrays (a state on a product space)."""
    if isinstance(tree, dict):
        return {f"{name}.{k}": np.asarray(x) for k, x in tree.items()}
    return {name: np.asarray(tree)}
