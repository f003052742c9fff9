"""Throughput of batched chain-pendulum simulation: sphere_mech vs MuJoCo vs angles.

Every method integrates the same chain pendulum (unit masses at the tips of unit massless
links, gravity 9.81) with the classic fourth-order Runge-Kutta method at a fixed step
dt = 1e-3, so each does the same work per step (four force evaluations):

- sphere_mech: `sm.simulate_batch` with `sm.Projected(sm.RK4())`, sharded over the
  devices (on CPU this script asks XLA for one device per core);
- bare scan: the same RK4 step and projection over the same `system.rates`, written as a
  `lax.fori_loop` under `jax.vmap` with no diffrax loop: the floor for our own code, so the
  ratio sphere_mech / bare scan is the cost of the diffrax loop and our wrapper;
- MuJoCo (CPU): a chain of ball joints carrying point masses (tiny rotational inertia),
  its RK4 integrator, stepped by `mujoco.rollout` on all cores;
- MJX (GPU, or CPU with --mjx): the same MuJoCo model stepped by `mujoco.mjx.step` in a
  `lax.fori_loop` under `jax.vmap`, when the `mujoco-mjx` package is installed;
- angles (CPU): the same Lagrangian written in two spherical angles per link,
  accelerations from autodiff Euler-Lagrange equations and a dense solve (as
  Lagrangian-neural-network code does it), an RK4 loop, `jax.vmap` over the batch.

First the methods are checked to agree (mass positions after 0.2 s, to 1e-8 in float64).
Then pendulum-steps per second (trajectories x steps / wall time, after compilation;
median of 3 repeats, one for runs over 5 s) for n = 2, 8, 32 links and batch 1, 64, 1024,
8192, with the ratio to the peer (MuJoCo on CPU, MJX on GPU) measured in the same run;
then the cost of one step of a single trajectory against n. Prints markdown tables and
writes benchmarks/results/throughput.{png,md,json} (CPU, float64; else
`throughput_<device>_<dtype>.*`; `_quick` added with `--quick`).

    python benchmarks/throughput.py [--quick] [--device cpu|gpu] [--dtype float32|float64]

`--device gpu` fails unless JAX sees a GPU; it defaults to float32 (CPU: float64).
"""

from _options import CORES, parse_options, require_device


def add_arguments(parser):
    parser.add_argument("--ns", type=int, nargs="*", help="links to measure (default 2 8 32)")
    parser.add_argument("--batches", type=int, nargs="*", help="batch sizes")
    parser.add_argument("--per-n", type=int, nargs="*", help="n for the single-trajectory cost")
    parser.add_argument(
        "--merge",
        action="store_true",
        help="add to the results of earlier runs in the results .json",
    )


OPTS = parse_options(__doc__.splitlines()[0], add_arguments)

import json  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", OPTS.dtype == "float64")
import _harness  # noqa: E402
import _peers as peers  # noqa: E402
from _harness import RESULTS, publish, pyplot, save_figure, table  # noqa: E402
from _peers import (  # noqa: E402
    DT,
    HAVE_MJX,
    G,
    chain_xml,
    final_positions,
    fixed_step_loop,
    joint_state,
    rk4_step,
    throughput,
)

import sphere_mech as sm  # noqa: E402
from sphere_mech._linalg import spd_solve  # noqa: E402

AGREEMENT = {"float64": 1e-8, "float32": 1e-3}[OPTS.dtype]
"""Largest position difference accepted between methods after 0.2 s (float32: its
rounding amplified over 200 steps)."""
MJX_AGREEMENT = max(AGREEMENT, 1e-6)
"""MJX is held to 1e-6: in float64 it differs by 1.2e-7 both from sphere_mech and from
MuJoCo's C implementation of the same model (measured; the same for link inertias 1e-10
to 1e-3), so that is MJX's own difference, not ours."""


