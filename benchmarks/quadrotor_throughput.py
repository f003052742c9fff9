"""Throughput of a quadrotor carrying an n-link cable: sphere_mech against MuJoCo.

The system (`quadrotor`): a rigid body of 0.5 kg, inertia diag(0.00557, 0.00557, 0.0105)
kg m^2 (Goodarzi, Lee and Lee's quadrotor), carrying from the body point (0, 0, -0.05) m
a cable of n links (total length 1 m, total mass 0.05 kg, point masses at the links'
tips) with a 0.1 kg payload at its end, under gravity 9.81 and four rotors (`sm.Rotors`:
arm 0.17 m, yaw coefficient 0.0135 m) at constant thrusts: the hover thrust shared
equally plus +-0.01 N on opposite rotors, so that the body tilts and yaws as the cable
swings. n = 1, 5 and 20. Both integrate with the classic fourth-order Runge-Kutta method
at the fixed step dt = 1e-3:

- sphere_mech: `sm.simulate_batch` of the `Scene` (`RigidBase`, `Chain`, `Gravity`,
  `Rotors`: the O(n) fast path) with `sm.Projected(sm.RK4())` (rotations and unit vectors
  put back on their spaces after each step) and with `sm.LieRK(sm.RK4())` (moved by the
  groups, no projection), sharded over the devices (one per core);
- MuJoCo (C, `mujoco.rollout` on all cores): a free joint for the body, ball joints for
  the links carrying point masses (rotational inertia 1e-10), the rotors as four
  `general` actuators on sites at the rotor positions pushing along the body's e3 with
  the yaw reaction in their gear, their constant thrusts as affine biases at zero
  control; its RK4 integrator.

First the methods are checked to agree: every point mass's position (the body's centre
included) after 0.2 s from 4 random states (the body tilted up to 30 degrees, links
within 60 degrees of -e3, small velocities), against each other and against the exact
solution (`Projected(Dopri8())` at 1e-13). Then system-steps per second (trajectories x
steps / wall time after compilation, median of 3 repeats) at batch 1, 64 and 1024, with
the ratio to MuJoCo measured in the same run. Prints a markdown table and writes
benchmarks/results/quadrotor_throughput.{md,png}.

    python benchmarks/quadrotor_throughput.py [--quick] [--device cpu|gpu] [--dtype ...]

`--quick`: n = 1 and 5, batches 1 and 1024, fewer steps. `--device gpu`: sphere_mech on
the GPU (batches up to 65536; pass `--dtype float64` to keep the 1e-9 agreement check),
MuJoCo on the same machine's cores; writes `quadrotor_throughput_gpu.{md,png}`. `--links`
and `--batches` choose the sizes (the files then end in `_partial`).
"""

from _options import parse_options, require_device


def _sizes(parser):
    parser.add_argument("--links", type=int, nargs="+", help="cable links n (default 1 5 20)")
    parser.add_argument("--batches", type=int, nargs="+", help="batch sizes")


OPTS = parse_options(__doc__.splitlines()[0], _sizes, mjx=False)


import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", OPTS.dtype == "float64")
import _peers as peers  # noqa: E402
from _harness import load, machine, publish, pyplot, save_figure, table  # noqa: E402

import sphere_mech as sm  # noqa: E402

MASS, INERTIA, ATTACH = 0.5, np.array([0.00557, 0.00557, 0.0105]), np.array([0.0, 0.0, -0.05])
ARM, C_TF, PAYLOAD, CABLE_MASS, CABLE_LENGTH = 0.17, 0.0135, 0.1, 0.05, 1.0
DIFFERENTIAL = np.array([0.01, -0.01, 0.0, 0.0])  # N on rotors 1 and 2
LINKS = tuple(OPTS.links or ((1, 5) if OPTS.quick else (1, 5, 20)))
GPU = OPTS.device == "gpu"
BATCHES = tuple(
    OPTS.batches
    or ((1, 1024) if OPTS.quick else (1, 64, 1024, 8192, 65536) if GPU else (1, 64, 1024))
)
DT, G = peers.DT, peers.G
AGREEMENT = {"float64": 1e-9, "float32": 1e-3}[OPTS.dtype]
"""The largest position difference (m) allowed beyond the RK4 errors' slack."""


def thrusts():
    hover = (MASS + CABLE_MASS + PAYLOAD) * G / 4
    return hover + DIFFERENTIAL


