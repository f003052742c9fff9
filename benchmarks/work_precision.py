"""Work-precision benchmark: what accuracy costs in time, per integrator and scene.

For every integrator (each diffrax solver under `sm.Projected` at several tolerances,
fixed-step methods at several step sizes) and every scene, on (S^2)^n or, for the drone
carrying a cable, on the mixed space R^3 x (S^2)^5 (all through the scene's API: its
`space`, `points`, `spheres`), it measures

- the error at the final time against a float64 reference computed with a much tighter
  tolerance (`Projected(Dopri8)`, rtol = atol = 1e-14): the largest distance between the
  point masses (`scene.points`: the base's point included) and the reference's;
- the largest energy error `max_t |E(t) - E(0)|` and the largest constraint error
  `max_t max_i | |q_i| - 1 |` (over the spheres), over every step of the run;
- the wall time of a compiled run (median of repeats; the first call is timed apart and
  the difference is reported as compile time; `cached` when the same program was already
  compiled for an earlier scene of the same size);
- the number of force evaluations, counted by a host callback (`jax.debug.callback`)
  in the chain's potential, in a separate diagnostic run so the counter never slows the
  timed run. Every vector-field evaluation of our equations evaluates the gradient of
  the potential once, so for explicit Runge-Kutta methods (and LieRK) this is the
  number of vector-field evaluations, `num_steps x new stages per step + start-up
  calls`; for implicit solvers one batched Jacobian (`jax.jacfwd`) counts as one; for
  the variational integrator it is the gradient evaluations of its Newton iterations.
  The angle baseline counts calls of its vector field.

Baselines measured in the same run: the same double pendulum written in spherical angles
(polar angle from the downward vertical, azimuth) with autodiff Euler-Lagrange equations
as in Lagrangian-neural-network code (`pinv(Hessian) @ (grad - mixed @ qdot)`),
integrated with the same diffrax solver; and a motion that passes within ~1e-6 rad of the
angle chart's pole, where the angle baseline's cost or error blows up while ours does not.

    python benchmarks/work_precision.py           # full run, < ~10 min on 2 cores
    python benchmarks/work_precision.py --quick   # < 1 min (run by notebooks/04_accuracy)
    python benchmarks/work_precision.py --scenes drone   # one scene, merged into the results

Writes `<out>/work_precision.{md,png,json}` (`work_precision_quick.*` with `--quick`).
Integrators are listed in `methods()`; adding one is one line there.
"""

import argparse
import dataclasses
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _harness, when the tests import us
from _harness import RESULTS as RESULTS_DIR, publish, save_figure, table, timing  # noqa: E402

import sphere_mech as sm  # noqa: E402

REFERENCE_TOL = 1e-14

# ----------------------------------------------------------------------------------------
# Counting vector-field evaluations

_CALLS = [0]


def _tick():
    _CALLS[0] += 1


class Counter(sm.AbstractPotential):
    """A zero potential whose every evaluation bumps a host-side counter: added to a
    scene, it counts the evaluations of the vector field (a scene, so that solvers that
    need a Lagrangian system, such as `Variational`, accept it)."""

    def potential(self, t, q, scene, args):
        jax.debug.callback(_tick)
        return jnp.zeros((), scene.spheres(q).dtype)


def counted(chain):
    return sm.Scene(*chain.effects, Counter())


# ----------------------------------------------------------------------------------------
# The angle baseline: spherical angles, autodiff Euler-Lagrange (LNN style)


def unit_from_angles(x):
    """`(n, 2)` angles (polar from -e3, azimuth) -> `(n, 3)` unit vectors."""
    theta, phi = x[:, 0], x[:, 1]
    s = jnp.sin(theta)
    return jnp.stack([s * jnp.cos(phi), s * jnp.sin(phi), -jnp.cos(theta)], axis=-1)