# ----------------------------------------------------------------------------- states
def random_states(n, batch, seed=0):
    q, v = _harness.random_states(n, batch, seed, speed=0.5)
    # Keep every link away from the poles +-e1 of the angle chart (and from +e3 for the
    # MuJoCo quaternions): resample such links at a fixed safe direction.
    bad = (jnp.abs(q[..., 0]) > 0.95) | (q[..., 2] > 0.95)
    safe = jnp.array([0.0, 0.6, -0.8])
    q = jnp.where(bad[..., None], safe, q)
    return q, sm.project(q, v)


# ------------------------------------------------------------- the methods, for n links
def chain(n):
    return sm.chain_pendulum(jnp.ones(n), jnp.ones(n), G)


class SphereMech(peers.SphereMech):
    name = "sphere_mech"  # also the class's: the tables name the methods by class

    def __init__(self, n):
        super().__init__(chain(n), chain(n).positions)


class BareScan(peers.BareScan):
    def __init__(self, n):
        super().__init__(chain(n), chain(n).positions)


class MuJoCo(peers.MuJoCo):
    def __init__(self, n, nthread=CORES):
        super().__init__(chain_xml(np.ones(n), np.ones(n)), joint_state, nthread)


class MJX(peers.MJX):
    def __init__(self, n):
        super().__init__(chain_xml(np.ones(n), np.ones(n)), joint_state)


# ------------------------------------------------------------------------------ angles
def angles_to_q(angles):
    th, ph = angles[..., 0], angles[..., 1]
    return jnp.stack([jnp.cos(th), jnp.sin(th) * jnp.cos(ph), jnp.sin(th) * jnp.sin(ph)], -1)


class Angles:
    """Lagrangian-neural-network style: L(theta, thetadot) by autodiff, then
    thetaddot = H^-1 (dL/dtheta - d2L/dthetadot dtheta thetadot), H = d2L/dthetadot2.

    H is solved by the elementwise unrolled Cholesky that sphere_mech uses for small
    dense systems: `jnp.linalg.solve` under `vmap` calls LAPACK once per tiny matrix,
    which is slow on CPU and twice stalled (no CPU use, never returned) in this script's
    two-host-device setting at batch 8192."""

    name = "angles (autodiff EL)"

    def __init__(self, n):
        self.n = n

        def lagrangian(th, thd):
            q, qdot = jax.jvp(angles_to_q, (th.reshape(n, 2),), (thd.reshape(n, 2),))
            x, xdot = jnp.cumsum(q, axis=0), jnp.cumsum(qdot, axis=0)
            return 0.5 * jnp.sum(xdot * xdot) - G * jnp.sum(x[:, 2])

        def accel(th, thd):
            H = jax.hessian(lagrangian, 1)(th, thd)
            dq = jax.grad(lagrangian, 0)(th, thd)
            mixed = jax.jacfwd(jax.grad(lagrangian, 1), 0)(th, thd)
            return spd_solve(H, dq - mixed @ thd)

        self.solve = fixed_step_loop(lambda y: rk4_step(lambda y_: (y_[1], accel(*y_)), y))

    def prepare(self, q, v):
        q, v = np.asarray(q), np.asarray(v)
        th = np.arccos(np.clip(q[..., 0], -1, 1))
        ph = np.arctan2(q[..., 2], q[..., 1])
        angles = jnp.asarray(np.stack([th, ph], -1))
        J = jax.vmap(jax.vmap(jax.jacfwd(angles_to_q)))(angles)  # (B, n, 3, 2)
        JtJ = np.einsum("bnca,bncd->bnad", J, J)
        Jtv = np.einsum("bnca,bnc->bna", J, v)
        angle_rates = np.linalg.solve(JtJ, Jtv[..., None])[..., 0]
        batch = q.shape[0]
        return angles.reshape(batch, -1), jnp.asarray(angle_rates.reshape(batch, -1))

    def run(self, y, nsteps):
        out = self.solve(y, nsteps)
        jax.block_until_ready(out)
        return out, nsteps

    def positions(self, out):
        q = angles_to_q(out[0].reshape(out[0].shape[0], self.n, 2))
        return np.asarray(jnp.cumsum(q, axis=1))


