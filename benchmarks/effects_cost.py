"""Cost per step as effects are added to a scene: "only what is called for".

An 8-link chain is built with gravity only, then with one more effect at a time (joint
damping, a PD base torque, a tip force, bending stiffness, a spring, a vibrating
support). For each scene we count the equations of the vector field's jaxpr (nested
jaxprs included) and time one step of `simulate` with fixed-step `Projected(RK4())`
(4 vector-field evaluations), the median (and the minimum) of interleaved rounds after
compiling.
Ratios are to the gravity-only scene measured in the same run.

Run: python benchmarks/effects_cost.py   (writes benchmarks/results/effects_cost.{md,png})
"""

import equinox as eqx
import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)
from _harness import load, machine, publish, pyplot, save_figure, table, timings  # noqa: E402

import sphere_mech as sm  # noqa: E402

N_LINKS, STEPS, DT, REPEATS = 8, 4000, 1e-3, 7


def scenes():
    chain = sm.Chain(jnp.full(N_LINKS, 0.2), jnp.full(N_LINKS, 0.25))
    added = [
        ("gravity", sm.Gravity()),
        ("+ joint damping", sm.JointDamping(0.01)),
        ("+ PD base torque", sm.BaseTorque(sm.PDTorque(2.0, 0.2))),
        ("+ tip force", sm.TipForce(jnp.array([0.5, 0.0, 0.0]))),
        ("+ bending", sm.Bending(0.05)),
        ("+ spring", sm.Spring(N_LINKS - 1, jnp.array([1.0, 0.0, -1.0]), 3.0)),
        ("+ vibrating support", sm.VibratingSupport(0.01, 30.0)),
    ]
    effects = [chain]
    for name, effect in added:
        effects.append(effect)
        yield name, sm.Scene(*effects)


def count_equations(jaxpr):
    total = 0
    for eqn in jaxpr.eqns:
        total += 1
        for param in eqn.params.values():
            for sub in param if isinstance(param, list | tuple) else [param]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    total += count_equations(inner)
    return total


def step_runner():
    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def solve(scene, y0):  # one compiled program per scene structure
        return sm.simulate(
            scene, y0, STEPS * DT, solver=sm.Projected(sm.RK4()), dt0=DT, max_steps=STEPS + 1
        ).ys

    return solve


def main():
    q0 = sm.normalize(jnp.tile(jnp.array([[0.3, 0.1, -1.0]]), (N_LINKS, 1)))
    y0 = (q0, sm.project(q0, jnp.tile(jnp.array([[0.0, 1.0, 0.0]]), (N_LINKS, 1))))
    cases = [(name, scene, step_runner()) for name, scene in scenes()]
    eqns = [
        count_equations(jax.make_jaxpr(lambda y, sc=sc: sc.rates(0.1, y, None))(y0).jaxpr)
        for _, sc, _ in cases
    ]
    # interleaved rounds: machine load affects all alike
    loads = [load()]
    measured = timings([lambda c=c: c[2](c[1], y0) for c in cases], REPEATS, what="the scenes")
    loads.append(load())
    rows = [
        (name, e, t.median / STEPS, t.min / STEPS)
        for (name, _, _), e, t in zip(cases, eqns, measured, strict=True)
    ]
    base = rows[0]
    publish(
        f"Cost of effects, {N_LINKS}-link chain, fixed-step Projected(RK4), dt={DT}, "
        f"{STEPS} steps, median of {REPEATS} interleaved rounds; ratios to gravity-only "
        f"in the same run ({machine(loads)}).\n\n"
        + table(
            [
                "scene",
                "jaxpr equations of the vector field",
                "ratio",
                "time per step (us)",
                "ratio",
                "min time per step (us)",
            ],
            [
                (
                    name,
                    e,
                    f"{e / base[1]:.2f}",
                    f"{1e6 * t:.1f}",
                    f"{t / base[2]:.2f}",
                    f"{1e6 * t_min:.1f}",
                )
                for name, e, t, t_min in rows
            ],
            "lrrrrr",
        ),
        "effects_cost.md",
    )
    fig, axes = pyplot().subplots(1, 2, figsize=(11, 4))
    names = [r[0] for r in rows]
    axes[0].bar(names, [r[1] / base[1] for r in rows], color="tab:gray")
    axes[0].set_title("jaxpr equations / gravity-only")
    axes[1].plot(names, [r[2] / base[2] for r in rows], "o-")
    axes[1].set_title("time per RK4 step / gravity-only (same run)")
    for ax in axes:
        ax.tick_params(axis="x", rotation=35)
        ax.axhline(1.0, color="k", lw=0.5)
    save_figure(fig, "effects_cost.png", dpi=110)


if __name__ == "__main__":
    main()