class AngleChain(eqx.Module):
    """The same chain, in angles: `L(x, xt) = chain.lagrangian(q(x), dq/dx xt)`."""

    chain: sm.Scene

    def lagrangian(self, x, xt):
        q, qdot = jax.jvp(unit_from_angles, (x,), (xt,))
        return self.chain.lagrangian(0.0, q, qdot, None)

    def rates(self, t, y, args):
        # As Lagrangian-neural-network code writes it, on flattened coordinates.
        x, xt = y
        shape = x.shape
        L = lambda a, b: self.lagrangian(a.reshape(shape), b.reshape(shape))
        a, b = x.reshape(-1), xt.reshape(-1)
        H = jax.hessian(L, 1)(a, b)
        mixed = jax.jacobian(jax.jacobian(L, 1), 0)(a, b)
        xtt = jnp.linalg.pinv(H) @ (jax.grad(L, 0)(a, b) - mixed @ b)
        return xt, xtt.reshape(shape)

    def energy(self, x, xt):
        p = jax.grad(self.lagrangian, 1)(x, xt)
        return jnp.sum(p * xt) - self.lagrangian(x, xt)

    def points(self, x):
        return self.chain.points(unit_from_angles(x))


def angles_from_state(q, v):
    """Angles and angle rates of a state `(q, qdot)` (least squares through dq/dx)."""
    x = jnp.stack([jnp.arccos(jnp.clip(-q[:, 2], -1.0, 1.0)), jnp.arctan2(q[:, 1], q[:, 0])], -1)
    J = jax.jacfwd(lambda a: unit_from_angles(a.reshape(x.shape)).reshape(-1))(x.reshape(-1))
    xt = jnp.linalg.lstsq(J, v.reshape(-1))[0]
    return x, xt.reshape(x.shape)


def _angle_vector_field(t, y, system):
    return system.rates(t, y, None)


def _angle_vector_field_counted(t, y, system):
    jax.debug.callback(_tick)
    return system.rates(t, y, None)


# ----------------------------------------------------------------------------------------
# Scenes and methods


@dataclasses.dataclass
class Scene:
    name: str
    chain: sm.Scene
    y0: tuple
    t1: float
    steps: tuple  # step sizes for fixed-step methods
    angle_baseline: bool = False
    pole: bool = False  # only the Tsit5 methods, the angle baseline from rtol 1e-8 on
    note: str = ""


@dataclasses.dataclass
class Method:
    label: str
    make: Callable  # make(scene) -> a diffrax solver
    tolerances: tuple | None = None  # adaptive: these rtol = atol; None: scene.steps
    angles: bool = False  # the spherical-angle baseline instead of our formulation
    quick: bool = False  # part of --quick
    max_fixed_steps: int = 100_000  # skip step sizes needing more steps than this


ADAPTIVE_TOLS = (1e-4, 1e-6, 1e-8, 1e-10)
POLE_ANGLE_MIN_TOL = 1e-8
"""The angle baseline on the pole passage stops at rtol 1e-8: at 1e-10 it alone took about
a minute (297x our force evaluations), the point is made at 1e-8 already."""


