"""Throughput of batched mixed systems R^m x (S^2)^n: sphere_mech vs MuJoCo.

Two systems whose state has a point-mass base and a chain of point masses hanging from it:

- cart pendulum: a 1.0 kg cart on the x axis carrying a spherical pendulum (0.8 m, a
  0.5 kg point mass at its tip), free;
- drone with a cable: a 1.5 kg point mass in 3-D carrying a 5-link cable (links of 0.2 m,
  0.02 kg at each link's tip, a 0.3 kg payload added at the last one), held at the hover
  point 0 by the PD force `f = kp (0 - x) - kd xdot + (total mass) g e3` on the drone,
  kp = 20 N/m, kd = 8 N s/m.

Gravity 9.81 along -e3. Every method integrates them with the classic fourth-order
Runge-Kutta method at the fixed step dt = 1e-3 (four force evaluations per step):

- sphere_mech: `sm.simulate_batch` with `sm.Projected(sm.RK4())` of the system as a
  `Scene` with a `Base` (`our_system`: the O(n) fast path), sharded over the devices (on
  CPU one device per core);
- sphere_mech (general L): the same, with the scene's energies and forces written as a
  user's `sm.Lagrangian` on `{"base": Euclidean(m), "spheres": Spheres(n)}` (Hessians of
  L by autodiff and a dense solve per evaluation);
- bare scan: the same RK4 step over the same `system.rates` and the same retraction, in
  a `lax.fori_loop` under `jax.vmap` on one device: the floor for our own code (on CPU
  at batch 1 only, see `BATCHED_BARE_SCAN`);
- MuJoCo (CPU): slide joints for the base, then ball joints carrying point masses (tiny
  rotational inertia), its RK4 integrator, stepped by `mujoco.rollout` on all cores; the
  drone's force is one `general` actuator per slide joint with an affine bias
  `kp (target - x) - kd xdot + feedforward` at zero control, recomputed at every stage;
- MJX (GPU, or CPU with --mjx): the same MuJoCo model stepped by `mujoco.mjx.step` in a
  `lax.fori_loop` under `jax.vmap`, when the `mujoco-mjx` package is installed. Not yet
  usable on the drone: with --mjx on CPU (float64) its agreement check fails (it is then
  left out of the timings, with a message), MJX 8.8e-5 from sphere_mech (cart pendulum:
  5.6e-9). At one drone state MJX's actuator forces equal MuJoCo C's but its accelerations
  differ by 1.6e-3 (the point masses' 1e-12 rotational inertia against the 1.5 kg base;
  the free drone agrees to 2.5e-8).

First the methods are checked to agree: the positions of every point mass (the base
included) after 0.2 s from random states (links within 60 degrees of -e3, the base within
0.1 m of 0, small velocities). Then system-steps per second (trajectories x steps / wall
time after compilation, median of 3 repeats) at batch 1, 64, 1024 and 8192, with the ratio
to the peer (MuJoCo on CPU, MJX on GPU) measured in the same run. Prints a markdown table
and writes benchmarks/results/mixed_throughput_<device>[_<dtype>][_quick].{md,json,png}
(the dtype when it is not the device's default, float64 on CPU and float32 on GPU).

    python benchmarks/mixed_throughput.py [--quick] [--device cpu|gpu]
        [--dtype float32|float64] [--mjx]

`--quick`: batches 1, 64, 1024 and fewer steps. `--device gpu` fails unless JAX sees a
GPU; it defaults to float32 (CPU: float64).
"""

import sys

from _options import CORES, parse_options, require_device

OPTS = parse_options(__doc__.splitlines()[0])

import datetime  # noqa: E402
import json  # noqa: E402
from typing import NamedTuple  # noqa: E402

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", OPTS.dtype == "float64")
import _peers as peers  # noqa: E402
from _harness import RESULTS, cpu_name, load, publish, pyplot, save_figure, table  # noqa: E402
from _peers import DT, HAVE_MJX, G, chain_xml, final_positions, joint_state  # noqa: E402

import sphere_mech as sm  # noqa: E402