def quadrotor(n):
    """The system as a `Scene` (the O(n) fast path)."""
    wrench = sm.mixing_matrix(jnp.asarray(ARM), jnp.asarray(C_TF)) @ jnp.asarray(thrusts())
    return sm.Scene(
        sm.RigidBase(MASS, INERTIA, attach=ATTACH),
        sm.Chain(CABLE_MASS / n, CABLE_LENGTH / n, links=n, payload=PAYLOAD),
        sm.Gravity(G),
        sm.Rotors(wrench, ARM, C_TF),
    )


def mujoco_xml(n):
    """The same system in MuJoCo: a free body with sites at the rotors, ball joints."""
    masses = np.full(n, CABLE_MASS / n)
    masses[-1] += PAYLOAD
    lengths = np.full(n, CABLE_LENGTH / n)
    chain = peers.chain_xml(lengths, masses, inertia=1e-10)
    links = chain[chain.index("<worldbody>") + len("<worldbody>") : chain.index("</worldbody>")]
    attach = " ".join(map(repr, ATTACH.tolist()))
    links = links.replace('<body pos="0 0 0">', f'<body pos="{attach}">', 1)  # the joint
    angles = np.arange(4) * np.pi / 2
    sites = "".join(
        f'<site name="rotor{i}" pos="{float(ARM * np.cos(a))!r} {float(ARM * np.sin(a))!r} 0"/>'
        for i, a in enumerate(angles)
    )
    motors = "".join(  # constant thrust: an affine bias at zero control
        f'<general site="rotor{i}" gear="0 0 1 0 0 {C_TF * (1 if i % 2 == 0 else -1)!r}" '
        f'biastype="affine" biasprm="{float(f)!r} 0 0"/>'
        for i, f in enumerate(thrusts())
    )
    J = " ".join(repr(float(x)) for x in INERTIA)
    body = (
        f'<body name="quadrotor"><freejoint/><inertial pos="0 0 0" mass="{MASS!r}" '
        f'diaginertia="{J}"/>{sites}{links}</body>'
    )
    head = chain[: chain.index("<worldbody>")]
    return f"{head}<worldbody>{body}</worldbody><actuator>{motors}</actuator></mujoco>"


def to_joints(q, v):
    """MuJoCo's `(qpos, qvel)`: the free joint (centre, unit quaternion; velocity, body
    angular velocity in the body's frame), then the ball joints relative to the body."""
    R = np.asarray(q["attitude"][:, 0])
    Rdot = np.asarray(v["attitude"][:, 0])
    Omega = np.stack([np.asarray(sm.vee(r.T @ rd)) for r, rd in zip(R, Rdot, strict=True)])
    quat = np.zeros((len(R), 4))
    for b, r in enumerate(R):
        mujoco.mju_mat2Quat(quat[b], r.reshape(-1))
    w = np.einsum("bij,bj->bi", R, Omega)  # world angular velocity
    qpos, qvel = peers.joint_state(q["spheres"], v["spheres"], parent=R, parent_omega=w)
    free_pos = np.concatenate([np.asarray(q["base"]), quat], axis=1)
    free_vel = np.concatenate([np.asarray(v["base"]), Omega], axis=1)
    return np.concatenate([free_pos, qpos], 1), np.concatenate([free_vel, qvel], 1)


