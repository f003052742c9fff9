"""Long-time energy behaviour: 10^6 fixed steps of a double spherical pendulum with the
variational integrator, classic RK4 and Projected(RK4), all at the same step.

For each method: the relative energy error |E(t) - E0| / |E0| at every step, its
max-envelope over 100 windows, and the fitted trend of that envelope (slope, and the
growth it predicts over the run relative to the envelope's mean). A symplectic method
shows a bounded envelope (growth near 0); RK4 drifts (growth of order 1 or more).
Prints a markdown table and writes benchmarks/results/long_time_energy.png.

Run: python benchmarks/long_time_energy.py [--steps N] [--dt H]
"""

import argparse
import functools
import sys
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _harness, when the tests import us
from _harness import publish, pyplot, save_figure, table, timing  # noqa: E402

import sphere_mech as sm  # noqa: E402

CHAIN = sm.chain_pendulum([1.0, 1.0], [1.0, 1.0])
Q0 = sm.normalize(jnp.array([[1.0, 0.0, -1.0], [0.0, 1.0, -1.0]]))
V0 = sm.project(Q0, jnp.array([[0.0, 2.0, 0.0], [2.0, 0.0, 0.0]]))
WINDOWS = 100


def _energy(system, t, y, args):
    return system.energy(t, y[0], y[1], args), sm.constraint_error(y[0])


def run(solver, dt, steps, system=CHAIN, y0=(Q0, V0)):
    """`steps` fixed steps through `sm.simulate`; returns times, relative energy errors,
    constraint errors, the result code and the wall time (after compilation)."""
    saveat = diffrax.SaveAt(steps=True, fn=functools.partial(_energy, system))
    go = lambda t1: sm.simulate(
        system,
        y0,
        jnp.asarray(t1),
        solver=solver,
        dt0=jnp.asarray(dt),
        saveat=saveat,
        max_steps=steps,
        throw=False,
    )
    # compiled once on 10 steps (the same shapes), then one timed run
    t = timing(lambda: go(dt * steps), 1, warmup=lambda: go(dt * 10).ys, what=type(solver).__name__)
    sol, wall = t.result, t.median
    e0 = float(system.energy(0.0, *y0, None))
    k = int(sol.stats["num_steps"])
    energy, constraint = (np.asarray(x[:k]) for x in sol.ys)
    return np.asarray(sol.ts[:k]), np.abs(energy - e0) / abs(e0), constraint, sol.result, wall


def envelope_trend(t, error, windows=WINDOWS):
    """Max-envelope of `error` over `windows` equal windows and the least-squares line
    through it: `(centres, maxima, slope, growth)` with `growth = slope * duration /
    mean(maxima)` (about 0 when bounded, >= 1 for a steady drift from zero)."""
    m = len(t) // windows * windows
    centres = t[:m].reshape(windows, -1).mean(axis=1)
    maxima = error[:m].reshape(windows, -1).max(axis=1)
    if not np.all(np.isfinite(maxima)):
        return centres, maxima, np.inf, np.inf
    slope = np.polyfit(centres, maxima, 1)[0]
    return centres, maxima, slope, slope * (t[m - 1] - t[0]) / np.mean(maxima)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1_000_000)
    parser.add_argument("--dt", type=float, default=0.01)
    opts = parser.parse_args()
    methods = {
        "Variational()": sm.Variational(),
        "Variational(4)": sm.Variational(4),
        "RK4": sm.RK4(),
        "Projected(RK4)": sm.Projected(sm.RK4()),
    }
    results = {}
    for name, solver in methods.items():
        results[name] = run(solver, opts.dt, opts.steps)
        print(f"ran {name}", flush=True)
    base_wall = results["Projected(RK4)"][4]  # plain RK4 may stop early (it diverges)
    rows = []
    for name, (t, err, cons, result, wall) in results.items():
        _, _, slope, growth = envelope_trend(t, err)
        status = "ok" if result == sm.RESULTS.successful else "failed"
        rows.append(
            (
                name,
                status,
                f"{np.nanmax(err):.3e}",
                f"{slope:.3e}",
                f"{growth:+.3f}",
                f"{np.nanmax(cons):.1e}",
                f"{wall:.1f}",
                f"{wall / base_wall:.2f}",
            )
        )
    columns = ["method", "result", "max rel. energy error", "envelope slope (1/s)"]
    columns += ["envelope growth over run", "max constraint error", "wall time (s)"]
    publish(
        f"\nDouble spherical pendulum, {opts.steps} steps of dt = {opts.dt} "
        f"(T = {opts.steps * opts.dt:g} s), E0 = {float(CHAIN.energy(0.0, Q0, V0)):.4f}\n\n"
        + table([*columns, "time / Projected(RK4)"], rows)
    )
    plot(results, opts)


def plot(results, opts):
    fig, ax = pyplot().subplots(figsize=(8, 4.5))
    for name, (t, err, *_) in results.items():
        centres, maxima, slope, _ = envelope_trend(t, err)
        (line,) = ax.semilogy(centres, maxima, label=name)
        if np.isfinite(slope):
            fit = np.polyval(np.polyfit(centres, maxima, 1), centres)
            ax.semilogy(
                centres, np.where(fit > 0, fit, np.nan), "--", color=line.get_color(), lw=0.8
            )
    ax.set_xlabel("t (s)")
    ax.set_ylabel("max |E - E0| / |E0| per window")
    ax.set_title(
        f"Double spherical pendulum, {opts.steps:.0e} steps, dt = {opts.dt} (dashed: fitted trend)"
    )
    ax.legend()
    save_figure(fig, "long_time_energy.png")


if __name__ == "__main__":
    main()
