"""The integration program of `sphere-mech run`, and where it is kept.

A run integrates the scene segment by segment (at most `SEGMENTS`, each a whole number of
save intervals) with one compiled program that calls nothing back in Python: the
progress bar moves between segments, and a failure comes back as a result code that is
raised after the run with `simulate`'s message. Such a program can be stored: with a
cache folder the compiled program is written to `<folder>/programs/<key>.bin` (with its
inputs in `<key>.npz`), `key` a hash of the scene file's bytes, `--t1`, the package's
source and the versions of JAX and its libraries, and a later run of the same file loads
it and starts integrating before importing diffrax or tracing anything.

Each segment is `simulate`'s core (`_solve.solve`) from the state the previous one
reached. Adaptive solvers choose the segment's first step afresh, so their steps differ
from one `simulate` call's at the segment ends (the error per step is controlled as
there). Fixed steps divide each segment equally into as many steps as `dt0` fits: one
`simulate` call's steps when a segment holds whole steps (`save_dt` a multiple of `dt0`),
else steps slightly shorter than `dt0`.
"""

import dataclasses
import hashlib
import importlib.metadata
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

SEGMENTS = 100
"""The most segments a run is cut into: the steps of the progress bar."""
LIBRARIES = ("jax", "jaxlib", "diffrax", "equinox", "optimistix", "lineax", "numpy")
"""The libraries whose versions are part of a stored program's key."""
_BAR = "{percentage:.2f}%|{bar}| [{elapsed}<{remaining}, {rate_fmt}{postfix}]"  # diffrax's


