"""Cost of one acceleration evaluation: the constant-inertia fast path against the general
autodiff path, on the same Lagrangian.

The chain pendulum (`sm.chain_pendulum`, the paper's Corollary 1: constant scalar inertia,
no Hessian of L) against `sm.Lagrangian(chain.lagrangian)` (the Hessian of the same L by
forward-over-reverse autodiff and a 2n x 2n solve), both with a tip force and a base
torque, in float64, for n = 1, 2, 4, 8, 16, 32, 64 links (1 to 8 with `--quick`). Each is
`jax.jit`-compiled (compile time reported separately), `jax.vmap`-ed over a batch of
states, and timed as the median over repeats of the wall time per batch divided by the
batch size. The two paths are first checked to agree. The baseline is the general path
measured in the same run.
A third column times Hamilton's equations of `sm.legendre(chain)` (the inverse Legendre
map by the same O(n) fast path, gradients by the envelope theorem) against the chain's
own accelerations. Prints a markdown table; writes benchmarks/results/fast_path.{png,md}
(`fast_path_quick.*` with `--quick`).

Second table: the variational integrator on the same chains, whose Newton solve uses the
same O(n) multiplier solve. Cost per step of one trajectory (`sm.simulate`, float64,
fixed step `--dt`, default 1e-3, from a chain released near its hanging position, median
(and minimum) of 5 runs) of
`Variational(2)` and `Variational(4)` against `Projected(RK4())` measured in the same run
(ratios), and of the dense-Newton `Variational(2, fast_path=False)` (the path general
systems take) for n <= 32, checked to agree with the O(n) path.

Third table (`--base`, alone): the same chains hanging from a moving base (a drone: a
`Base` point mass in space; a cart: a `Base` on a line; a rigid body: a `RigidBase` with
an attitude, the chain hung 5 cm from its centre of mass), the scene's O(n) fast path
against its general autodiff twin (the same energies through `sm.Lagrangian` on the
product space) and against the fixed-pivot chain of the same n, per acceleration
evaluation as in the first table. Writes benchmarks/results/fast_path_base.{md,png}.

    python benchmarks/fast_path.py [--quick] [--dt 1e-3] [--steps 1000]
    python benchmarks/fast_path.py --base [--quick]
"""

import argparse

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
from _harness import load, machine, publish, pyplot, random_states, save_figure, table, timing  # noqa: E402

import sphere_mech as sm  # noqa: E402


def make_systems(n):
    rng = np.random.default_rng(n)
    chain = sm.chain_pendulum(
        rng.uniform(0.5, 2.0, n),
        rng.uniform(0.5, 2.0, n),
        9.81,
        torque=jnp.array([0.1, -0.2, 0.3]),
        tip_force=jnp.array([0.5, 0.0, -0.4]),
    )
    general = sm.Lagrangian(chain.lagrangian, forces=chain.generalized_force)
    return chain, general


BASES = {
    "drone": lambda: sm.Base(1.5),
    "cart": lambda: sm.Base(1.5, axes=[[1.0, 0.0, 0.0]]),
    "rigid body": lambda: sm.RigidBase(1.5, [0.02, 0.02, 0.04], attach=[0.0, 0.0, -0.05]),
}
"""The moving bases of the third table."""


def base_systems(n, base):
    """A chain (tip force, gravity) hanging from `base`, and the same energies and forces
    through the general path on the product space."""
    rng = np.random.default_rng(n)
    scene = sm.Scene(
        base,
        sm.Chain(rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 2.0, n)),
        sm.Gravity(9.81),
        sm.TipForce(jnp.array([0.5, 0.0, -0.4])),
    )
    lagrangian = lambda t, q, qdot, args: scene.kinetic_energy(q, qdot) - scene.potential(t, q)
    return scene, sm.Lagrangian(lagrangian, scene.forces, space=scene.space)


