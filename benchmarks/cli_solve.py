"""Solve time of `sphere-mech run` against `sm.simulate` on every example scene.

For each `examples/*.toml`: the command line's integration program (`_program.build`,
compiled first, then `Program.integrate`: every segment, the work of the forces included)
against `sm.simulate` with the file's solver, tolerances and `max_steps`, saving at the
same times (`SaveAt(ts=...)`, compiled first, `block_until_ready`). Medians of
`--repeats` runs (default 3) in one process. Prints a markdown table and writes
benchmarks/results/cli_solve.md.

    python benchmarks/cli_solve.py [--repeats 3] [scenes ...]
"""

import argparse
import os
import pathlib
import platform
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import numpy as np  # noqa: E402

import sphere_mech as sm  # noqa: E402
from sphere_mech._program import build  # noqa: E402
from sphere_mech._scene_files import load_scene  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def median_time(run, repeats: int) -> float:
    run()  # compile / warm up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def scene_times(path: pathlib.Path, repeats: int) -> tuple[float, float, int]:
    spec = load_scene(path)
    program = build(spec)[0]
    cli = median_time(lambda: program.integrate(), repeats)
    ts = np.concatenate(
        [row[(k > 0) : c] for k, (row, c) in enumerate(zip(program.ts, program.count, strict=True))]
    )

    def simulate():
        sol = sm.simulate(
            spec.scene,
            spec.y0,
            spec.t1,
            t0=spec.t0,
            solver=spec.solver,
            dt0=spec.dt0,
            rtol=spec.rtol,
            atol=spec.atol,
            max_steps=spec.max_steps,
            saveat=diffrax.SaveAt(ts=ts),
        )
        jax.block_until_ready(sol.ys)

    return cli, median_time(simulate, repeats), len(program.ts)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("scenes", nargs="*", type=pathlib.Path)
    ns = parser.parse_args()
    scenes = ns.scenes or sorted((ROOT / "examples").glob("*.toml"))
    rows, load = [], [os.getloadavg()[0]]
    for path in scenes:
        cli, simulate, segments = scene_times(path, ns.repeats)
        forced = load_scene(path).scene.has_forces
        rows.append(
            f"| {path.name} | {'yes' if forced else 'no'} | {segments} | {cli:.3f} | "
            f"{simulate:.3f} | {cli / simulate:.1f} |"
        )
        print(rows[-1], flush=True)
        load.append(os.getloadavg()[0])
    machine = (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"load average {min(load):.1f}-{max(load):.1f} during the runs"
    )
    table = "\n".join(
        [
            f"Solve time of `sphere-mech run` against `sm.simulate`, medians of {ns.repeats} "
            f"runs after compiling; {machine}.",
            "",
            "| scene | forces | segments | command line (s) | sm.simulate (s) | ratio |",
            "|---|---|---|---|---|---|",
            *rows,
            "",
        ]
    )
    print(table)
    if not ns.scenes:
        RESULTS.mkdir(exist_ok=True)
        (RESULTS / "cli_solve.md").write_text(table)


if __name__ == "__main__":
    main()
