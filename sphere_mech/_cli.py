"""The command line: `sphere-mech run [SCENE.toml] [--out DIR]`.

Runs a scene file (data only, see the README's "Scenes") or, with no file, the packaged
default scene (a double spherical pendulum, 20 s), and writes `trajectory.npz`,
`summary.json` and `plot.png` to the output folder. Files are written under temporary
names and renamed, so a failing run loses nothing already there. Problems in the scene
file give one line `sphere-mech: error: <file>: <field>: <expected>` and exit status 2.
"""

import argparse
import contextlib
import importlib.resources
import json
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

PROG = "sphere-mech"


def _plot(path, result):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x, s = result.x, result.summary
    fig = plt.figure(figsize=(13, 4))
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    for i in range(x.shape[1]):
        label = f"mass {i}" if x.shape[1] <= 8 else None
        ax.plot(x[:, i, 0], x[:, i, 1], x[:, i, 2], lw=0.6, label=label)
    ax.set_title(f"{s['scene']}: paths of the masses", fontsize=9)
    if x.shape[1] <= 8:
        ax.legend(fontsize=7)
    forced = "max_relative_work_energy_balance" in s
    title = "|E - E(0) - W| / scale" if forced else "|E - E(0)| / |E(0)|"
    eps = np.finfo(np.float64).eps
    for k, (t, values, name) in enumerate(
        [(result.error_t, np.abs(result.error), title),
         # running maximum: the constraint error sits at rounding level, often exactly 0
         (result.t, np.maximum.accumulate(result.constraint),
          "max_i | |q_i| - 1 | (running maximum)")]
    ):
        a = fig.add_subplot(1, 3, k + 2)
        a.semilogy(t, np.maximum(values, eps / 100), lw=0.8)  # exact zeros drawn at eps/100
        if k == 1:
            a.axhline(eps, color="gray", lw=0.6, ls="--", label="float64 epsilon")
            a.set_ylim(eps / 300, max(1e-12, a.get_ylim()[1]))
            a.legend(fontsize=7)
        a.set_xlabel("t [s]")
        a.set_title(name, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_outputs(out: Path, result) -> None:
    """Write the three result files to `out`, each under a temporary name first."""
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out, prefix=".sphere-mech-") as tmp:
        tmp = Path(tmp)
        np.savez(tmp / "trajectory.npz", t=result.t, q=result.q, v=result.v, x=result.x,
                 energy=result.energy, error_t=result.error_t, error=result.error)
        (tmp / "summary.json").write_text(json.dumps(result.summary, indent=2) + "\n")
        _plot(tmp / "plot.png", result)
        for name in ("trajectory.npz", "summary.json", "plot.png"):
            os.replace(tmp / name, out / name)


@contextlib.contextmanager
def _scene_path(scene):
    if scene is not None:
        yield Path(scene)
        return
    resource = importlib.resources.files("sphere_mech") / "scenes" / "default.toml"
    with importlib.resources.as_file(resource) as path:
        yield path


def _print_summary(s: dict, out: Path) -> None:
    if "max_relative_energy_error" in s:
        energy = f"max relative energy error {s['max_relative_energy_error']:.1e}"
    else:
        energy = f"max work-energy balance {s['max_relative_work_energy_balance']:.1e} (relative)"
    print(f"{s['scene']}: {s['t1']:g} s, {s['solver']}, {s['steps']} steps in "
          f"{s['wall_time_s']:.2f} s; max constraint error {s['max_constraint_error']:.1e}; "
          f"{energy}")
    print(f"wrote {out}/trajectory.npz, summary.json, plot.png")


def run(scene=None, out=Path("sphere_mech_out"), *, duration=None, progress=True):
    """Run a scene file (default: the packaged default scene); returns the summary."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from ._scene.files import load_scene
    from ._scene.report import run_scene

    with _scene_path(scene) as path:
        spec = load_scene(path)
    result = run_scene(spec, duration=duration, progress=progress)
    write_outputs(Path(out), result)
    return result.summary


def _fail(message: str, status: int) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return status


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_run = sub.add_parser("run", help="simulate a scene file and write results")
    p_run.add_argument("scene", nargs="?", help="a scene file (.toml); default: the "
                       "packaged double spherical pendulum")
    p_run.add_argument("--out", type=Path, default=Path("sphere_mech_out"),
                       help="output folder (default ./sphere_mech_out)")
    p_run.add_argument("--duration", type=float, default=None,
                       help="override the scene's duration (s)")
    p_run.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    ns = parser.parse_args(argv)
    if ns.duration is not None and not ns.duration > 0:
        return _fail(f"--duration: expected a positive time in s, got {ns.duration}", 2)
    from ._scene.files import SceneFileError

    try:
        summary = run(ns.scene, ns.out, duration=ns.duration, progress=not ns.no_progress)
    except SceneFileError as e:
        return _fail(str(e), 2)
    except Exception as e:  # the solver failed: one line, keep earlier outputs
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        return _fail(f"{ns.scene or 'default scene'}: simulation failed: {first}", 1)
    _print_summary(summary, ns.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