def base_rows(ns, batch, repeats):
    """Per-evaluation cost of the base scenes' fast path, their general twins and the
    fixed-pivot chain of the same n (checked to agree)."""
    rows = []
    for n in ns:
        keys = jax.random.split(jax.random.PRNGKey(n), batch)
        s, sdot = random_states(n, batch, seed=n)
        fixed, _ = make_systems(n)
        pivot, _ = time_per_evaluation(batched_rates(fixed), s, sdot, repeats)
        for name, make in BASES.items():
            scene, general = base_systems(n, make())
            x = jax.random.normal(keys[0], (batch, scene.base.m))
            q, v = {"base": x, "spheres": s}, {"base": x[:, ::-1], "spheres": sdot}
            if scene.rigid_body is not None:
                R = jax.vmap(sm.rotation_matrix)(jax.random.normal(keys[1], (batch, 3)))
                Omega = jax.random.normal(keys[2], (batch, 3))
                q["attitude"], v["attitude"] = R[:, None], (R @ sm.hat(Omega))[:, None]
            fast_fn, general_fn = batched_rates(scene), batched_rates(general)
            fast, _ = time_per_evaluation(fast_fn, q, v, repeats)
            slow, _ = time_per_evaluation(general_fn, q, v, repeats)
            a, b = fast_fn(q, v)[1], general_fn(q, v)[1]
            error = max(
                float(jnp.max(jnp.abs(x - y)) / jnp.max(jnp.abs(y)))
                for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
            )
            assert error < 1e-10, f"paths disagree for the {name} at n={n}: {error}"
            rows.append((name, n, fast, slow, pivot, error))
            print(
                f"{name} n={n}: fast {fast * 1e6:.2f} us, general {slow * 1e6:.2f} us, "
                f"fixed pivot {pivot * 1e6:.2f} us",
                flush=True,
            )
    return rows


def base_table(rows, batch, repeats, where):
    header = (
        f"Chains on a moving base ({where}): acceleration evaluations, float64, jit(vmap) "
        f"over a batch "
        f"of {batch} states, median of {repeats} repeats. Drone: a `Base` in space; cart: "
        "a `Base` on a line; rigid body: a `RigidBase` (mass 1.5 kg, inertia diag(0.02, "
        "0.02, 0.04) kg m^2, the chain hung 5 cm below its centre of mass). General path: "
        "the same energies and forces through "
        "`sm.Lagrangian` on the product space; fixed pivot: the chain of the same n without "
        "a base, in the same run.\n\n"
    )
    columns = ["base", "n", "fast path (us/eval)", "general path (us/eval)", "speed-up"]
    columns += ["fast / fixed pivot", "max rel. difference"]
    cells = [
        (name, n, f"{f * 1e6:.3f}", f"{s * 1e6:.3f}", f"{s / f:.1f}x", f"{f / p:.2f}", f"{e:.1e}")
        for name, n, f, s, p, e in rows
    ]
    return header + table(columns, cells, "lrrrrrr") + "\n"


def batched_rates(system):
    """jit(vmap(rates)) with a guard against recompilation."""

    @jax.jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(q, v):
        return jax.vmap(lambda q_, v_: system.rates(0.0, (q_, v_), None))(q, v)

    return run


def time_per_evaluation(fn, q, qdot, repeats):
    """(median seconds per single evaluation, compile time)."""
    t = timing(lambda: fn(q, qdot), repeats)
    return t.median / len(jax.tree.leaves(q)[0]), t.compile


def start_state(n):
    """A chain released near its hanging position: links tilted by about 0.3 rad, slow."""
    kq, kv = jax.random.split(jax.random.PRNGKey(n))
    q = sm.normalize(0.3 * jax.random.normal(kq, (n, 3)) + jnp.array([0.0, 0.0, -1.0]))
    return q, sm.project(q, 0.3 * jax.random.normal(kv, (n, 3)))


def time_per_step(system, solver, y0, dt, steps, repeats):
    """(seconds per step of one trajectory, median and minimum over `repeats` runs;
    final state; seconds of the first call: compilation and one run)."""

    def run():
        sol = sm.simulate(
            system,
            y0,
            jnp.asarray(dt * steps),
            solver=solver,
            dt0=jnp.asarray(dt),
            max_steps=steps + 1,
        )
        return sol.ys

    t = timing(run, repeats, what=type(solver).__name__)
    return t.median / steps, t.min / steps, t.result, t.first


