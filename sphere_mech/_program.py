"""The program of `sphere-mech run`: `_solve.solve` over at most `SEGMENTS` segments of whole
save intervals (the progress bar's steps), compiled once (keyed by the traced program: a file's
comments or `name` do not recompile). Adaptive solvers choose each segment's first step afresh;
fixed steps: segments of whole steps of `dt0` (`simulate`'s) where save times allow it."""

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
    """What a run returns: save times `t (T,)`, states `q`, `v` (`(T, n, 3)`, or dicts of
    such arrays), the solver's steps over all segments, the segments' wall time and, with
    forces (else `None`), the indices into `t` of the start and every segment's end with the
    work of the forces from the start to those times (`WithWork`: summed over the steps)."""

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
    """A compiled segment program and its inputs. `call(t_start, ts, q, v, params)` saves at
    `ts` from `(q, v)` at `t_start = ts[0]`: `(q_saved, v_saved, failed, code, steps,
    rejected[, work])`. `ts` holds each segment's save times `(segments, m + 1)` padded with
    its end, `count` how many are not padding; `max_steps` counts all segments together
    (`max_steps_code`: the code of exceeding it)."""

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
        """Run every segment; a failure raises `simulate`'s `RuntimeError`."""
        bar = None
        if progress:
            import tqdm

            bar = tqdm.tqdm(total=100, unit="%", bar_format=_BAR)
        start, (t0, t1) = time.perf_counter(), (self.ts[0, 0], self.ts[-1, -1])
        q, v, parts, steps, rejected, code, work = self.q0, self.v0, [], 0, 0, None, [0.0]
        for k, (ts, count) in enumerate(zip(self.ts, self.count, strict=True)):
            out = jax.tree.map(np.asarray, self.call(ts[0], ts, q, v, self.params))
            steps, rejected = steps + int(out[4]), rejected + int(out[5])
            if out[2] or steps > self.max_steps:
                code = int(out[3]) if out[2] else self.max_steps_code
                break
            first = 0 if k == 0 else 1  # a segment starts where the last one saved
            parts.append(_take([ts, *out[:2]], slice(first, count)))
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
        joined = jax.tree.map(lambda *x: np.concatenate(x), *parts)  # t, q, v
        elapsed = time.perf_counter() - start
        ends = np.concatenate([[0], np.cumsum(self.count - 1)]) if self.forced else None
        work = np.array(work) if self.forced else None
        return Integrated(*joined, steps, rejected, elapsed, ends, work)


def _take(tree, index):
    return jax.tree.map(lambda x: x[index], tree)


