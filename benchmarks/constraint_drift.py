"""Constraint drift: max_i | |q_i| - 1 | over 10^5 fixed steps of a double spherical
pendulum (dt = 1e-3, 100 s) for plain RK4, Projected(RK4), LieRK4 and (when present)
the variational integrator, and the wall time of a run (median and minimum of 2 after
compiling). Prints a markdown table and writes
benchmarks/results/constraint_drift.png (constraint error against time).

Run: python benchmarks/constraint_drift.py
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

from _harness import publish, pyplot, save_figure, table, timing  # noqa: E402

import sphere_mech as sm  # noqa: E402

DT, T1 = 1e-3, 100.0
STEPS = int(round(T1 / DT))
CHAIN = sm.chain_pendulum(jnp.array([1.0, 1.0]), jnp.array([1.0, 1.0]))
Q0 = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
V0 = jnp.array([[0.0, 0.5, 1.0], [0.0, 0.0, 2.0]])


def _per_step(t, y, args):
    return sm.constraint_error(y[0]), CHAIN.energy(t, y[0], y[1], args)


@eqx.filter_jit
@eqx.debug.assert_max_traces(max_traces=4)  # one per solver, never per call
def run(solver, dt, t1):
    """Fixed steps with diffrax directly, so that nothing retracts the saved states."""
    saveat = diffrax.SaveAt(steps=True, fn=_per_step)
    return diffrax.diffeqsolve(
        sm.MechanicsTerm(CHAIN),
        solver,
        0.0,
        t1,
        dt,
        (Q0, V0),
        saveat=saveat,
        stepsize_controller=diffrax.ConstantStepSize(),
        max_steps=STEPS,
        throw=False,
    )


def methods():
    out = {"RK4 (plain)": sm.RK4(), "Projected(RK4)": sm.Projected(sm.RK4()), "LieRK4": sm.LieRK4()}
    if hasattr(sm, "Variational"):
        out["Variational(order=4)"] = sm.Variational(order=4)
    return out


def main():
    dt, t1 = jnp.asarray(DT), jnp.asarray(T1)
    e0 = float(CHAIN.energy(0.0, Q0, V0))
    rows, curves = [], {}
    for name, solver in methods().items():
        wall = timing(lambda solver=solver: run(solver, dt, t1), 2, what=name)
        sol = wall.result
        ts = np.asarray(sol.ts)
        c, energy = (np.asarray(x) for x in sol.ys)
        done = np.isfinite(ts)
        ts, c, energy = ts[done], c[done], energy[done]
        finite = np.isfinite(c) & np.isfinite(energy)
        blew_up = not finite.all()
        t_end = ts[finite][-1] if finite.any() else 0.0
        rows.append(
            dict(
                name=name,
                steps=int(done.sum()),
                max_c=float(np.max(c[finite])),
                c_10=float(np.max(c[finite & (ts <= 10.0)])),
                energy=float(np.max(np.abs(energy[finite] - e0)) / abs(e0)),
                wall=wall.median,
                wall_min=wall.min,
                note=f"NaN after t = {t_end:.1f} s" if blew_up else "",
            )
        )
        curves[name] = (ts[finite], c[finite])
    baseline = next(r for r in rows if r["name"] == "Projected(RK4)")
    columns = [
        "method",
        "steps",
        "max abs(abs(q_i)-1), t <= 10 s",
        "max abs(abs(q_i)-1)",
        "max rel. energy error",
        "wall (s)",
        "wall / Projected(RK4)",
        "note",
        "wall, min (s)",
    ]
    rows = [
        (
            r["name"],
            r["steps"],
            f"{r['c_10']:.2e}",
            f"{r['max_c']:.2e}",
            f"{r['energy']:.2e}",
            f"{r['wall']:.2f}",
            f"{r['wall'] / baseline['wall']:.2f}",
            r["note"],
            f"{r['wall_min']:.2f}",
        )
        for r in rows
    ]
    publish(
        f"Double spherical pendulum, dt = {DT:g}, {STEPS} steps ({T1:g} s).\n\n"
        + table(columns, rows, "lrrrrrrlr")
    )
    plot(curves)


def plot(curves):
    """Running maximum of the constraint error, on a log scale (exact zeros shown at
    1e-17)."""
    fig, ax = pyplot().subplots(figsize=(7, 4))
    for name, (ts, c) in curves.items():
        running = np.maximum.accumulate(np.maximum(c, 1e-17))
        keep = np.zeros(len(ts), bool)
        keep[:: max(1, len(ts) // 2000)] = True
        keep[-1] = True
        ax.semilogy(ts[keep], running[keep], label=name)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("running max of max_i | |q_i| - 1 |")
    ax.set_title(f"Constraint drift, double spherical pendulum, dt = {DT:g}")
    ax.legend()
    ax.grid(True, which="both", alpha=0.3)
    save_figure(fig, "constraint_drift.png")


if __name__ == "__main__":
    main()
