"""Tracing the equations once: the time JAX spends tracing `sm.simulate` (Python running
the library and the user's energies into a jaxpr) with `sphere_mech._system.vector_field`
caching the vector field's trace (the library since this benchmark) against tracing it at
every call (before: each Runge-Kutta stage, loop pass and check traced `system.rates`
again, and `jax.jvp` / `jax.grad` traced it all once more), in the same process, turns
alternating.

Scenes: the default scene (`examples/double_pendulum.toml`) and the quadrotor with a cable
(`examples/quadrotor_cable.toml`, whose equations and controller are the largest of the
examples); fixed steps of `Projected(RK4())` (dt 0.01 over 1 s). Rows: the forward solve,
its forward-mode Jacobian in the initial velocities (`jax.jacfwd`, `ForwardMode`) and its
gradient (`jax.grad`, default adjoint), each traced with `jax.make_jaxpr` of a new
function (so JAX's own caches hold no earlier trace), medians of repeats; and the forward
solve's XLA compilation (`.lower(...).compile()` less its trace), which the cache does not
change (XLA inlines the cached call). Prints a table and writes
benchmarks/results/trace_cache.{md,png}.

    python benchmarks/trace_cache.py [--repeats 3]
"""

import argparse
import statistics
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)
from _harness import bars, load, machine, publish, pyplot, save_figure, table, timed_call  # noqa: E402

import sphere_mech as sm  # noqa: E402
import sphere_mech._system as system_module  # noqa: E402

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
CACHED = system_module._jitted_rates
UNCACHED = CACHED.__wrapped__  # the same function, traced inline at every call


def cases(spec):
    """`name: function of nothing` that traces one program of the scene."""
    scene, y0 = spec.scene, spec.y0
    opts = dict(solver=sm.Projected(sm.RK4()), dt0=0.01)
    final = lambda y, **kw: jax.tree.leaves(sm.simulate(scene, y, 1.0, **opts, **kw).ys[0])
    with_v = lambda v: (y0[0], v)
    return {
        "forward": lambda: jax.make_jaxpr(lambda y: final(y))(y0),
        "jacfwd": lambda: jax.make_jaxpr(
            lambda v: jax.jacfwd(lambda v: final(with_v(v), adjoint=diffrax.ForwardMode()))(v)
        )(y0[1]),
        "grad": lambda: jax.make_jaxpr(
            lambda v: jax.grad(lambda v: sum(jnp.sum(x) for x in final(with_v(v))))(v)
        )(y0[1]),
        "compile (forward)": lambda: jax.jit(lambda y: final(y)).lower(y0).compile(),
    }


def measure(spec, repeats):
    """`{case: (median uncached s, median cached s)}`; compile rows less their trace."""
    out = {}
    for name, fn in cases(spec).items():
        times = {True: [], False: []}
        for _ in range(repeats):
            for cached in (False, True):
                system_module._jitted_rates = CACHED if cached else UNCACHED
                jax.clear_caches()  # no trace or program kept from the other turn
                times[cached].append(timed_call(fn)[0])
        out[name] = tuple(statistics.median(times[c]) for c in (False, True))
    system_module._jitted_rates = CACHED
    compiled, trace = out["compile (forward)"], out["forward"]
    out["compile (forward)"] = tuple(c - t for c, t in zip(compiled, trace, strict=True))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    loads, rows, results = [load()], [], {}
    for example in ("double_pendulum", "quadrotor_cable"):
        spec = sm.load_scene(EXAMPLES / f"{example}.toml")
        results[example] = measure(spec, args.repeats)
        loads.append(load())
        for name, (before, after) in results[example].items():
            rows.append((example, name, f"{before:.2f}", f"{after:.2f}", f"{before / after:.1f}"))
            print(f"  {rows[-1]}", flush=True)
    text = table(
        ["scene", "program", "traced at every call [s]", "traced once [s]", "ratio"],
        rows,
        "llrrr",
    )
    publish(
        "Tracing `simulate` (`Projected(RK4())`, dt 0.01 over 1 s) with the vector field "
        "traced at every call against traced once (`vector_field`'s cache), medians of "
        f"{args.repeats} turns taken alternately, JAX's caches cleared before each; the "
        "compile row is `.lower().compile()` less the forward trace.\n\n"
        f"Machine: {machine(loads)}, `python benchmarks/trace_cache.py`.\n\n" + text + "\n",
        "trace_cache.md",
    )
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), squeeze=False)
    for ax, (example, res) in zip(axes[0], results.items(), strict=True):
        series = {
            "at every call": [r[0] for r in res.values()],
            "once (cached)": [r[1] for r in res.values()],
        }
        bars(ax, list(res), series)
        ax.set(ylabel="seconds", title=example)
    save_figure(fig, "trace_cache.png")


if __name__ == "__main__":
    main()