def variational_rows(ns, dt, steps, repeats):
    """Per-step cost of Projected(RK4), Variational(2), Variational(4) and the dense
    Variational(2, fast_path=False) (n <= 32) on the chains of `make_systems`."""
    rows = []
    for n in ns:
        chain, _ = make_systems(n)
        y0 = start_state(n)
        rk4, rk4_min, _, _ = time_per_step(chain, sm.Projected(sm.RK4()), y0, dt, steps, repeats)
        var2, var2_min, (q2, _), compile2 = time_per_step(
            chain, sm.Variational(), y0, dt, steps, repeats
        )
        var4, _, _, _ = time_per_step(chain, sm.Variational(4), y0, dt, steps, repeats)
        dense, difference = float("nan"), float("nan")
        if n <= 32:
            dense, _, (qd, _), _ = time_per_step(
                chain, sm.Variational(fast_path=False), y0, dt, steps, repeats
            )
            difference = float(jnp.max(jnp.abs(q2[-1] - qd[-1])))
            assert difference < 1e-9, f"O(n) and dense variational steps disagree: {difference}"
        rows.append((n, rk4, var2, var4, dense, difference, compile2, var2_min / rk4_min))
        print(
            f"n={n}: Projected(RK4) {rk4 * 1e6:.1f} us/step, Variational(2) "
            f"{var2 * 1e6:.1f}, Variational(4) {var4 * 1e6:.1f}, dense Variational(2) "
            f"{dense * 1e6:.1f}",
            flush=True,
        )
    return rows


