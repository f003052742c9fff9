"""Scaling of `sm.simulate_batch` (and of a `jax.grad` through it) over devices and processes.

The same batch of chain pendulums (RK4, fixed step dt = 1e-3, float64 on CPU, float32 on a
GPU) is integrated by one worker process per configuration:

- 1 device in 1 process (the baseline);
- for each k of `--k`: k devices in 1 process (`--xla_force_host_platform_device_count=k`
  on CPU; the GPUs of the machine with `--device gpu`), and k processes of 1 device each,
  joined by `jax.distributed.initialize` on localhost (gloo collectives on CPU), every
  process passing the whole batch and integrating its slice.

Each worker times the run with `_harness.timing` (first call apart, median of repeats, no
recompilation) and checks its states against the baseline's; the reported time is the
slowest process's. Throughput: pendulum-steps per second; parallel efficiency: t1 / (k tk).
On a machine with fewer free cores than k the workers share cores and the efficiency
shows that, not the method (the table records the load average). Writes
benchmarks/results/scaling_<device>[_quick].{md,png} (or `--name`, e.g. `scaling_cpu_16core`
for the 16-core run the docs show; under `--out` if given).

    python benchmarks/scaling.py [--quick] [--device cpu|gpu] [--k 2 4 ...] [--batch B]
        [--n N] [--steps S] [--grad] [--out DIR] [--name STEM]
"""

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def options(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a small batch, few steps")
    parser.add_argument("--device", choices=("cpu", "gpu"), default="cpu")
    parser.add_argument(
        "--k", type=int, nargs="+", default=[2], help="devices / processes (default 2)"
    )
    parser.add_argument("--batch", type=int, help="trajectories (default 1024, quick 64)")
    parser.add_argument("--n", type=int, default=4, help="links per pendulum (default 4)")
    parser.add_argument("--steps", type=int, help="RK4 steps (default 1000, quick 200)")
    parser.add_argument("--grad", action="store_true", help="also time jax.grad")
    parser.add_argument("--out", help="folder for the results (default benchmarks/results)")
    parser.add_argument("--name", help="the results' file stem (default scaling_<device>[_quick])")
    parser.add_argument("--worker", nargs=4, metavar=("RANK", "PROCS", "PORT", "OUT"))
    opts = parser.parse_args(argv)
    opts.batch = opts.batch or (64 if opts.quick else 1024)
    opts.steps = opts.steps or (200 if opts.quick else 1000)
    return opts


# ------------------------------------------------------------------------------ worker
def worker(opts):
    rank, procs, port, out = opts.worker
    rank, procs = int(rank), int(procs)
    import jax

    jax.config.update("jax_enable_x64", opts.device == "cpu")
    if procs > 1:
        jax.distributed.initialize(f"localhost:{port}", procs, process_id=rank)
    import diffrax
    import jax.numpy as jnp
    from _harness import random_states, timing
    from jax.experimental import multihost_utils

    import sphere_mech as sm

    dt = 1e-3
    t1 = opts.steps * dt
    y0 = random_states(opts.n, opts.batch, speed=0.5)
    kw = dict(solver=sm.Projected(sm.RK4()), dt0=dt, saveat=diffrax.SaveAt(t1=True))
    kw["stepsize_controller"] = diffrax.ConstantStepSize()
    masses = jnp.ones(opts.n)

    def run():
        chain = sm.chain_pendulum(masses, jnp.ones(opts.n))
        return sm.simulate_batch(chain, y0, t1, **kw).ys

    def grad():
        def loss(m):
            sol = sm.simulate_batch(sm.chain_pendulum(m, jnp.ones(opts.n)), y0, t1, **kw)
            return jnp.sum(sol.ys[1] ** 2)

        return jax.grad(loss)(masses)

    result = {"devices": len(jax.devices()), "processes": procs}
    simulated = timing(run, repeats=3, what="simulate_batch")
    result["run"] = simulated.median
    states = multihost_utils.process_allgather(simulated.result, tiled=True)
    if opts.grad:
        result["grad"] = timing(grad, repeats=3, what="jax.grad").median
    if rank == 0:
        import numpy as np

        np.save(out + ".npy", np.concatenate([np.ravel(x) for x in states]))
    Path(f"{out}.{rank}.json").write_text(json.dumps(result))


# ------------------------------------------------------------------------------ driver
def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def configuration(opts, devices, procs, out):
    """Run the workers of one configuration; `{devices, processes, run[, grad]}` with the
    slowest process's seconds, and the states process 0 gathered."""
    import numpy as np

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HERE), os.environ.get("PYTHONPATH")]))
    if opts.device == "cpu":
        env["JAX_PLATFORMS"] = "cpu"
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices // procs}"
    else:
        gpus = range(devices) if procs == 1 else None
        env["CUDA_VISIBLE_DEVICES"] = ",".join(map(str, gpus)) if gpus else ""
    port = _free_port()
    argv = [sys.executable, __file__, "--device", opts.device, "--batch", str(opts.batch)]
    argv += ["--n", str(opts.n), "--steps", str(opts.steps)] + (["--grad"] if opts.grad else [])
    workers = []
    for rank in range(procs):
        wenv = dict(env)
        if opts.device == "gpu" and procs > 1:
            wenv["CUDA_VISIBLE_DEVICES"] = str(rank)
        cmd = argv + ["--worker", str(rank), str(procs), str(port), out]
        workers.append(subprocess.Popen(cmd, env=wenv))
    for w in workers:
        if w.wait(timeout=3600) != 0:
            raise RuntimeError(f"a worker of {devices} devices / {procs} processes failed")
    parts = [json.loads(Path(f"{out}.{r}.json").read_text()) for r in range(procs)]
    result = {key: max(p[key] for p in parts) for key in parts[0]}
    return result, np.load(out + ".npy")