AGREEMENT = {"float64": 1e-8, "float32": 1e-3}[OPTS.dtype]
"""Largest position difference accepted between methods after 0.2 s, as in
throughput.py (MJX: 1e-6, its own difference from MuJoCo C there)."""
MJX_AGREEMENT = max(AGREEMENT, 1e-6)
INERTIA = 1e-12
"""The point masses' rotational inertia in MuJoCo: the cable's links have m l^2 = 8e-4,
and throughput.py's 1e-10 (for m l^2 = 1) left a model difference of 3e-8 in the
positions after 0.2 s (measured at dt = 2.5e-4, where the RK4 errors are below it)."""


class Setup(NamedTuple):
    axes: tuple  # the base's directions in space, one per coordinate
    base_mass: float
    masses: tuple  # the point masses at the links' tips
    lengths: tuple
    gains: tuple | None  # (kp, kd) of the hover controller, or None: free
    target: tuple = (0.0, 0.0, 0.0)


SYSTEMS = {
    "cart pendulum": Setup(((1.0, 0.0, 0.0),), 1.0, (0.5,), (0.8,), None),
    "drone with a cable": Setup(
        ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
        1.5,
        (0.02,) * 4 + (0.32,),
        (0.2,) * 5,
        (20.0, 8.0),
    ),
}


# ------------------------------------------------------------------------ sphere_mech
GENERAL = "sphere_mech (general L)"


def our_system(kind):
    """The system `kind` of SYSTEMS as a `Scene`: a `Base`, a `Chain` hanging from it,
    gravity and the hover force (`BaseForce(PDPosition(...))`): the O(n) fast path."""
    s = SYSTEMS[kind]
    effects = [sm.Base(s.base_mass, axes=s.axes), sm.Chain(s.masses, s.lengths), sm.Gravity(G)]
    if s.gains:
        E, weight = np.asarray(s.axes), (s.base_mass + sum(s.masses)) * G
        effects.append(
            sm.BaseForce(
                sm.PDPosition(
                    *s.gains, target=E @ np.asarray(s.target), feedforward=weight * E[:, 2]
                )
            )
        )
    return sm.Scene(*effects)


def general_twin(scene):
    """The same energies and forces written as a user's `sm.Lagrangian` on the product
    space: the general path (Hessians of L by autodiff, a dense solve)."""
    lagrangian = lambda t, q, qdot, args: scene.kinetic_energy(q, qdot) - scene.potential(t, q)
    return sm.Lagrangian(lagrangian, scene.forces, space=scene.space)


# ------------------------------------------------------------------------------ MuJoCo
def mujoco_xml(kind):
    """The system `kind` as a MuJoCo model; the hover force as `general` actuators whose
    affine bias `b0 + b1 x + b2 xdot` is the whole force at zero control."""
    s = SYSTEMS[kind]
    actuators = ""
    if s.gains:
        kp, kd = s.gains
        weight = (s.base_mass + sum(s.masses)) * G
        actuators = (
            "<actuator>"
            + "".join(
                f'<general joint="slide{k}" biastype="affine" '
                f'biasprm="{float(kp * np.dot(a, s.target) + weight * a[2])!r} {-kp!r} {-kd!r}"/>'
                for k, a in enumerate(s.axes)
            )
            + "</actuator>"
        )
    slides = [" ".join(map(str, a)) for a in s.axes]
    return chain_xml(s.lengths, s.masses, s.base_mass, slides, actuators, inertia=INERTIA)


def to_joints(q, v):
    return joint_state(q["spheres"], v["spheres"], q["base"], v["base"])


# ----------------------------------------------------------------------------- states
def random_states(kind, batch, seed=0):
    """Links within 60 degrees of -e3, the base within 0.1 m of 0, small velocities."""
    s, rng = SYSTEMS[kind], np.random.default_rng(seed)
    m, n = len(s.axes), len(s.lengths)
    q, v = peers.hanging_links(rng, batch, n)
    dtype = jnp.zeros(()).dtype
    q0 = {"base": rng.uniform(-0.1, 0.1, (batch, m)), "spheres": q}
    v0 = {"base": rng.normal(0.0, 0.1, (batch, m)), "spheres": v}
    return jax.tree.map(lambda a: jnp.asarray(a, dtype), (q0, v0))


# ------------------------------------------------------------------------- the methods
def methods(kind):
    """The methods this run compares; the first is the peer that ratios divide by."""
    system = our_system(kind)
    ours = [
        peers.SphereMech(system, system.points),
        peers.SphereMech(general_twin(system), system.points, GENERAL),
        peers.BareScan(system, system.points),
    ]
    if OPTS.device == "gpu":
        return ([peers.MJX(mujoco_xml(kind), to_joints)] if HAVE_MJX else []) + ours
    mjx = [peers.MJX(mujoco_xml(kind), to_joints)] if OPTS.mjx else []
    return [peers.MuJoCo(mujoco_xml(kind), to_joints), *ours, *mjx]


