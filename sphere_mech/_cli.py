"""The command line: `sphere-mech run [--out DIR]`."""

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _default_problem():
    import jax.numpy as jnp

    from ._chain import chain_pendulum
    from ._geometry import normalize, project

    system = chain_pendulum(jnp.array([1.0, 1.0]), jnp.array([1.0, 1.0]), g=9.81)
    q0 = normalize(jnp.array([[0.6, 0.0, -0.8], [0.0, 0.8, 0.6]]))
    v0 = project(q0, jnp.array([[0.0, 2.5, 0.0], [-2.0, 0.0, 1.0]]))
    return "double spherical pendulum", system, (q0, v0), 20.0


def _plot(path, t, x, energy_error, constraint):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(12, 4))
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    for i in range(x.shape[1]):
        ax.plot(x[:, i, 0], x[:, i, 1], x[:, i, 2], lw=0.6, label=f"mass {i + 1}")
    ax.set_title("paths of the masses")
    ax.legend(fontsize=7)
    for k, (values, title) in enumerate(
        [(np.abs(energy_error) + 1e-18, "|relative energy error|"),
         (constraint + 1e-18, "max_i | |q_i| - 1 |")]
    ):
        a = fig.add_subplot(1, 3, k + 2)
        a.semilogy(t, values, lw=0.8)
        a.set_xlabel("t [s]")
        a.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(out: Path) -> dict:
    import diffrax
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    from ._simulate import default_solver, simulate

    name, system, y0, t1 = _default_problem()
    y0 = tuple(jnp.asarray(a, dtype=jnp.float64) for a in y0)
    ts = jnp.linspace(0.0, t1, 2001)
    start = time.perf_counter()
    sol = simulate(system, y0, t1, saveat=diffrax.SaveAt(ts=ts), progress=True)
    jax.block_until_ready(sol.ys)
    wall = time.perf_counter() - start
    q, v = (np.asarray(a) for a in sol.ys)
    energy = np.asarray(jax.vmap(system.energy, (0, 0, 0, None))(ts, sol.ys[0], sol.ys[1], None))
    e_rel = (energy - energy[0]) / abs(energy[0])
    constraint = np.max(np.abs(np.linalg.norm(q, axis=-1) - 1.0), axis=-1)
    x = np.asarray(jax.vmap(system.positions)(sol.ys[0]))
    summary = {
        "scene": name,
        "solver": type(default_solver()).__name__ + "(" + type(default_solver().solver).__name__ + ")",
        "t1": float(t1),
        "steps": int(sol.stats["num_steps"]),
        "rejected_steps": int(sol.stats["num_rejected_steps"]),
        "wall_time_s": wall,
        "max_constraint_error": float(constraint.max()),
        "max_relative_energy_error": float(np.abs(e_rel).max()),
    }
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out) as tmp:
        tmp = Path(tmp)
        np.savez(tmp / "trajectory.npz", t=np.asarray(ts), q=q, v=v, x=x, energy=energy)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        _plot(tmp / "plot.png", np.asarray(ts), x, e_rel, constraint)
        for f in ("trajectory.npz", "summary.json", "plot.png"):
            os.replace(tmp / f, out / f)
    return summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="sphere-mech", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    p_run = sub.add_parser("run", help="simulate a scene and write results")
    p_run.add_argument("--out", type=Path, default=Path("sphere_mech_out"))
    ns = parser.parse_args(argv)
    summary = run(ns.out)
    print(f"{summary['scene']}: {summary['steps']} steps in {summary['wall_time_s']:.2f} s, "
          f"max constraint error {summary['max_constraint_error']:.1e}, "
          f"max relative energy error {summary['max_relative_energy_error']:.1e}")
    print(f"wrote {ns.out}/trajectory.npz, summary.json, plot.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