def methods(quick: bool) -> list[Method]:
    """The integrators compared. One line per integrator."""
    P = sm.Projected
    ms = [
        Method("Projected(Tsit5)", lambda s: P(diffrax.Tsit5()), ADAPTIVE_TOLS, quick=True),
        Method("Projected(Dopri5)", lambda s: P(diffrax.Dopri5()), ADAPTIVE_TOLS),
        Method("Projected(Dopri8)", lambda s: P(diffrax.Dopri8()), (1e-6, 1e-8, 1e-10, 1e-12)),
        # Kvaerno5 at 1e-8 (108 s, none of it informative on these non-stiff scenes) is left
        # out to keep the full run near 10 minutes.
        Method("Projected(Kvaerno5)", lambda s: P(diffrax.Kvaerno5()), (1e-4, 1e-6)),
        Method("LieRK4", lambda s: sm.LieRK4(), ADAPTIVE_TOLS),
        Method("LieRK4 (fixed steps)", lambda s: sm.LieRK4(), quick=True),
        # The best Lie-group solvers of benchmarks/nfold_pendulum.py (SE(3) action).
        Method("LieRK(Tsit5)", lambda s: sm.LieRK(diffrax.Tsit5()), ADAPTIVE_TOLS),
        Method("LieRK(Dopri8)", lambda s: sm.LieRK(diffrax.Dopri8()), (1e-6, 1e-8, 1e-10, 1e-12)),
        Method("Variational (order 2)", lambda s: sm.Variational(), max_fixed_steps=20_000),
        Method("Variational (order 4)", lambda s: sm.Variational(order=4), max_fixed_steps=4_000),
        Method("Projected(RK4)", lambda s: P(sm.RK4())),
        Method("RK4 (no projection)", lambda s: sm.RK4()),
        Method(
            "angles + Tsit5 (LNN-style)",
            lambda s: diffrax.Tsit5(),
            ADAPTIVE_TOLS,
            angles=True,
            quick=True,
        ),
    ]
    if quick:
        ms = [m for m in ms if m.quick]
    return ms


def _chain_state(thetas, phis, speeds_theta, speeds_phi):
    """The spheres' `(q, v)` from polar angles (from -e3), azimuths and rates along e_theta,
    e_phi (a scene's `space.retract` puts them exactly on its tangent bundle)."""
    x = jnp.stack([jnp.asarray(thetas, float), jnp.asarray(phis, float)], -1)
    q = unit_from_angles(x)
    th, ph = x[:, 0], x[:, 1]
    e_th = jnp.stack([jnp.cos(th) * jnp.cos(ph), jnp.cos(th) * jnp.sin(ph), jnp.sin(th)], -1)
    e_ph = jnp.stack([-jnp.sin(ph), jnp.cos(ph), jnp.zeros_like(ph)], -1)
    v = jnp.asarray(speeds_theta)[:, None] * e_th + jnp.asarray(speeds_phi)[:, None] * e_ph
    return q, v


def double_pendulum_scene(t1):
    chain = sm.chain_pendulum(jnp.ones(2), jnp.ones(2))
    y0 = chain.space.retract(*_chain_state([0.9, 1.2], [0.0, 0.5], [0.0, -0.3], [2.0, 1.5]))
    return Scene("double pendulum", chain, y0, t1, (1e-2, 3e-3, 1e-3, 3e-4), angle_baseline=True)


def triple_pendulum_state():
    q = sm.normalize(jnp.array([[1.0, 0.0, 0.2], [0.0, 1.0, 0.1], [-1.0, 0.3, 0.5]]))
    v = sm.project(q, jnp.array([[0.0, 2.0, 1.0], [1.5, 0.0, -1.0], [0.5, -2.0, 0.0]]))
    return q, v


def triple_pendulum_scene(t1):
    chain = sm.chain_pendulum(jnp.ones(3), jnp.ones(3))
    return Scene(
        "chaotic triple pendulum", chain, triple_pendulum_state(), t1, (3e-3, 1e-3, 3e-4, 1e-4)
    )


def hanging_chain_scene(t1, n=16):
    chain = sm.chain_pendulum(jnp.full(n, 1.0 / n), jnp.full(n, 1.0 / n))
    i = np.arange(n)
    y0 = chain.space.retract(
        *_chain_state(
            0.6 * np.sin(np.pi * (i + 1) / (n + 1)),
            0.2 * i / n,
            np.zeros(n),
            0.5 * np.cos(np.pi * i / n),
        )
    )
    return Scene(f"{n}-link hanging chain", chain, y0, t1, (1e-2, 3e-3, 1e-3, 3e-4))