EXACT_TOL = {"float64": 1e-13, "float32": 1e-6}[OPTS.dtype]
"""The reference's tolerance: near the dtype's rounding (float32's 1e-13 never stops)."""


def exact_positions(kind, y, t1):
    """The point masses' positions at `t1` by `Projected(Dopri8())` at `EXACT_TOL`."""
    system = our_system(kind)
    sol = sm.simulate_batch(
        system,
        y,
        t1,
        solver=sm.Projected(diffrax.Dopri8()),
        rtol=EXACT_TOL,
        atol=EXACT_TOL,
        max_steps=100_000,
    )
    final = jax.tree.map(lambda a: a[:, -1], sol.ys[0])
    return np.asarray(jax.vmap(system.points)(final))


def check_agreement(kind, batch=4, nsteps=200):
    """Max position differences from sphere_mech after `nsteps` steps, and each method's
    RK4 error (against `exact_positions`). The bare scan runs sphere_mech's arithmetic
    and is held to AGREEMENT. MuJoCo's RK4 steps other coordinates (quaternions), so
    its truncation error differs from ours: it is held to AGREEMENT plus twice our RK4
    error (on the cable, whose light links swing fast, both are about 3e-7 at dt = 1e-3
    and fall 16-fold per halving of dt). MJX over its bound (see the module's docstring)
    is left out of the timings, with a message; any other method over its bound stops
    the run. Returns the errors and the methods left out."""
    y = random_states(kind, batch, seed=7)
    pos = final_positions(methods(kind), y, nsteps)
    exact = exact_positions(kind, y, nsteps * DT)
    diff = lambda a, b: float(np.max(np.abs(a - b)))
    ours = pos["sphere_mech"]
    errors = {
        name: {"difference": diff(p, ours), "rk4_error": diff(p, exact)} for name, p in pos.items()
    }
    print(
        f"\n{kind}, after {nsteps * DT:g} s ({batch} random states): "
        + "; ".join(
            f"{name} {e['difference']:.1e} from sphere_mech, {e['rk4_error']:.1e} "
            "from the exact solution"
            for name, e in errors.items()
        ),
        flush=True,
    )
    slack = AGREEMENT + 2 * errors["sphere_mech"]["rk4_error"]
    # The general path equals the fast path on the tangent bundle (to 1e-12, tested) but
    # not at the RK4 stages' points off it (|q| != 1): a difference within the RK4 error.
    bound = {
        "sphere_mech": 0.0,
        GENERAL: slack,
        "bare scan": AGREEMENT,
        "MuJoCo": slack,
        "MJX": max(MJX_AGREEMENT, slack),
    }
    over = [name for name, e in errors.items() if e["difference"] > bound[name]]
    assert set(over) <= {"MJX"}, errors
    for name in over:
        print(
            f"{kind}: {name} left out of the timings, {errors[name]['difference']:.1e} "
            f"from sphere_mech (bound {bound[name]:.1e})",
            flush=True,
        )
    return errors, over


BATCHED_BARE_SCAN = OPTS.device == "gpu"
"""The bare scan runs at every batch on one GPU only, as in throughput.py; on CPU at
batch 1 only, the cost of one trajectory's steps. There sphere_mech splits the batch
over the cores and into chunks and the bare scan does not, and the bare scan of the drone
at batch 1024 (one `vmap` of this `sm.Lagrangian`'s dense `jnp.linalg.solve` on one of
the two host devices) stalled with no CPU use, twice; with one host device it ran."""


def measure(kind, batches, budget, left_out=()):
    """`{method: {batch: (system-steps/s, compile s)}}`, about `budget` system-steps a
    run, for the methods not `left_out`."""
    out = {}
    for batch in batches:
        y = random_states(kind, batch, seed=1)
        for method in methods(kind):
            if method.name in left_out or (
                method.name == "bare scan" and batch > 1 and not BATCHED_BARE_SCAN
            ):
                continue
            rate, compile_s, _ = peers.throughput(method, y, budget, repeats=3)
            out.setdefault(method.name, {})[batch] = (rate, compile_s)
            print(f"{kind}, {method.name}, batch={batch}: {rate:.3g} steps/s", flush=True)
    return out