def variational_table(rows, dt, steps, repeats):
    header = (
        f"Variational integrator, cost per step of one trajectory (float64, dt = {dt:g}, "
        f"{steps} steps from a chain released near its hanging position, median of "
        f"{repeats} runs), against Projected(RK4()) in the same run. Dense: "
        "Variational(2, fast_path=False), Newton with the dense Jacobian (n <= 32); "
        "max |q| difference: its final state against the O(n) path's.\n\n"
    )
    columns = [
        "n",
        "Projected(RK4) (us/step)",
        "Variational(2) (us/step)",
        "Variational(2) / RK4",
        "Variational(4) (us/step)",
        "Variational(4) / RK4",
        "dense Variational(2) (us/step)",
        "dense / O(n)",
        "max abs q difference",
        "first call of Variational(2) (s)",
        "Variational(2) / RK4, fastest runs",
    ]
    cells = [
        (n, f"{r * 1e6:.1f}", f"{v2 * 1e6:.1f}", f"{v2 / r:.2f}", f"{v4 * 1e6:.1f}")
        + (f"{v4 / r:.2f}", f"{d * 1e6:.1f}", f"{d / v2:.1f}", f"{e:.1e}", f"{c:.1f}")
        + (f"{fastest:.2f}",)
        for n, r, v2, v4, d, e, c, fastest in rows
    ]
    return header + table(columns, cells, "r" * len(columns)) + "\n"


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="n <= 8, fewer repeats")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--dt", type=float, default=1e-3, help="variational table: step")
    parser.add_argument("--steps", type=int, default=1000, help="variational table: steps")
    parser.add_argument(
        "--base", action="store_true", help="only the table of chains on a moving base"
    )
    opts = parser.parse_args()
    ns = [1, 2, 4, 8] if opts.quick else [1, 2, 4, 8, 16, 32, 64]
    repeats = 5 if opts.quick else 20
    stem = "fast_path" + ("_base" if opts.base else "") + ("_quick" if opts.quick else "")
    if opts.base:
        loads = [load()]
        rows = base_rows(ns, opts.batch, repeats)
        loads.append(load())
        publish(base_table(rows, opts.batch, repeats, machine(loads)), f"{stem}.md")
        fig, ax = pyplot().subplots(figsize=(5.5, 3.8))
        for name in BASES:
            picked = [(n, s / f) for base, n, f, s, _, _ in rows if base == name]
            ax.loglog(*zip(*picked, strict=True), "o-", label=name)
        ax.set_xscale("log", base=2)
        ax.set_xticks(ns, [str(n) for n in ns])
        ax.set(xlabel="links n", ylabel="general path / fast path\n(time per evaluation)")
        ax.set_title(f"chains on a moving base\n{machine(loads)}", fontsize=7)
        ax.legend(fontsize=8)
        save_figure(fig, f"{stem}.png")
        return
    rows, loads = [], [load()]
    for n in ns:
        chain, general = make_systems(n)
        q, qdot = random_states(n, opts.batch, seed=n)
        fast_fn, general_fn = batched_rates(chain), batched_rates(general)
        hamilton_fn = batched_rates(sm.legendre(chain))
        mu = jax.vmap(lambda q_, v_, c=chain: c.momentum(0.0, q_, v_, None))(q, qdot)
        fast, fast_compile = time_per_evaluation(fast_fn, q, qdot, repeats)
        slow, slow_compile = time_per_evaluation(general_fn, q, qdot, repeats)
        ham, _ = time_per_evaluation(hamilton_fn, q, mu, repeats)
        reference = general_fn(q, qdot)[1]
        error = float(jnp.max(jnp.abs(fast_fn(q, qdot)[1] - reference)))
        scale = float(jnp.max(jnp.abs(reference)))
        assert error < 1e-10 * scale, f"paths disagree at n={n}: {error}"
        legendre_error = float(jnp.max(jnp.abs(hamilton_fn(q, mu)[0] - qdot)))
        assert legendre_error < 1e-10 * float(jnp.max(jnp.abs(qdot))), legendre_error
        rows.append(
            (n, fast, slow, slow / fast, fast_compile, slow_compile, error / scale, ham, ham / fast)
        )
        print(
            f"n={n}: fast {fast * 1e6:.2f} us, general {slow * 1e6:.2f} us, "
            f"legendre {ham * 1e6:.2f} us",
            flush=True,
        )

    var_repeats = 3 if opts.quick else 5
    var_rows = variational_rows(ns[1:], opts.dt, opts.steps, var_repeats)
    var_table = variational_table(var_rows, opts.dt, opts.steps, var_repeats)
    loads.append(load())
    header = (
        f"Acceleration evaluations, float64, jit(vmap) over a batch of {opts.batch} states, "
        f"median of {repeats} repeats, {jax.device_count()} device(s).\n\n"
        f"Machine: {machine(loads)}, JAX on {jax.devices()[0].platform}; "
        f"`python benchmarks/fast_path.py{' --quick' if opts.quick else ''}`.\n\n"
    )
    columns = ["n", "fast path (us/eval)", "general path (us/eval)", "speed-up"]
    columns += ["compile fast (s)", "compile general (s)", "max rel. difference"]
    columns += ["legendre(chain) (us/eval)", "legendre / fast"]
    cells = [
        (n, f"{f * 1e6:.3f}", f"{s * 1e6:.3f}", f"{r:.1f}x", f"{cf:.2f}", f"{cs:.2f}")
        + (f"{e:.1e}", f"{h * 1e6:.3f}", f"{hr:.2f}")
        for n, f, s, r, cf, cs, e, h, hr in rows
    ]
    print()
    publish(header + table(columns, cells, "r" * len(columns)) + "\n\n" + var_table, f"{stem}.md")

    n_arr = np.array([r[0] for r in rows])
    fig, (ax1, ax2, ax3) = pyplot().subplots(1, 3, figsize=(15, 4))
    ax1.loglog(n_arr, [r[1] * 1e6 for r in rows], "o-", label="fast path (constant inertia)")
    ax1.loglog(n_arr, [r[2] * 1e6 for r in rows], "s-", label="general path (autodiff Hessian)")
    ax1.loglog(n_arr, [r[7] * 1e6 for r in rows], "^-", label="legendre(chain): Hamilton")
    ax1.set_xlabel("links n")
    ax1.set_ylabel("time per acceleration evaluation (us)")
    ax1.set_xscale("log", base=2)
    ax1.legend()
    ax1.grid(True, which="both", alpha=0.3)
    ax2.loglog(n_arr, [r[3] for r in rows], "o-", color="C2")
    ax2.set_xscale("log", base=2)
    ax2.set_xlabel("links n")
    ax2.set_ylabel("speed-up of the fast path (x)")
    ax2.grid(True, which="both", alpha=0.3)
    n_var = np.array([r[0] for r in var_rows])
    for k, label in (
        (1, "Projected(RK4())"),
        (2, "Variational(2), O(n)"),
        (3, "Variational(4), O(n)"),
        (4, "Variational(2), dense Newton"),
    ):
        ax3.loglog(n_var, [r[k] * 1e6 for r in var_rows], "o-", label=label)
    ax3.set_xscale("log", base=2)
    ax3.set_xlabel("links n")
    ax3.set_ylabel(f"time per step, one trajectory (us), dt = {opts.dt:g}")
    ax3.legend()
    ax3.grid(True, which="both", alpha=0.3)
    fig.suptitle(
        f"Chain pendulum, float64: accelerations (batch {opts.batch}) and integrator steps"
    )
    save_figure(fig, f"{stem}.png")


if __name__ == "__main__":
    main()