def drone_cable_scene(t1, n=5):
    """The mixed space R^3 x (S^2)^5: a drone (a 1.5 kg point mass moving in space, no
    thrust: no controller) carrying a 0.3 kg payload on a 5-link cable of 0.02 kg links,
    tossed up at 14 m/s with the cable tilted and swinging; no damping, so the energy is
    conserved. The whole falls freely (the centre of mass on a parabola, back near its
    start at t1 = 3 s) while the cable whips around it."""
    chain = sm.Scene(sm.Base(1.5), sm.Chain(0.02, 0.2, links=n, payload=0.3), sm.Gravity())
    i = np.arange(n)
    q, v = _chain_state(0.5 + 0.25 * i, 0.3 * i, 3.0 * np.cos(i), 4.0 - i)
    y0 = chain.space.retract(
        {"base": jnp.zeros(3), "spheres": q}, {"base": jnp.array([0.5, -0.3, 14.0]), "spheres": v}
    )
    return Scene(f"drone with a {n}-link cable", chain, y0, t1, (1e-2, 3e-3, 1e-3, 3e-4))


# ----------------------------------------------------------------------------------------
# Compiled runs (one program per method and system size; t1 and the tolerance or step
# are traced, so sweeping them does not recompile)


def _raw(t, y, args):
    # `simulate` puts saved (q, v) pairs back on the spheres (for dense output); saving a
    # dict keeps the states exactly as the solver made them, so drift stays visible.
    return dict(q=y[0], v=y[1])


@eqx.filter_jit
def _integrate(chain, solver, y0, t1, param, adaptive, diagnostics, max_steps):
    system = counted(chain) if diagnostics else chain
    saveat = diffrax.SaveAt(steps=diagnostics, t1=not diagnostics, fn=_raw)
    if adaptive:
        step = dict(rtol=param, atol=param)
    else:
        step = dict(dt0=param, stepsize_controller=diffrax.ConstantStepSize())
    sol = sm.simulate(
        system, y0, t1, solver=solver, saveat=saveat, max_steps=max_steps, throw=False, **step
    )
    ys = (sol.ys["q"], sol.ys["v"])
    return sol.ts, ys, sol.result == sm.RESULTS.successful, sol.stats["num_steps"]


@eqx.filter_jit
def _integrate_angles(angle_chain, solver, y0, t1, param, adaptive, diagnostics, max_steps):
    vf = _angle_vector_field_counted if diagnostics else _angle_vector_field
    saveat = diffrax.SaveAt(steps=True) if diagnostics else diffrax.SaveAt(t1=True)
    if adaptive:
        controller, dt0 = diffrax.PIDController(rtol=param, atol=param), None
    else:
        controller, dt0 = diffrax.ConstantStepSize(), param
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(vf),
        solver,
        0.0,
        t1,
        dt0,
        y0,
        args=angle_chain,
        saveat=saveat,
        stepsize_controller=controller,
        max_steps=max_steps,
        throw=False,
    )
    return sol.ts, sol.ys, sol.result == diffrax.RESULTS.successful, sol.stats["num_steps"]


@eqx.filter_jit
def _reference_solution(chain, y0, t1, tol):
    return sm.simulate(
        chain,
        y0,
        t1,
        solver=sm.Projected(diffrax.Dopri8()),
        rtol=tol,
        atol=tol,
        max_steps=1_000_000,
        saveat=diffrax.SaveAt(t1=True, dense=True),
    )


def reference_solution(scene, tol=REFERENCE_TOL):
    """`Projected(Dopri8)` at rtol = atol = `tol` (dense output on)."""
    return _reference_solution(scene.chain, scene.y0, jnp.asarray(scene.t1), jnp.asarray(tol))


@eqx.filter_jit
def _evaluate_q(chain, sol, ts):
    return jax.vmap(lambda t: chain.space.normalize(sol.evaluate(t)[0]))(ts)


def _last(tree):
    return jax.tree.map(lambda a: a[-1], tree)


@eqx.filter_jit
def _mapped(fn, *xs):
    """`jax.vmap(fn)(*xs)`, compiled once per function (a pytree) and shapes: the energy
    along a run is otherwise evaluated op by op (0.6 s of a 0.8 s row)."""
    return jax.vmap(fn)(*xs)