def segment_times(
    t0: float, t1: float, save_dt: float, dt0: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """`linspace(t0, t1, T)` (steps of about `save_dt`) in at most `SEGMENTS` rows of `m + 1`
    (each starts where the last ended; the last padded with `t1`), and each row's count.
    With fixed steps of `dt0`, `m` is the fewest save intervals (at least the bar's) that
    hold a whole number of steps (`simulate`'s steps), else that hold at least one."""
    import jax.numpy as jnp

    n_out = max(2, int(round((t1 - t0) / save_dt)) + 1)
    ts = np.asarray(jnp.linspace(t0, t1, n_out))
    m = math.ceil((n_out - 1) / SEGMENTS)
    if dt0 is not None:
        m = _whole_steps(m, n_out - 1, (t1 - t0) / (n_out - 1) / dt0)
    starts = range(0, n_out - 1, m)
    rows = [np.pad(ts[s : s + m + 1], (0, max(0, s + m + 1 - n_out)), mode="edge") for s in starts]
    return np.stack(rows), np.array([min(m + 1, n_out - s) for s in starts])


def _whole_steps(m: int, intervals: int, ratio: float, search: int = 10_000) -> int:
    """The fewest save intervals `k >= m` (at most `intervals`) whose span `k ratio` (in
    steps) is a whole number of steps to rounding (searched up to `m + search`), else the
    fewest that span at least one step. Before, a segment shorter than `dt0` took shorter
    steps, so a run's steps depended on its end time (`--t1`)."""
    for k in range(m, min(intervals, m + search) + 1):
        steps = k * ratio
        if steps >= 1 - 1e-9 and abs(steps - round(steps)) <= 1e-9 * steps:
            return k
    return min(intervals, max(m, math.ceil(1 / ratio - 1e-9)))


def fixed_step_count(span, dt0):
    """How many equal fixed steps a segment of length `span` takes: as many as `dt0` fits
    (to rounding). Operators only: NumPy floats where a scene file is checked, traced
    arrays in the run."""
    return -(-(span / dt0 * (1 - 1e-12)) // 1)  # the ceiling


def fixed_steps_taken(t0: float, t1: float, save_dt: float, dt0: float) -> tuple[int, float, int]:
    """How many fixed steps a run from `t0` to `t1` takes (each segment as many equal ones
    as `dt0` fits), the longest (`dt0` where the segments hold whole steps), and in how
    many segments."""
    rows = segment_times(t0, t1, save_dt, dt0)[0]
    spans = rows[:, -1] - rows[:, 0]
    counts = fixed_step_count(spans, dt0)
    return int(np.sum(counts)), float(np.max(spans / counts)), len(rows)


def build(spec, t1=None) -> tuple[Program, jax.stages.Compiled]:
    """The `Program` of a `SceneSpec` (to another end time `t1`) and its compiled program."""
    import diffrax
    import equinox as eqx

    from ._misc import tree_dtype
    from ._results import RESULTS, code, failed
    from ._solve import prepare, solve, times
    from ._solvers.work import WithWork, work_done

    end = float(spec.t1 if t1 is None else t1)
    ts, count = segment_times(spec.t0, end, spec.save_dt, spec.dt0 if spec.fixed_steps else None)
    options = dict(solver=spec.solver, dt0=spec.dt0, rtol=spec.rtol, atol=spec.atol)
    options |= dict(t0=spec.t0, t1=ts[-1, -1], max_steps=spec.max_steps)
    run = prepare(spec.scene, spec.y0, **options)
    scene, (q0, v0), opts = run.system, run.y0, run.opts
    dynamic, static = eqx.partition(scene, eqx.is_array)
    params, treedef = jax.tree.flatten(dynamic)

    def segment(t_start, ts, q, v, params):
        system = eqx.combine(jax.tree.unflatten(treedef, params), static)
        forced = system.has_forces
        solver = WithWork(opts.solver) if forced else opts.solver
        saveat = diffrax.SaveAt(ts=ts, solver_state=forced)
        t_start, t_end, dt0 = times(tree_dtype((q, v)), t_start, ts[-1], spec.dt0)
        if isinstance(opts.controller, diffrax.ConstantStepSize):
            dt0 = (t_end - t_start) / fixed_step_count(t_end - t_start, dt0)
        segment_opts = eqx.tree_at(lambda o: (o.saveat, o.solver), opts, (saveat, solver))
        sol = solve(system, (q, v), t_start, t_end, dt0, None, segment_opts)
        result = code(sol.result)
        work = (work_done(sol.solver_state),) if forced else ()
        counts = sol.stats["num_steps"], sol.stats["num_rejected_steps"]
        return (*sol.ys, failed(result), result, *counts, *work)

    inputs = (ts[0, 0], ts[0], *jax.tree.map(np.asarray, (q0, v0)), [np.asarray(p) for p in params])
    compiled = jax.jit(segment).lower(*inputs).compile()
    args = (*inputs[2:], spec.max_steps, int(code(RESULTS.max_steps_reached)), scene.has_forces)
    return Program(compiled, ts, count, *args), compiled


def flat(name: str, tree) -> dict[str, np.ndarray]:
    """A state's arrays named for an `.npz` file: `{name: x}`, or `{"name.key": x[key]}`."""
    if isinstance(tree, dict):
        return {f"{name}.{k}": np.asarray(x) for k, x in tree.items()}
    return {name: np.asarray(tree)}
