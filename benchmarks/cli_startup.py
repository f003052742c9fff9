"""Start-up of `sphere-mech run` on the default scene: the first run in a row (an empty
cache folder: trace, compile) against the second (trace, every program from JAX's
persistent compilation cache), each in a fresh process.

Measured from just before the process is started to the first output of the progress
bar (printed when the first segment of the integration is dispatched: "time to first
step"), and to the process's exit (total, with plot.png and animation.html written).
The pairs run alternately, each with a fresh cache folder; the table gives medians and
the ratio second / first of the same pairs. Prints a markdown table and writes
benchmarks/results/cli_startup.{md,png} (the figure: every pair's times).

    python benchmarks/cli_startup.py [--repeats 5]
"""

import argparse
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import threading
import time

from _harness import load, machine, publish, pyplot, save_figure, table

ROOT = pathlib.Path(__file__).resolve().parents[1]
COMMAND = "import sys; from sphere_mech._cli import console_main; sys.exit(console_main())"


def timed_run(cache: pathlib.Path, out: pathlib.Path) -> tuple[float, float]:
    """One `sphere-mech run` of the default scene: (time to first step, total) in s."""
    env = {
        **os.environ,
        "SPHERE_MECH_CACHE_DIR": str(cache),
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
    }
    env.pop("EQX_ON_ERROR", None)
    first = []
    start = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-c", COMMAND, "run", "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=env,
    )

    def watch():  # the bar's first frame, "0.00%|", marks the first segment
        seen = b""
        while chunk := proc.stderr.read1(4096):
            seen += chunk
            if not first and b"%|" in seen:
                first.append(time.perf_counter() - start)

    reader = threading.Thread(target=watch)
    reader.start()
    status = proc.wait(timeout=600)
    total = time.perf_counter() - start
    reader.join()
    if status != 0 or not first:
        raise RuntimeError(f"sphere-mech run failed (status {status})")
    return first[0], total


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    repeats = parser.parse_args().repeats
    rows = {"first": [], "second": []}
    loads = [load()]
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeats):
            cache, out = pathlib.Path(tmp) / f"cache{k}", pathlib.Path(tmp) / f"out{k}"
            for run in ("first", "second"):
                rows[run].append(timed_run(cache, out))
                print(
                    f"repeat {k + 1}/{repeats} {run}: first step {rows[run][-1][0]:.2f} s, "
                    f"total {rows[run][-1][1]:.2f} s",
                    file=sys.stderr,
                )
            loads.append(load())
    med = {run: [statistics.median(r[i] for r in rows[run]) for i in (0, 1)] for run in rows}
    ratio = [
        statistics.median(b[i] / a[i] for a, b in zip(rows["first"], rows["second"], strict=True))
        for i in (0, 1)
    ]
    publish(
        f"`sphere-mech run` (default scene), medians of {repeats} pairs; {machine(loads)}.\n\n"
        + table(
            ["run", "time to first step (s)", "total (s)"],
            [
                *((run, f"{med[run][0]:.2f}", f"{med[run][1]:.2f}") for run in rows),
                ("second / first", f"{ratio[0]:.2f}", f"{ratio[1]:.2f}"),
            ],
        )
        + "\n",
        "cli_startup.md",
    )
    fig, axes = pyplot().subplots(1, 2, figsize=(8, 3.5), sharey=True)
    for ax, i, what in zip(axes, (0, 1), ("time to first step", "total"), strict=True):
        for run, color in (("first", "C3"), ("second", "C0")):
            times = [r[i] for r in rows[run]]
            ax.plot(range(1, repeats + 1), times, "o-", color=color, label=f"{run} run")
        ax.set(xlabel="pair", title=what, ylim=(0, None))
    axes[0].set_ylabel("seconds from process start")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"sphere-mech run, default scene; {machine(loads)}", fontsize=8)
    save_figure(fig, "cli_startup.png")


if __name__ == "__main__":
    main()