def random_states(n, batch, seed=0):
    """The body tilted up to 30 degrees (any yaw), links within 60 degrees of -e3, small
    velocities."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=(batch, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    tilt = np.radians(30.0) * rng.uniform(size=(batch, 1)) * axis
    yaw = rng.uniform(0, 2 * np.pi, (batch, 1)) * np.array([0.0, 0.0, 1.0])
    R = jax.vmap(lambda a, b: sm.rotation_matrix(a) @ sm.rotation_matrix(b))(tilt, yaw)
    Omega = rng.normal(0.0, 0.5, (batch, 3))
    s, sdot = peers.hanging_links(rng, batch, n)
    dtype = jnp.zeros(()).dtype
    q = {"attitude": R[:, None], "base": rng.uniform(-0.1, 0.1, (batch, 3)), "spheres": s}
    v = {
        "attitude": (R @ jax.vmap(sm.hat)(jnp.asarray(Omega)))[:, None],
        "base": rng.normal(0.0, 0.1, (batch, 3)),
        "spheres": sdot,
    }
    return jax.tree.map(lambda a: jnp.asarray(a, dtype), (q, v))


def methods(n):
    """MuJoCo (the peer, first), sphere_mech with two solvers."""
    scene = quadrotor(n)
    lie = peers.SphereMech(scene, scene.points, "sphere_mech LieRK(RK4)")
    lie.solver = sm.LieRK(sm.RK4())
    return [
        peers.MuJoCo(mujoco_xml(n), to_joints),
        peers.SphereMech(scene, scene.points, "sphere_mech Projected(RK4)"),
        lie,
    ]


def check_agreement(n, batch=4, nsteps=200):
    y = random_states(n, batch, seed=7)
    pos = peers.final_positions(methods(n), y, nsteps)
    scene = quadrotor(n)
    sol = sm.simulate_batch(
        scene, y, nsteps * DT, solver=sm.Projected(diffrax.Dopri8()), rtol=1e-13, atol=1e-13
    )
    exact = np.asarray(jax.vmap(scene.points)(jax.tree.map(lambda a: a[:, -1], sol.ys[0])))
    ours = pos["sphere_mech Projected(RK4)"]
    errors = {
        name: {
            "difference": float(np.max(np.abs(p - ours))),
            "rk4_error": float(np.max(np.abs(p - exact))),
        }
        for name, p in pos.items()
    }
    print(f"n = {n}: {errors}", flush=True)
    slack = AGREEMENT + 2 * max(e["rk4_error"] for e in errors.values())
    assert all(e["difference"] <= slack for e in errors.values()), errors
    return errors


def measure(n, budget):
    out = {}
    for batch in BATCHES:
        y = random_states(n, batch, seed=1)
        for method in methods(n):
            rate, compile_s, _ = peers.throughput(method, y, budget, repeats=3)
            out.setdefault(method.name, {})[batch] = (rate, compile_s)
            print(f"n = {n}, {method.name}, batch {batch}: {rate:.3g} steps/s", flush=True)
    return out


def main():
    require_device(OPTS)
    budget = (5e4 if OPTS.quick else 2e5) * (100 if GPU else 1)
    loads = [load()]
    agreement = {n: check_agreement(n) for n in LINKS}
    records = {n: measure(n, budget) for n in LINKS}
    loads.append(load())
    where = f"{machine(loads)}, {OPTS.dtype}"
    if GPU:
        where = f"sphere_mech on {jax.devices()[0].device_kind}, MuJoCo on {where}"
    rows = []
    for n, by_method in records.items():
        peer = by_method["MuJoCo"]
        for batch in BATCHES:
            for name, by_batch in by_method.items():
                rate, compile_s = by_batch[batch]
                ratio = rate / peer[batch][0]
                rows.append((n, batch, name, f"{rate:.3g}", f"{ratio:.2f}", f"{compile_s:.1f}"))
    throughput = table(
        ["links n", "batch", "method", "system-steps/s", "ratio to MuJoCo", "compile (s)"], rows
    )
    check = table(
        ["links n", "method", "from sphere_mech Projected(RK4)", "from the exact solution"],
        [
            (n, name, f"{e['difference']:.1e}", f"{e['rk4_error']:.1e}")
            for n, errs in agreement.items()
            for name, e in errs.items()
        ],
    )
    stem = "quadrotor_throughput" + ("_gpu" if GPU else "") + ("_quick" if OPTS.quick else "")
    stem += "_partial" if OPTS.links or OPTS.batches else ""
    publish(
        f"Quadrotor with an n-link cable, RK4 at dt = {DT:g} ({where}).\n\n"
        f"Agreement: max position difference after 0.2 s (4 random states).\n\n{check}\n\n"
        f"Throughput:\n\n{throughput}\n",
        f"{stem}.md",
    )
    plt = pyplot()
    fig, axes = plt.subplots(1, len(LINKS), figsize=(5 * len(LINKS), 4), sharey=True, squeeze=False)
    axes = axes[0]
    for ax, n in zip(axes, LINKS, strict=True):
        for name, by_batch in records[n].items():
            pts = sorted((b, r) for b, (r, _) in by_batch.items())
            ax.loglog(*zip(*pts, strict=True), marker="o", label=name)
        ax.set(xlabel="batch size", title=f"quadrotor, {n}-link cable")
        ax.legend(fontsize=8)
    axes[0].set_ylabel("system-steps per second")
    fig.suptitle(where, fontsize=9)
    save_figure(fig, f"{stem}.png")


if __name__ == "__main__":
    main()
