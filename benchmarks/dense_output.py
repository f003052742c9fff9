"""Dense output of `LieRK` against its steps: a spherical pendulum (length 0.7 m, a
non-planar motion over 3 s) integrated by `LieRK(Dopri5 / Tsit5 / Dopri8)` at
rtol = atol = 1e-6, 1e-9, 1e-12; the largest error of (q, qdot) at the accepted steps
(`SaveAt(steps=True)`) beside the largest error at 301 equally spaced times
(`SaveAt(ts=...)`, which lie between steps and come from the dense output), both against
an independent scipy `DOP853` solve of the Cartesian constrained equation
`qddot = -(g/l) (e_z - (e_z . q) q) - |qdot|^2 q` at rtol = atol = 1e-14 with steps of at
most 1 ms. Then the time of an event (a planar release at 1 rad crossing the vertical,
located by Newton on the dense output) with `LieRK(Dopri8)` and `Projected(Dopri8)` at
tol 1e-8 against the closed form `sqrt(l/g) K(sin^2(1/2))`. Fixed-step rows:
`Projected(RK4())`, `LieRK4()` and `Variational(order=2, 4)` at dt = 7e-3 and 7e-4 s
(`diffrax.ConstantStepSize()`).

    python benchmarks/dense_output.py     # about a minute on 2 cores

Prints a markdown table and writes it, with the event times, to
benchmarks/results/dense_output.md; the figure (error between steps against error at
them, one point per solver and tolerance or step) to benchmarks/results/dense_output.png.
"""

import sys
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from scipy.integrate import solve_ivp
from scipy.special import ellipk

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _harness, when the tests import us
from _harness import publish, pyplot, save_figure, table  # noqa: E402

import sphere_mech as sm  # noqa: E402

G, LENGTH, T1 = 9.81, 0.7, 3.0
PENDULUM = sm.chain_pendulum([1.0], [LENGTH], G)
TS = np.linspace(0.0, T1, 301)


def initial_state():
    q = np.array([np.sin(1.0), 0.0, -np.cos(1.0)])
    return q, np.array([0.3, 2.5, 0.3 * np.tan(1.0)])  # tangent: q . qdot = 0


def reference():
    """A dense scipy solution of the Cartesian equation (a function of t -> (q, qdot))."""
    ez = np.array([0.0, 0.0, 1.0])

    def rhs(t, y):
        q, qd = y[:3], y[3:]
        return np.concatenate([qd, -(G / LENGTH) * (ez - q[2] * q) - (qd @ qd) * q])

    sol = solve_ivp(
        rhs,
        (0.0, T1),
        np.concatenate(initial_state()),
        method="DOP853",
        rtol=100 * np.finfo(float).eps,  # the smallest scipy takes (it raises 1e-14 to it)
        atol=1e-14,
        max_step=1e-3,
        dense_output=True,
    )
    return lambda t: sol.sol(t).T


def errors(solver, tol, ref, dt=None):
    """Largest errors at the steps and at `TS`, the number of `TS` and the largest
    `| |q| - 1 |` there: adaptive steps at `rtol = atol = tol`, or fixed steps of `dt`."""
    q0, v0 = (jnp.asarray(x)[None] for x in initial_state())
    steps = dict(rtol=tol, atol=tol)
    if dt is not None:
        steps = dict(dt0=dt, stepsize_controller=diffrax.ConstantStepSize())
    run = lambda saveat: sm.simulate(
        PENDULUM, (q0, v0), T1, solver=solver, saveat=saveat, max_steps=100_000, **steps
    )
    out = []
    for sol in (run(diffrax.SaveAt(steps=True)), run(diffrax.SaveAt(ts=jnp.asarray(TS)))):
        ts = np.asarray(sol.ts)
        keep = np.isfinite(ts)
        y = np.concatenate([np.asarray(sol.ys[0])[keep, 0], np.asarray(sol.ys[1])[keep, 0]], 1)
        out.append(np.max(np.abs(y - ref(ts[keep]))))
    q = np.asarray(sol.ys[0])[:, 0]
    unit = np.max(np.abs(np.linalg.norm(q, axis=1) - 1))
    return out[0], out[1], int(keep.sum()), unit


def event_time(solver, tol=1e-8):
    q = jnp.array([[np.sin(1.0), 0.0, -np.cos(1.0)]])
    event = diffrax.Event(
        lambda t, y, args, **kw: y[0][0, 0],
        root_finder=optx.Newton(rtol=1e-13, atol=1e-13),
        direction=False,
    )
    sol = sm.simulate(
        PENDULUM, (q, jnp.zeros_like(q)), 10.0, solver=solver, rtol=tol, atol=tol, event=event
    )
    return float(sol.ts[-1])


def main():
    ref = reference()
    rows, points = [], []
    for name, inner in (
        ("Dopri5", diffrax.Dopri5()),
        ("Tsit5", diffrax.Tsit5()),
        ("Dopri8", diffrax.Dopri8()),
    ):
        for tol in (1e-6, 1e-9, 1e-12):
            at_steps, at_ts, _, _ = errors(sm.LieRK(inner), tol, ref)
            points.append((f"LieRK({name})", at_steps, at_ts))
            rows.append(
                (
                    f"LieRK({name})",
                    f"{tol:.0e}",
                    f"{at_steps:.1e}",
                    f"{at_ts:.1e}",
                    f"{at_ts / at_steps:.1f}",
                )
            )
    for name, solver in (
        ("Projected(RK4())", sm.Projected(sm.RK4())),
        ("LieRK4()", sm.LieRK4()),
        ("Variational()", sm.Variational()),
        ("Variational(order=4)", sm.Variational(order=4)),
    ):
        for dt in (7e-3, 7e-4):  # steps that do not fall on the 0.01 s grid of TS
            at_steps, at_ts, _, _ = errors(solver, None, ref, dt=dt)
            points.append((name, at_steps, at_ts))
            ratio = f"{at_ts / at_steps:.1f}"
            rows.append((name, f"dt {dt:.0e}", f"{at_steps:.1e}", f"{at_ts:.1e}", ratio))
    columns = ["solver", "tol or step", "max error at steps", "max error at SaveAt(ts)", "ratio"]
    exact = np.sqrt(LENGTH / G) * ellipk(np.sin(0.5) ** 2)
    events = [f"Event at tol 1e-8, exact time {exact:.12f} s:"]
    for name, solver in (
        ("LieRK(Dopri8)", sm.LieRK(diffrax.Dopri8())),
        ("Projected(Dopri8)", sm.Projected(diffrax.Dopri8())),
    ):
        t = event_time(solver)
        events.append(f"- {name}: {t:.12f} s, off by {t - exact:.1e} s")
    publish(table(columns, rows) + "\n\n" + "\n".join(events) + "\n", "dense_output.md")

    fig, ax = pyplot().subplots(figsize=(5.5, 4.5))
    for i, name in enumerate(dict.fromkeys(name for name, *_ in points)):
        xy = [(a, b) for n, a, b in points if n == name]
        ax.loglog(*zip(*xy, strict=True), "o", color=f"C{i}", label=name)
    lo, hi = min(min(p[1:]) for p in points), max(max(p[1:]) for p in points)
    ax.loglog([lo, hi], [lo, hi], "k:", lw=1, label="equal")
    ax.set(xlabel="max error at the steps", ylabel="max error at SaveAt(ts) (between steps)")
    ax.set_title("dense output against the steps (spherical pendulum, 3 s)", fontsize=9)
    ax.legend(fontsize=7)
    save_figure(fig, "dense_output.png")


if __name__ == "__main__":
    main()