# ------------------------------------------------------------------------------ report
def report(records, stem, setting):
    lines = []
    for kind, by_method in records["batch"].items():
        peer = next(iter(by_method))  # the first method measured (MJX may be left out)
        for batch in by_method[peer]:
            base = by_method[peer][batch][0]
            for name in (name for name in by_method if batch in by_method[name]):
                rate, compile_s = by_method[name][batch]
                lines.append(
                    (kind, batch, name, f"{rate:.3g}", f"{rate / base:.2f}", f"{compile_s:.1f}")
                )
    throughput = table(
        ["system", "batch", "method", "system-steps/s", "ratio to the peer", "compile (s)"],
        lines,
    )
    agreement = table(
        ["system", "method", "from sphere_mech", "from the exact solution"],
        [
            (kind, name, f"{e['difference']:.1e}", f"{e['rk4_error']:.1e}")
            for kind, errs in records["agreement"].items()
            for name, e in errs.items()
            if name != "sphere_mech"
        ],
    )
    loads = " and ".join(f"{x:.1f}" for x in records["load"])
    left_out = "".join(
        f" {kind}: {', '.join(names)} left out of the timings (over its agreement bound)."
        for kind, names in records["left_out"].items()
        if names
    )
    publish(
        f"Command: `{records['command']}`. Measured on {setting}, {records['date']} "
        f"(1-minute load average {loads} at the start and the end).\n\n"
        "Agreement: max position difference after 0.2 s (4 random states), from "
        "sphere_mech and from the exact solution (`Projected(Dopri8())` at 1e-13); "
        f"sphere_mech's own RK4 error is the bare scan's.{left_out}\n\n{agreement}\n\n"
        f"Throughput:\n\n{throughput}\n",
        f"{stem}.md",
    )

    plt = pyplot()
    colors = {"sphere_mech": "C0", GENERAL: "C2", "bare scan": "C1", "MuJoCo": "C3", "MJX": "C4"}
    kinds = list(records["batch"])
    fig, axes = plt.subplots(1, len(kinds), figsize=(5.5 * len(kinds), 4.2), sharey=True)
    for ax, kind in zip(axes, kinds, strict=True):
        for name, by_batch in records["batch"][kind].items():
            pts = sorted((int(b), r) for b, (r, _) in by_batch.items())
            ax.loglog(*zip(*pts, strict=True), marker="o", color=colors[name], label=name)
        ax.set(xlabel="batch size", title=f"{kind} (RK4, dt = {DT:g})")
        ax.legend()
    axes[0].set_ylabel("system-steps per second")
    fig.suptitle(setting, fontsize=9)
    save_figure(fig, f"{stem}.png")


def main():
    require_device(OPTS)
    gpu = OPTS.device == "gpu"
    batches = (
        (1, 64, 1024) if OPTS.quick else (1, 64, 1024, 8192, 65536) if gpu else (1, 64, 1024, 8192)
    )
    budget = (5e4 if OPTS.quick else 2e5) * (100 if gpu else 1)  # system-steps a run
    device = jax.devices()[0].device_kind if gpu else f"{cpu_name()}, {CORES} cores"
    setting = f"{device}, {OPTS.dtype}"
    print(f"devices: {jax.devices()}; {setting}, RK4, dt = {DT}")
    records = {
        "command": " ".join(["python benchmarks/mixed_throughput.py", *sys.argv[1:]]),
        "setting": setting,
        "date": datetime.date.today().isoformat(),
        "load": [load()],
    }
    checks = {kind: check_agreement(kind) for kind in SYSTEMS}
    records["agreement"] = {kind: errors for kind, (errors, _) in checks.items()}
    records["left_out"] = {kind: over for kind, (_, over) in checks.items()}
    records["batch"] = {
        kind: measure(kind, batches, budget, records["left_out"][kind]) for kind in SYSTEMS
    }
    records["load"].append(load())
    default_dtype = "float32" if gpu else "float64"
    stem = (
        f"mixed_throughput_{OPTS.device}"
        + (f"_{OPTS.dtype}" if OPTS.dtype != default_dtype else "")
        + ("_quick" if OPTS.quick else "")
    )
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{stem}.json").write_text(json.dumps(records, indent=1))
    report(records, stem, setting)


if __name__ == "__main__":
    main()