def _energy(system, q, v):
    return system.energy(0.0, q, v, None)


def measure(scene, method, param, ref_points, repeats, max_steps):
    """One point of the work-precision diagram: a dict of measured numbers."""
    adaptive = method.tolerances is not None
    solver = method.make(scene)
    t1 = jnp.asarray(scene.t1)
    p = jnp.asarray(param)
    if method.angles:
        angle_chain = AngleChain(scene.chain)
        y0 = angles_from_state(*scene.y0)
        run = lambda diag: _integrate_angles(
            angle_chain, solver, y0, t1, p, adaptive, diag, max_steps
        )
        points = angle_chain.points
        energy = jax.tree_util.Partial(_mapped, angle_chain.energy)
        constraint = lambda ys: float("nan")
    else:
        y0 = scene.y0
        run = lambda diag: _integrate(scene.chain, solver, y0, t1, p, adaptive, diag, max_steps)
        points = scene.chain.points
        energy = jax.tree_util.Partial(_mapped, jax.tree_util.Partial(_energy, scene.chain))
        constraint = lambda ys: float(sm.constraint_error(scene.chain.spheres(ys[0])))

    # `repeats` runs, fewer past 2 s in all, more (up to 30) while under 0.3 s
    timed = timing(lambda: run(False), repeats, budget=2.0, fast=0.3, most=30, what=method.label)
    _, ys, ok, num_steps = timed.result
    final_error = float(jnp.max(jnp.linalg.norm(points(_last(ys[0])) - ref_points, axis=-1)))

    _CALLS[0] = 0
    ts, ys_all, ok_diag, _ = run(True)
    jax.block_until_ready(ys_all)
    evaluations = _CALLS[0]
    keep = np.isfinite(np.asarray(ts))
    ys_all = jax.tree.map(lambda a: np.asarray(a)[keep], ys_all)
    e0 = float(energy(*jax.tree.map(lambda a: a[None], y0))[0])
    energy_error = float(np.max(np.abs(np.asarray(energy(*ys_all)) - e0)))
    ok = bool(ok) and bool(ok_diag)
    if not ok:
        final_error = energy_error = float("nan")
    return dict(
        scene=scene.name,
        method=method.label,
        adaptive=adaptive,
        param=float(param),
        final_error=final_error,
        energy_error=energy_error,
        constraint_error=constraint(ys_all),
        wall_time=timed.median,
        wall_time_min=timed.min,
        compile_time=timed.compile,
        evaluations=evaluations,
        steps=int(num_steps),
        success=ok,
    )


# ----------------------------------------------------------------------------------------
# Predictability of the chaotic scene; pole passage


def predictability_time(scene, t_max, eps=1e-10, threshold=1e-2):
    """First time at which a 1e-10 perturbation of `q0` moves some mass by more than
    `threshold` (in units of the chain's length)."""
    q0, v0 = scene.y0
    q1, v1 = scene.chain.space.retract(q0 + eps * jnp.array([[0.0, 1.0, 0.0]] * q0.shape[0]), v0)
    ts = jnp.linspace(0.0, t_max, 2001)
    solver = sm.Projected(diffrax.Dopri8())
    run = lambda y: sm.simulate(
        scene.chain,
        y,
        t_max,
        solver=solver,
        rtol=1e-13,
        atol=1e-13,
        saveat=diffrax.SaveAt(ts=ts),
        max_steps=1_000_000,
    ).ys[0]
    xa = jax.vmap(scene.chain.points)(run((q0, v0)))
    xb = jax.vmap(scene.chain.points)(run((q1, v1)))
    sep = np.max(np.linalg.norm(np.asarray(xa - xb), axis=-1), axis=-1)
    size = float(jnp.sum(scene.chain.kinetic[0].lengths))
    above = np.nonzero(sep > threshold * size)[0]
    return float(ts[above[0]]) if above.size else float("inf")