@dataclasses.dataclass
class Integrated:
    """What a run returns: the saved trajectory (numpy) and the solver's counts.

    **Attributes:**
    - `t`, `q`, `v`: the save times `(T,)` and states `(T, n, 3)` (where the scene's state
      is a dict, dicts of such arrays with a leading `T` axis, e.g. `{"base": (T, m),
      "spheres": (T, n, 3)}`).
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
            from .._results import raise_on_codes

            raise_on_codes(np.array([code]), self.max_steps, "simulate")
        t = np.concatenate([ts[(k > 0):c] for k, (ts, c) in
                            enumerate(zip(self.ts, self.count, strict=True))])
        joined = jax.tree.map(lambda *x: np.concatenate(x), *parts)
        ends = np.concatenate([[0], np.cumsum(self.count - 1)]) if self.forced else None
        return Integrated(t, *joined, steps, rejected, time.perf_counter() - start, ends,
                          np.array(work) if self.forced else None)


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
    rows = [np.pad(ts[s:s + m + 1], (0, max(0, s + m + 1 - n_out)), mode="edge")
            for s in starts]
    return np.stack(rows), np.array([min(m + 1, n_out - s) for s in starts])


def build(spec, t1=None) -> tuple[Program, jax.stages.Compiled]:
    """Trace and compile the segment program of a scene file (`load_scene`'s
    `SceneSpec`), optionally up to another end time `t1`.

    **Returns:** the `Program` and the compiled program (for `store`).
    """
    import diffrax
    import equinox as eqx
    import jax.numpy as jnp

    from .._results import RESULTS, code, failed
    from .._solve import as_arrays, initial_state, options, solve, state_dtype, times
    from .._solvers.work import WithWork, work_done

    scene = as_arrays(spec.scene)
    scene.check_size(spec.y0[0])
    q0, v0 = initial_state(scene.space, scene.state_name, spec.y0)
    dynamic, static = eqx.partition(scene, eqx.is_array)
    params, treedef = jax.tree.flatten(dynamic)
    ts, count = segment_times(spec.t0, float(spec.t1 if t1 is None else t1), spec.save_dt)
    opts = options(spec.solver, spec.dt0, spec.rtol, spec.atol, None, None, spec.max_steps,
                   None, False, None, state_dtype((q0, v0)))

    def segment(t_start, ts, q, v, params):
        system = eqx.combine(jax.tree.unflatten(treedef, params), static)
        forced = system.has_forces  # the work of the forces, summed over the steps
        solver = WithWork(opts.solver) if forced else opts.solver
        saveat = diffrax.SaveAt(ts=ts, solver_state=forced)
        t_start, t_end, dt0 = times(state_dtype((q, v)), t_start, ts[-1], spec.dt0)
        if isinstance(opts.controller, diffrax.ConstantStepSize):  # diffrax divides a
            # segment into equal steps: as many as dt0 fits, the save times' rounding aside
            dt0 = (t_end - t_start) / jnp.ceil((t_end - t_start) / dt0 * (1 - 1e-12))
        sol = solve(system, (q, v), t_start, t_end, dt0, None,
                    eqx.tree_at(lambda o: (o.saveat, o.solver), opts, (saveat, solver)))
        result = code(sol.result)
        work = (work_done(sol.solver_state),) if forced else ()
        return (*sol.ys, failed(result), result, sol.stats["num_steps"],
                sol.stats["num_rejected_steps"], *work)

    inputs = (ts[0, 0], ts[0], *jax.tree.map(np.asarray, (q0, v0)),
              [np.asarray(p) for p in params])
    compiled = jax.jit(segment).lower(*inputs).compile()
    program = Program(compiled, ts, count, *inputs[2:], spec.max_steps,
                      int(code(RESULTS.max_steps_reached)), scene.has_forces)
    return program, compiled


def key(path, t1=None) -> str | None:
    """The name of a scene file's stored program: a hash of the file's bytes, `t1`, the
    package's source, the libraries' versions and the device; `None` if the file
    cannot be read (`load_scene` then says why)."""
    try:
        digest = hashlib.sha256(Path(path).read_bytes())
    except OSError:
        return None
    package = Path(__file__).resolve().parents[1]
    for file in sorted(package.rglob("*.py")):
        digest.update(f"{file.relative_to(package)}\0".encode() + file.read_bytes())
    versions = [f"{lib}={importlib.metadata.version(lib)}" for lib in LIBRARIES]
    device = jax.devices()[0]
    digest.update(repr((t1, versions, device.platform, device.device_kind,
                        jax.config.jax_enable_x64)).encode())
    return digest.hexdigest()[:32]


def _files(folder: Path, name: str) -> tuple[Path, Path]:
    return folder / "programs" / f"{name}.npz", folder / "programs" / f"{name}.bin"


def store(folder: Path, name: str, program: Program, compiled) -> bool:
    """Write a program for `load` (not one that calls back to Python, e.g. with
    `EQX_ON_ERROR=raise`: such a program only runs in the process that compiled it).

    **Returns:** whether it was written.
    """
    from jax.experimental.serialize_executable import serialize

    if "callback" in compiled.as_text():
        return False
    payload, in_tree, out_tree = serialize(compiled)
    if (in_tree, out_tree) != _trees(program):
        return False
    arrays, binary = _files(folder, name)
    params = {f"param{i}": p for i, p in enumerate(program.params)}
    try:  # a folder that cannot be written keeps nothing, as JAX's cache
        arrays.parent.mkdir(parents=True, exist_ok=True)
        for path, write in ((arrays, lambda f: np.savez(
                f, ts=program.ts, count=program.count, **flat("q0", program.q0),
                **flat("v0", program.v0),
                steps=[program.max_steps, program.max_steps_code, program.forced],
                **params)), (binary, lambda f: f.write(payload))):
            partial = path.with_name(f"{path.name}.{os.getpid()}.tmp")
            with open(partial, "wb") as f:
                write(f)
            os.replace(partial, path)
    except OSError:
        return False
    return True


def _trees(program: Program):
    state = (program.q0, program.v0)
    inputs = (program.ts[0, 0], program.ts[0], *state, program.params)
    outputs = (*state, 0, 0, 0, 0, *((0,) if program.forced else ()))
    return jax.tree.structure((inputs, {})), jax.tree.structure(outputs)


def flat(name: str, tree) -> dict[str, np.ndarray]:
    """The arrays of a state named for an `.npz` file: `{name: x}` for an array, and
    `{"name.key": x[key]}` for a dict of arrays (a state on a product space)."""
    if isinstance(tree, dict):
        return {f"{name}.{k}": np.asarray(x) for k, x in tree.items()}
    return {name: np.asarray(tree)}


def unflat(data, name: str):
    """The state `flat` named `name` in an `.npz` file's `data`."""
    keys = [f.removeprefix(f"{name}.") for f in data.files if f.startswith(f"{name}.")]
    return {k: data[f"{name}.{k}"] for k in keys} if keys else data[name]


def load(folder: Path, name: str) -> Program | None:
    """The program `store` wrote under `name`, ready to run; `None` if there is none."""
    from jax.experimental.serialize_executable import deserialize_and_load

    arrays, binary = _files(folder, name)
    if not (arrays.exists() and binary.exists()):
        return None
    try:
        with np.load(arrays) as data:
            params = [data[f"param{i}"] for i in
                      range(sum(f.startswith("param") for f in data.files))]
            max_steps, max_steps_code, forced = (int(x) for x in data["steps"])
            program = Program(None, data["ts"], data["count"], unflat(data, "q0"),
                              unflat(data, "v0"), params, max_steps, max_steps_code,
                              bool(forced))
        program.call = deserialize_and_load(binary.read_bytes(), *_trees(program))
    except Exception:  # unreadable (e.g. written by another jaxlib build): compile again
        return None
    return program
