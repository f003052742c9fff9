"""Solve time of `sphere-mech run` against `sm.simulate` on every example scene.

For each `examples/*.toml`: the command line's integration program (`_program.build`,
compiled first, then `Program.integrate`: every segment, the work of the forces included)
against `sm.simulate` with the file's solver, tolerances and `max_steps`, saving at the
same times (`SaveAt(ts=...)`, compiled first, `block_until_ready`). Medians (and minima)
of `--repeats` runs (default 3) in one process, neither compiling again. Prints a
markdown table and writes benchmarks/results/cli_solve.{md,png} (all scenes only).

    python benchmarks/cli_solve.py [--repeats 3] [scenes ...]
"""

import argparse
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import diffrax  # noqa: E402
import numpy as np  # noqa: E402
from _harness import bars, load, machine, publish, pyplot, save_figure, table, timing  # noqa: E402

import sphere_mech as sm  # noqa: E402
from sphere_mech._program import build  # noqa: E402
from sphere_mech._scene_files import load_scene  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def scene_times(path: pathlib.Path, repeats: int):
    """`(Timing of the command line, Timing of sm.simulate, segments)` of one scene."""
    spec = load_scene(path)
    program = build(spec)[0]
    cli = timing(lambda: program.integrate(), repeats, what=f"{path.name}: command line")
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
        return sol.ys

    return cli, timing(simulate, repeats, what=f"{path.name}: sm.simulate"), len(program.ts)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("scenes", nargs="*", type=pathlib.Path)
    ns = parser.parse_args()
    scenes = ns.scenes or sorted((ROOT / "examples").glob("*.toml"))
    rows, loads, medians = [], [load()], []
    for path in scenes:
        cli, simulate, segments = scene_times(path, ns.repeats)
        medians.append((path.stem, cli.median, simulate.median))
        forced = load_scene(path).scene.has_forces
        rows.append(
            (
                path.name,
                "yes" if forced else "no",
                segments,
                f"{cli.median:.3f}",
                f"{simulate.median:.3f}",
                f"{cli.median / simulate.median:.1f}",
                f"{cli.min:.3f} / {simulate.min:.3f}",
            )
        )
        print(" | ".join(map(str, rows[-1])), flush=True)
        loads.append(load())
    columns = ["scene", "forces", "segments", "command line (s)", "sm.simulate (s)", "ratio"]
    publish(
        f"Solve time of `sphere-mech run` against `sm.simulate`, medians of {ns.repeats} "
        f"runs after compiling; {machine(loads)}.\n\n"
        + table([*columns, "minima (s)"], rows)
        + "\n",
        None if ns.scenes else "cli_solve.md",
    )
    if not ns.scenes:
        fig, ax = pyplot().subplots(figsize=(8, 3.8))
        series = {
            "sphere-mech run (integration)": [m[1] for m in medians],
            "sm.simulate": [m[2] for m in medians],
        }
        bars(ax, [m[0] for m in medians], series, rotation=20)
        ax.set(yscale="log", ylabel="solve time after compiling (s)")
        ax.set_title(machine(loads), fontsize=8)
        save_figure(fig, "cli_solve.png")


if __name__ == "__main__":
    main()