def pole_scene(t1, approach=1e-6, delta0=1e-3):
    """A planar double-pendulum swing through the bottom pole (the angle chart's
    singular point), tilted out of plane by a small velocity so that the first link
    passes within `approach` rad of the pole. Returns the scene and the closest approach
    (measured on our reference trajectory)."""
    chain = sm.chain_pendulum(jnp.ones(2), jnp.ones(2))

    def state(delta):
        return chain.space.retract(*_chain_state([1.0, 1.0], [0.0, 0.0], [0.0, 0.0], [delta, 0.0]))

    def closest(delta):
        scene = Scene(
            "pole passage (double pendulum)",
            chain,
            state(delta),
            t1,
            (1e-2, 3e-3, 1e-3),
            angle_baseline=True,
            pole=True,
        )
        return scene, _closest_approach(scene, reference_solution(scene, 1e-12))

    _, d0 = closest(delta0)  # the out-of-plane excursion is linear in delta
    return closest(delta0 * approach / d0)


def _closest_approach(scene, sol):
    """Smallest angle between link 1 and -e3: at each sign change of its x component
    (found on a grid, refined by bisection on the dense output) the angle is |(x, y)|."""
    spheres = lambda ts: scene.chain.spheres(_evaluate_q(scene.chain, sol, jnp.asarray(ts)))
    q1_at = lambda ts: np.asarray(spheres(ts))[:, 0]
    ts = np.linspace(0.0, scene.t1, 4001)
    x = q1_at(ts)[:, 0]
    i = np.nonzero(np.sign(x[:-1]) != np.sign(x[1:]))[0]
    a, b, sign = ts[i], ts[i + 1], np.sign(x[i])
    for _ in range(60):  # bisection on every crossing at once
        m = 0.5 * (a + b)
        same = np.sign(q1_at(m)[:, 0]) == sign
        a, b = np.where(same, m, a), np.where(same, b, m)
    q = q1_at(0.5 * (a + b))
    return float(np.min(np.arctan2(np.hypot(q[:, 0], q[:, 1]), -q[:, 2])))


# ----------------------------------------------------------------------------------------
# Output


def _fmt(x, spec=".1e"):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "—"
    return format(x, spec)


def markdown_table(rows):
    columns = ["scene", "method", "tol / dt", "error at t1", "max energy error"]
    columns += ["max constraint error", "time (ms)", "compile (s)", "force evals", "steps"]
    cells = []
    for r in rows:
        compile_s = "cached" if r["compile_time"] < 0.05 else f"{r['compile_time']:.1f}"
        param = ("tol " if r["adaptive"] else "dt ") + f"{r['param']:.0e}"
        cells.append(
            (r["scene"], r["method"], param, _fmt(r["final_error"]), _fmt(r["energy_error"]))
            + (_fmt(r["constraint_error"]), f"{1e3 * r['wall_time']:.2f}", compile_s)
            + (r["evaluations"], f"{r['steps']}" + ("" if r["success"] else " (failed)"))
        )
    return table(columns, cells)


def ratio_table(rows, base="Projected(Tsit5)", other="angles + Tsit5 (LNN-style)"):
    """Same-tolerance comparison of the angle baseline against `base`, per scene."""
    columns = ["scene", "tol", f"{other}: time / ours", "evals / ours", "its error", "our error"]
    cells = []
    index = {(r["scene"], r["method"], r["param"]): r for r in rows}
    for (scene, method, param), r in index.items():
        ours = index.get((scene, base, param))
        if method != other or ours is None:
            continue
        cells.append(
            (scene, f"{param:.0e}", f"{r['wall_time'] / ours['wall_time']:.1f}")
            + (f"{r['evaluations'] / max(ours['evaluations'], 1):.1f}",)
            + (_fmt(r["final_error"]), _fmt(ours["final_error"]))
        )
    return table(columns, cells)