def methods():
    """The methods this run compares; the first is the peer that ratios divide by."""
    if OPTS.device == "gpu":
        return [MJX, SphereMech, BareScan] if HAVE_MJX else [SphereMech, BareScan]
    if OPTS.mjx and not HAVE_MJX:
        raise SystemExit("--mjx needs the mujoco-mjx package (pip install mujoco-mjx).")
    return [MuJoCo, SphereMech, BareScan, Angles] + ([MJX] if OPTS.mjx else [])


BATCHED_BARE_SCAN = OPTS.device == "gpu"
"""The bare scan joins the batch table on one GPU only, where both it and sphere_mech
run the whole batch as one vmap on one device. On CPU sphere_mech splits the batch over
the cores and into cache-sized chunks, which the bare scan does not; there it appears in
the one-trajectory table, which compares the cost of a step."""


def check_agreement(n=3, batch=4, nsteps=200):
    y = random_states(n, batch, seed=7)
    others = [cls(n) for cls in methods() if cls is not SphereMech]
    pos = final_positions([SphereMech(n), *others], y, nsteps)
    errors = {m.name: float(np.max(np.abs(pos[m.name] - pos[SphereMech.name]))) for m in others}
    publish(
        f"\nAgreement with sphere_mech, max |x_i| difference after {nsteps * DT:g} s "
        f"(n = {n}, {batch} random states):\n\n"
        + table(["method", "difference"], [(name, f"{err:.1e}") for name, err in errors.items()])
    )
    bound = {name: MJX_AGREEMENT if name == MJX.name else AGREEMENT for name in errors}
    assert all(errors[name] < bound[name] for name in errors), errors
    return errors


ANGLES_MAX_N = 8
"""The angle baseline is not run above this n: at n = 32 a trial run took 142 s to
compile and managed 19 pendulum-steps/s at batch 1 (dense 64 x 64 Hessians)."""


def measure_batches(ns, batches, budget, records):
    for n in ns:
        for batch in batches:
            for cls in methods():
                if (cls is Angles and n > ANGLES_MAX_N) or (
                    cls is BareScan and not BATCHED_BARE_SCAN
                ):
                    continue
                work = budget * 2 / n / (4 if cls is Angles and n >= 8 else 1)
                y = random_states(n, batch, seed=1)
                rate, compile_s, _ = throughput(cls(n), y, work, repeats=3)
                records["batch"][f"{cls.name}|{n}|{batch}"] = (rate, compile_s)
                print(f"{cls.name}, n={n}, batch={batch}: {rate:.3g} steps/s", flush=True)


def measure_cost(per_n, records):
    """The cost of one more step of one trajectory: the difference of the times of 2000
    and 500 steps over 1500, free of the per-call overhead (dispatch, checks)."""
    single = {MuJoCo: {"nthread": 1}}
    for n in per_n:
        for cls in methods():
            if cls is Angles:
                continue
            method = cls(n, **single.get(cls, {}))
            y = random_states(n, 1, seed=1)
            short = throughput(method, y, 500, repeats=3)[2] * 500
            cost = (throughput(method, y, 2000, repeats=3)[2] * 2000 - short) / 1500
            records["cost"][f"{cls.name}|{n}"] = cost
            print(f"{cls.name}, n={n}, one trajectory: {cost * 1e6:.2f} us/step", flush=True)