def main(opts):
    import tempfile

    from _harness import RESULTS, load, machine, publish, pyplot, save_figure, table

    loads, rows = [], []
    configs = [(1, 1)] + [(d, p) for k in opts.k for d, p in ((k, 1), (k, k))]
    with tempfile.TemporaryDirectory() as tmp:
        results = []
        for i, (devices, procs) in enumerate(configs):
            loads.append(load())
            start = time.perf_counter()
            res, states = configuration(opts, devices, procs, f"{tmp}/c{i}")
            res["wall"] = time.perf_counter() - start
            print(f"{devices} devices, {procs} processes: {res}", flush=True)
            results.append((res, states))
    base, base_states = results[0]
    work = opts.batch * opts.steps
    efficiency = lambda res, key: base[key] / (res["devices"] * res[key])
    for res, states in results:
        agree = float(abs(states - base_states).max())
        row = [res["devices"], res["processes"], f"{res['run']:.3f}", f"{work / res['run']:.3g}"]
        row += [f"{efficiency(res, 'run'):.2f}", f"{agree:.1e}"]
        if opts.grad:
            row += [f"{res['grad']:.3f}", f"{efficiency(res, 'grad'):.2f}"]
        rows.append(row)
    columns = ["devices", "processes", "run (s)", "steps/s", "efficiency", "max diff from 1 device"]
    columns += ["grad (s)", "grad efficiency"] if opts.grad else []
    what = (
        f"`simulate_batch`: {opts.batch} chain pendulums of {opts.n} links, {opts.steps} "
        f"RK4 steps, {opts.device}; {machine(loads)}.\n\n"
    )
    out = opts.out or RESULTS
    name = opts.name or f"scaling_{opts.device}" + ("_quick" if opts.quick else "")
    publish(what + table(columns, rows, "rrrrrr" + "rr" * opts.grad), name + ".md", out)
    plt = pyplot()
    keys = ["run"] + ["grad"] * opts.grad
    fig, axes = plt.subplots(1, len(keys), figsize=(5 * len(keys), 3.8), squeeze=False)
    by_config = {(r["devices"], r["processes"]): r for r, _ in results}
    ks = [1] + list(opts.k)
    for ax, key in zip(axes[0], keys, strict=True):
        for procs, label in ((lambda k: 1, "k devices, 1 process"), (lambda k: k, "k processes")):
            picked = [by_config[k, procs(k)] for k in ks]
            ax.plot(ks, [efficiency(r, key) for r in picked], "o-", label=label)
        ax.axhline(1.0, color="0.6", lw=0.8)
        ax.set(
            xlabel="k", ylabel="parallel efficiency t1 / (k tk)", title=f"simulate_batch ({key})"
        )
        ax.set_xscale("log", base=2)
        ax.legend()
    save_figure(fig, name + ".png", out)


if __name__ == "__main__":
    OPTS = options()
    if OPTS.worker:
        sys.path.insert(0, str(HERE))
        worker(OPTS)
    else:
        main(OPTS)