def figure(rows, path=None):
    import matplotlib

    if path is not None:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    labels = list(dict.fromkeys(r["method"] for r in rows))
    palette = [plt.cm.tab10(i) for i in range(10)] + ["black", "0.6"]
    colors = {m: palette[i % len(palette)] for i, m in enumerate(labels)}
    ncols = min(2, len(scenes))
    nrows = -(-len(scenes) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.2 * ncols, 3.9 * nrows + 0.8), squeeze=False)
    for ax in axes.flat[len(scenes) :]:
        ax.set_visible(False)
    for ax, scene in zip(axes.flat, scenes, strict=False):
        for m in labels:
            pts = sorted(
                (r["wall_time"], r["final_error"])
                for r in rows
                if r["scene"] == scene
                and r["method"] == m
                and r["success"]
                and r["final_error"] > 0
            )
            if pts:
                style = "--" if "angles" in m or "no projection" in m else "-"
                ax.loglog(
                    *zip(*pts, strict=True), style, marker="o", ms=3, color=colors[m], label=m
                )
        ax.set_title(scene, fontsize=10)
        ax.set_xlabel("wall time after compilation (s)")
        ax.grid(True, which="major", alpha=0.3)
    for row in axes:
        row[0].set_ylabel("max position error at t1 (m)")
    handles, names = [], []
    for ax in axes.flat:
        for h, n in zip(*ax.get_legend_handles_labels(), strict=True):
            if n not in names:
                handles.append(h)
                names.append(n)
    fig.legend(
        handles, names, loc="lower center", ncol=min(4, len(names)), fontsize=8, frameon=False
    )
    legend_height = 0.3 + 0.2 * -(-len(names) // 4)  # inches, 4 names a row
    fig.tight_layout(rect=(0, legend_height / fig.get_figheight(), 1, 1))
    if path is not None:
        save_figure(fig, Path(path).name, Path(path).parent, dpi=110, layout=False)
    return fig


# ----------------------------------------------------------------------------------------


def _triple(t1, info, log):
    triple = triple_pendulum_scene(t1)
    t_pred = predictability_time(triple, 20.0)
    log(
        f"chaotic triple pendulum: a 1e-10 perturbation of q0 grows past 1% of the "
        f"chain's length at t = {t_pred:.2f} s; horizon {triple.t1} s"
    )
    info["triple_predictability_time"] = t_pred
    return triple


def _pole(t1, info, log):
    pole, approach = pole_scene(t1)
    log(f"pole passage: closest approach of link 1 to the pole {approach:.2e} rad")
    info["pole_closest_approach"] = approach
    return pole


SCENES = ("double", "triple", "chain", "pole", "drone")
"""The scenes' keys for `--scenes`, in the order of the full run (`--quick`: double and
pole only)."""


def scenes_of(quick, keys, info, log):
    """The scenes named by `keys` (None: all) that the run (quick or full) has, built in
    order; what is measured on the way goes into `info`."""
    if quick:
        builders = dict(
            double=lambda: double_pendulum_scene(2.0), pole=lambda: _pole(2.0, info, log)
        )
    else:
        builders = dict(
            double=lambda: double_pendulum_scene(10.0),
            triple=lambda: _triple(5.0, info, log),
            chain=lambda: hanging_chain_scene(5.0),
            pole=lambda: _pole(5.0, info, log),
            drone=lambda: drone_cable_scene(3.0),
        )
    if keys is not None and not set(keys) <= set(builders):
        run = "quick" if quick else "full"
        raise ValueError(f"the {run} run has only the scenes {', '.join(builders)}")
    return [build() for key, build in builders.items() if keys is None or key in keys]


def parameters(scene, method, quick):
    """The tolerances or step sizes `method` runs at on `scene` (empty: it does not)."""
    if (method.angles and not scene.angle_baseline) or (
        scene.pole and not (method.angles or "Tsit5" in method.label)
    ):
        return []
    adaptive = method.tolerances is not None
    params = method.tolerances if adaptive else scene.steps
    if quick:
        params = params[:3] if adaptive else params[:2]
    if not adaptive:
        params = [p for p in params if scene.t1 / p <= method.max_fixed_steps]
    if scene.pole and method.angles:
        params = [p for p in params if p >= POLE_ANGLE_MIN_TOL]
    return list(params)


def measure_scene(scene, quick, repeats, info, log):
    """Every method on one scene: its rows (and its reference's error into `info`)."""
    final_points = lambda sol: scene.chain.points(_last(sol.ys[0]))
    ref = final_points(reference_solution(scene))
    check = final_points(reference_solution(scene, 100 * REFERENCE_TOL))
    ref_err = float(jnp.max(jnp.linalg.norm(ref - check, axis=-1)))
    info[f"reference_error[{scene.name}]"] = ref_err
    log(f"{scene.name}: t1 = {scene.t1} s, reference (tol 1e-14 vs 1e-12) differs by {ref_err:.1e}")
    rows = []
    for method in methods(quick):
        params = parameters(scene, method, quick)
        if not params:
            continue
        adaptive = method.tolerances is not None
        max_steps = 200_000 if adaptive else int(math.ceil(scene.t1 / min(params))) + 10
        for param in params:
            r = measure(scene, method, param, ref, repeats, max_steps)
            rows.append(r)
            log(
                f"  {method.label:28s} {param:8.0e}  err {_fmt(r['final_error'])}  "
                f"dE {_fmt(r['energy_error'])}  |q|-1 {_fmt(r['constraint_error'])}  "
                f"{1e3 * r['wall_time']:8.2f} ms  evals {r['evaluations']}"
            )
    return rows


def merged(old, new):
    """`old` results with the scenes of `new` replaced (or appended), in scene order."""
    names = {r["scene"] for r in new["rows"]}
    order = list(dict.fromkeys([r["scene"] for r in old["rows"] + new["rows"]]))
    rows = [r for r in old["rows"] if r["scene"] not in names] + new["rows"]
    rows.sort(key=lambda r: order.index(r["scene"]))  # stable: methods keep their order
    return dict(rows=rows, info=old["info"] | new["info"])


def run(quick=False, out=None, log=print, scenes=None):
    """Run the benchmark; returns `dict(rows=..., info=...)` and writes files to `out`.
    With `scenes` (keys of `SCENES`), only those run, and their rows replace theirs in
    the results already in `out` (the others are kept)."""
    repeats = 3 if quick else 5
    info = dict(quick=quick)
    rows = []
    for scene in scenes_of(quick, scenes, info, log):
        rows += measure_scene(scene, quick, repeats, info, log)
    results = dict(rows=rows, info=info)
    stem = "work_precision_quick" if quick else "work_precision"
    if out is not None and scenes is not None and (Path(out) / f"{stem}.json").exists():
        results = merged(json.loads((Path(out) / f"{stem}.json").read_text()), results)
        log(f"merged into {Path(out) / stem}.json")
    rows, info = results["rows"], results["info"]

    text = (
        "# Work-precision results\n\n"
        + "\n".join(f"- {k}: {v}" for k, v in info.items())
        + "\n\n"
        + markdown_table(rows)
        + "\n\n## Angle baseline / ours, same tolerance\n\n"
        + ratio_table(rows)
        + "\n"
    )
    publish(text, None if out is None else f"{stem}.md", out, show=log)
    if out is not None:
        (Path(out) / f"{stem}.json").write_text(json.dumps(results, indent=1))
        figure(rows, Path(out) / f"{stem}.png")
    return results


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small run (< 1 min)")
    parser.add_argument("--out", default=str(RESULTS_DIR), help="output directory")
    parser.add_argument(
        "--scenes",
        nargs="+",
        choices=SCENES,
        metavar="SCENE",
        help=f"run only these scenes ({', '.join(SCENES)}) and merge their "
        "rows into the results already in --out",
    )
    args = parser.parse_args(argv)
    return run(quick=args.quick, out=args.out, scenes=args.scenes)


if __name__ == "__main__":
    main()