def report(records, errors, stem, setting):
    names = [cls.name for cls in methods()]
    peer = names[0]
    rows = []
    for key, (rate, compile_s) in records["batch"].items():
        name, n, batch = key.split("|")
        base = records["batch"].get(f"{peer}|{n}|{batch}", (np.nan,))[0]
        rows.append((int(n), int(batch), name, rate, rate / base, compile_s))
    order = {name: i for i, name in enumerate(names)}
    rows.sort(key=lambda r: (r[0], r[1], order.get(r[2], len(order))))
    batch_table = table(
        ["method", "n", "batch", "pendulum-steps/s", f"ratio to {peer}", "compile (s)"],
        [(m, n, b, f"{r:.3g}", f"{x:.2f}", f"{c:.1f}") for n, b, m, r, x, c in rows],
    )
    cost = {}
    for key, value in records["cost"].items():
        name, n = key.split("|")
        cost.setdefault(int(n), {})[name] = value
    cost_names = [name for name in names if any(name in c for c in cost.values())]
    cost_table = table(
        ["n", *(f"{m} (us/step)" for m in cost_names)],
        [
            (n, *(f"{c.get(m, np.nan) * 1e6:.2f}" for m in cost_names))
            for n, c in sorted(cost.items())
        ],
    )

    plt = pyplot()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    colors = dict(
        zip(
            ["sphere_mech", "bare scan", "MuJoCo", "MJX", "angles (autodiff EL)"],
            ["C0", "C1", "C3", "C4", "C2"],
            strict=True,
        )
    )
    ns = sorted({r[0] for r in rows})
    styles = dict(zip(ns, ("-", "--", ":", "-.")[: len(ns)], strict=True))
    for name in names:
        for n in ns:
            pts = sorted((b, r) for nn, b, m, r, _, _ in rows if m == name and nn == n)
            if pts:
                ax.loglog(
                    *zip(*pts, strict=True),
                    styles[n],
                    marker="o",
                    color=colors[name],
                    label=f"{name}, n={n}",
                )
    ax.set(
        xlabel="batch size",
        ylabel="pendulum-steps per second",
        title=f"Throughput (RK4, dt = 1e-3, {setting})",
    )
    ax.legend(fontsize=7)
    for name in cost_names:
        pts = sorted((n, c[name] * 1e6) for n, c in cost.items() if name in c)
        ax2.loglog(*zip(*pts, strict=True), marker="o", color=colors[name], label=name)
    ax2.set(xlabel="links n", ylabel="microseconds per step", title="One trajectory")
    ax2.legend()
    save_figure(fig, f"{stem}.png")
    agreement = "\n".join(f"- {k}: {v:.1e}" for k, v in errors.items())
    publish(
        f"Measured on: {setting}.\n\n"
        f"Agreement with sphere_mech (max position difference after 0.2 s):\n{agreement}\n\n"
        f"{batch_table}\n\nOne trajectory, cost per RK4 step:\n\n{cost_table}\n",
        f"{stem}.md",
    )


def main():
    require_device(OPTS)
    quick, gpu = OPTS.quick, OPTS.device == "gpu"
    ns = OPTS.ns if OPTS.ns is not None else ((2, 8) if quick else (2, 8, 32))
    batches = OPTS.batches or (
        (1, 1024) if quick else (1, 1024, 8192, 65536) if gpu else (1, 64, 1024, 8192)
    )
    per_n = (
        OPTS.per_n
        if OPTS.per_n is not None
        else ((1, 4, 16) if quick else (1, 2, 4, 8, 16, 32, 64))
    )
    budget = (5e4 if quick else 2e5) * (100 if gpu else 1)  # pendulum-steps per run, n = 2
    device = jax.devices()[0].device_kind if gpu else f"{CORES}-core CPU"
    setting = f"{device}, {OPTS.dtype}"
    print(f"devices: {jax.devices()}; {setting}, RK4, dt = {DT}")
    RESULTS.mkdir(exist_ok=True)
    stem = (
        "throughput"
        if (OPTS.device, OPTS.dtype) == ("cpu", "float64")
        else f"throughput_{OPTS.device}_{OPTS.dtype}"
    ) + ("_quick" if quick else "")
    store = RESULTS / f"{stem}.json"
    records = {"batch": {}, "cost": {}, "agreement": {}}
    if OPTS.merge and store.exists():
        records = json.loads(store.read_text())
    records["agreement"] = check_agreement()
    measure_batches(ns, batches, budget, records)
    measure_cost(per_n, records)
    store.write_text(json.dumps(records, indent=1))
    report(records, records["agreement"], stem, setting)


if __name__ == "__main__":
    main()
