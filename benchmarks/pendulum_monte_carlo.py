"""Monte Carlo of the FDCL 3-D pendulum: sphere_mech against MuJoCo and a scipy loop.

The setup of Lee et al.'s 3-D pendulum uncertainty propagation (public repository
fdcl-gwu/hybridPendulum-UP, `propagation/pendulum_MC.m`; its equations and parameters
only, no code): a rigid body on a fixed frictionless pivot, `J Omegadot = J Omega x
Omega + m g (R^T e3) x rho`, with J = tr(J_d) I - J_d for J_d = diag(1, 2, 3) (so
J = diag(5, 4, 3) about the pivot), rho = (0, 0, 1), m = 10, g = 9.8, dt = 0.01, and
1e5 samples from their initial density: the attitude from the matrix Fisher density
with F = exp(hat(2 pi/3 e1)) diag(5, 5, 5) (sampled here by rejection from an angular
central Gaussian on unit quaternions, Kent, Ganeiber and Mardia 2013) and the body
angular velocity Gaussian, mean 0, standard deviation 2 rad/s a component (their
`Sigma = (2 tscale)^2 I` in scaled time). Their damping and process noise are left
out: every method integrates the same deterministic dynamics, 50 steps (T = 0.5 s; their
horizon is 1 s, `--steps 100`: 50 keeps the default run under about 5 minutes on a loaded
2-core machine). Methods:

- sphere_mech: `sm.simulate_batch` of `sm.AngularLagrangian(L)` on `sm.Rotations(1)`,
  `L = 1/2 Omega.J Omega - m g e3.(R rho)`, fixed step dt,
  `quadratic_in_velocity=True` (one linear solve for the velocity); `--solver
  variational` (default: `sm.Variational()`, Lee, Leok and McClamroch's Lie group
  variational integrator), `chord` (the same with `root_finder="chord"`), `variational4`
  (`sm.Variational(4)`) or `lierk` (`sm.LieRK(sm.RK4())`),
  `chunk_size` 50000 (`--chunk`; the library's CPU default, about 512 rows, measured 4x
  slower here), timed on one device and sharded over all of them (`--devices`: XLA is
  asked for one CPU device per core; on the loaded machine one device was 3x faster);
- MuJoCo (C, `mujoco.rollout` on all cores): a body on a ball joint with its RK4
  integrator at the same step and number of steps (the peer of the ratios), and with its
  default semi-implicit Euler integrator (cheaper, less accurate). MuJoCo's inertia must
  be positive about the centre of mass, and m = 10 at |rho| = 1 with J = diag(5, 4, 3)
  about the pivot leaves diag(-5, -6, 3) there. The dynamics on a fixed pivot depend only
  on the inertia about the pivot J and the first moment m rho, so the model carries the
  same J and the same m rho with mass m' = 100 at rho' = rho / 10 (inertia diag(4, 3, 3)
  about its centre of mass): the same equation of motion, all in MuJoCo's C loop (no
  per-step callback). Its ball joint's `qvel` is the body angular velocity Omega;
- scipy: `solve_ivp` (DOP853, `--scipy-rtol`) on the unit-quaternion ODE, one sample
  after another, on a small subset; its time for all samples is extrapolated.

First the methods are checked against a tight reference (the same quaternion ODE,
DOP853 at rtol = atol = 1e-13) on a subset: the attitude error angle at the final time
is the accuracy at which they are compared. Then the whole batch is timed (compiled
first; MuJoCo warmed up on a few samples), and throughput is reported as
samples x steps per second with the ratios to MuJoCo's RK4. The load average of the
machine is recorded (a loaded machine slows the methods unevenly). Writes
benchmarks/results/pendulum_monte_carlo{,_<solver>}{,_gpu}{,_quick}.{md,png} (`_<solver>` unless
the default variational): the table, the throughput and
the Monte Carlo's spread (the distribution of e3.(R rho), the height of the centre of
mass over the pivot, at a few times, and of the direction R rho).

    python benchmarks/pendulum_monte_carlo.py [--quick]
        [--solver variational|chord|variational4|lierk] [--device cpu|gpu]
"""

from _options import CORES, parse_options, require_device

SOLVERS = ("variational", "chord", "variational4", "lierk")


def add_arguments(parser):
    parser.add_argument("--samples", type=int, help="Monte Carlo samples (default 1e5)")
    parser.add_argument(
        "--steps", type=int, help="steps of dt = 0.01 (default 50, T = 0.5 s; 20 with --quick)"
    )
    parser.add_argument("--solver", choices=SOLVERS, default="variational")
    parser.add_argument(
        "--chunk", type=int, default=50_000, help="simulate_batch's chunk_size (default 50000)"
    )
    parser.add_argument(
        "--devices", type=int, nargs="+", help="JAX device counts to time (default: 1 and all)"
    )
    parser.add_argument("--scipy-samples", type=int, help="samples in the scipy loop")
    parser.add_argument("--scipy-rtol", type=float, default=1e-8, help="scipy's rtol = atol")
    parser.add_argument("--check-samples", type=int, help="samples checked against the reference")
    parser.add_argument("--seed", type=int, default=0)


OPTS = parse_options(__doc__.splitlines()[0], add_arguments, mjx=False)

import functools  # noqa: E402
import time  # noqa: E402

import diffrax  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from mujoco import rollout  # noqa: E402
from scipy.integrate import solve_ivp  # noqa: E402
from scipy.optimize import brentq  # noqa: E402

jax.config.update("jax_enable_x64", OPTS.dtype == "float64")
from _harness import load, machine, publish, pyplot, save_figure, table, timing  # noqa: E402

import sphere_mech as sm  # noqa: E402

# ----------------------------------------------------------------------- their setup
J_D = np.diag([1.0, 2.0, 3.0])
J = np.diag(np.trace(J_D) * np.eye(3) - J_D)  # (5, 4, 3): the inertia about the pivot
RHO = np.array([0.0, 0.0, 1.0])  # the centre of mass in the body frame (m)
MASS, G, DT = 10.0, 9.8, 0.01
F_ROTATION = np.array([2 * np.pi / 3, 0.0, 0.0])  # F = exp(hat(F_ROTATION)) diag(F_SINGULAR)
F_SINGULAR = np.array([5.0, 5.0, 5.0])
OMEGA_STD = 2.0  # rad/s, each component of the body angular velocity
SPREAD_TIMES = (0.0, 0.25, 0.5, 1.0)  # fractions of T at which the spread is shown
REFERENCE_TOL = 1e-13
MUJOCO_INTEGRATORS = ("RK4", "Euler")  # RK4 the peer; Euler (semi-implicit) MuJoCo's default
PEER = "MuJoCo RK4"
SCIPY = f"scipy DOP853 (rtol {OPTS.scipy_rtol:g})"
STEM = "pendulum_monte_carlo" + ("" if OPTS.solver == "variational" else f"_{OPTS.solver}")
STEM += ("_gpu" if OPTS.device == "gpu" else "") + ("_quick" if OPTS.quick else "")


# --------------------------------------------------------------------- quaternions
def quaternion_matrix(qt):
    """Rotation matrices of unit quaternions `(..., 4)` = (w, x, y, z)."""
    w, x, y, z = np.moveaxis(np.asarray(qt), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def quaternion_product(a, b):
    """`a b` of quaternions `(..., 4)`."""
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    vector = aw * bv + bw * av + np.cross(av, bv)
    return np.concatenate([aw * bw - np.sum(av * bv, -1, keepdims=True), vector], -1)


def axis_angle_quaternion(v):
    """The unit quaternion of the rotation vector `v` (3,)."""
    angle = np.linalg.norm(v)
    return np.concatenate([[np.cos(angle / 2)], 0.5 * np.sinc(angle / (2 * np.pi)) * v])


def angle_between(A, B):
    """The rotation angle of `A^T B` (rad), accurate for small angles:
    `|A - B|_F = 2 sqrt(2) sin(angle / 2)`."""
    frobenius = np.linalg.norm(np.asarray(A) - np.asarray(B), axis=(-2, -1))
    return 2 * np.arcsin(np.minimum(frobenius / (2 * np.sqrt(2)), 1.0))


# ----------------------------------------------------------- their initial density
def sample_matrix_fisher_quaternions(rotation, singular, size, rng):
    """Unit quaternions `(size, 4)` of rotations from the matrix Fisher density
    `exp(tr(F^T R))`, `F = exp(hat(rotation)) diag(singular)` (`singular` the proper
    singular values). `R = U Q` with `Q` of density `exp(tr(S Q))`, which is the Bingham
    density `exp(q^T D q)` on Q's unit quaternion q, D = diag(s1 + s2 + s3, s1 - s2 - s3,
    -s1 + s2 - s3, -s1 - s2 + s3); sampled by rejection from the angular central
    Gaussian envelope of Kent, Ganeiber and Mardia (2013)."""
    s1, s2, s3 = singular
    d = np.array([s1 + s2 + s3, s1 - s2 - s3, -s1 + s2 - s3, -s1 - s2 + s3])
    lam = d.max() - d  # exp(q^T D q) = const exp(-q^T A q), A = diag(lam) >= 0
    b = brentq(lambda b: np.sum(1.0 / (b + 2 * lam)) - 1.0, 1e-12, 4.0)
    omega = 1.0 + 2.0 * lam / b  # the envelope's precision: y ~ N(0, diag(omega)^-1)
    log_bound = -(4 - b) / 2 + 2 * np.log(4 / b)
    accepted = []
    while sum(len(a) for a in accepted) < size:
        y = rng.standard_normal((2 * size + 64, 4)) / np.sqrt(omega)
        x = y / np.linalg.norm(y, axis=1, keepdims=True)
        log_ratio = -(x * x) @ lam + 2 * np.log((x * x) @ omega) - log_bound
        accepted.append(x[np.log(rng.uniform(size=len(x))) < log_ratio])
    q = np.concatenate(accepted)[:size]
    return quaternion_product(axis_angle_quaternion(rotation)[None], q)


def initial_states(size, seed):
    """Their initial density: quaternions `(size, 4)` and body angular velocities
    `(size, 3)`."""
    rng = np.random.default_rng(seed)
    quats = sample_matrix_fisher_quaternions(F_ROTATION, F_SINGULAR, size, rng)
    return quats, OMEGA_STD * rng.standard_normal((size, 3))


# ---------------------------------------------------------------------- sphere_mech
def lagrangian(t, R, W, args):
    return 0.5 * jnp.sum(jnp.asarray(J) * W**2) - MASS * G * (R[0] @ jnp.asarray(RHO))[2]


SYSTEM = sm.AngularLagrangian(lagrangian, space=sm.Rotations(1), quadratic_in_velocity=True)


def solver():
    return {
        "variational": lambda: sm.Variational(),
        "chord": lambda: sm.Variational(root_finder="chord"),
        "variational4": lambda: sm.Variational(4),
        "lierk": lambda: sm.LieRK(sm.RK4()),
    }[OPTS.solver]()


SOLVER_NAME = {
    "variational": "Variational()",
    "chord": 'Variational(root_finder="chord")',
    "variational4": "Variational(4)",
    "lierk": "LieRK(RK4())",
}[OPTS.solver]
OURS = f"sphere_mech {SOLVER_NAME}"


def sphere_mech_run(quats, omega, steps, times=None, devices=1):
    """`(R (batch, len(times), 3, 3), Omega (batch, len(times), 3))` at `times` (default:
    the final time) from `simulate_batch` with the fixed step DT on the first `devices`
    of JAX's devices."""
    T = steps * DT
    ts = jnp.asarray([T] if times is None else times)
    y0 = (jnp.asarray(quaternion_matrix(quats))[:, None], jnp.asarray(omega)[:, None])
    sol = sm.simulate_batch(
        SYSTEM,
        y0,
        T,
        solver=solver(),
        dt0=DT,
        stepsize_controller=diffrax.ConstantStepSize(),
        saveat=diffrax.SaveAt(ts=ts),
        max_steps=steps + 1,
        chunk_size=OPTS.chunk,
        devices=jax.devices()[:devices],
    )
    return sol.ys[0][:, :, 0], sol.ys[1][:, :, 0]


# --------------------------------------------------------------------------- MuJoCo
MJ_OFFSET = 0.1  # |rho'|: the model's centre of mass, rho' = MJ_OFFSET rho / |rho|


def mujoco_xml(integrator="RK4"):
    """The body on a ball joint with J about the pivot and first moment m rho: mass
    m' = m |rho| / MJ_OFFSET at rho' (see the module's docstring)."""
    assert RHO[0] == RHO[1] == 0.0  # rho along the body's e3 axis
    mass = float(MASS * np.linalg.norm(RHO) / MJ_OFFSET)
    com = MJ_OFFSET * RHO / np.linalg.norm(RHO)
    inertia = J - mass * (com @ com - com * com)  # parallel axes: about the centre of mass
    assert np.all(inertia > 0)
    numbers = lambda v: " ".join(repr(float(x)) for x in v)
    return (
        f'<mujoco><option timestep="{DT!r}" integrator="{integrator}" gravity="0 0 {-G!r}">'
        '<flag contact="disable" constraint="disable"/></option><worldbody><body>'
        f'<joint type="ball"/><inertial pos="{numbers(com)}" mass="{mass!r}" '
        f'diaginertia="{numbers(inertia)}"/></body></worldbody></mujoco>'
    )


class MuJoCo:
    """The model with `integrator` stepped by `mujoco.rollout` on `CORES` threads, `chunk`
    samples a call (its output holds every step's state: this bounds the memory)."""

    def __init__(self, integrator="RK4", chunk=20_000):
        self.name = f"MuJoCo {integrator}"
        self.model = mujoco.MjModel.from_xml_string(mujoco_xml(integrator))
        self.data = [mujoco.MjData(self.model) for _ in range(CORES)]
        self.spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.chunk = chunk

    def states(self, quats, omega):
        d = self.data[0]
        mujoco.mj_resetData(self.model, d)
        state = np.zeros(mujoco.mj_stateSize(self.model, self.spec))
        mujoco.mj_getState(self.model, d, state, self.spec)
        states = np.tile(state, (len(quats), 1))
        states[:, 1:5] = quats  # after the time: qpos = the ball joint's quaternion
        states[:, 5:8] = omega  # qvel: the body angular velocity
        return states

    def run(self, states, steps):
        """Quaternions `(batch, 4)` after `steps` steps."""
        final = []
        for start in range(0, len(states), self.chunk):
            part = states[start : start + self.chunk]
            out, _ = rollout.rollout(self.model, self.data[: len(part)], part, nstep=steps)
            final.append(out[:, -1, 1:5])
        return np.concatenate(final)


# ---------------------------------------------------------------------------- scipy
def quaternion_ode(t, y):
    """`qdot = q (0, Omega) / 2`, `J Omegadot = J Omega x Omega + m g (R^T e3) x rho`."""
    q, w = y[:4], y[4:]
    w0, w1, w2, w3 = q
    e3_body = 2 * np.array([w1 * w3 - w0 * w2, w2 * w3 + w0 * w1, 0.5 - w1 * w1 - w2 * w2])
    wdot = (np.cross(J * w, w) + MASS * G * np.cross(e3_body, RHO)) / J
    qdot = 0.5 * quaternion_product(q, np.concatenate([[0.0], w]))
    return np.concatenate([qdot, wdot])


def scipy_run(quats, omega, T, rtol, method="DOP853"):
    """Final quaternions, one `solve_ivp` a sample."""
    final = []
    for q, w in zip(quats, omega, strict=True):
        sol = solve_ivp(
            quaternion_ode, (0.0, T), np.concatenate([q, w]), method, rtol=rtol, atol=rtol
        )
        final.append(sol.y[:4, -1] / np.linalg.norm(sol.y[:4, -1]))
    return np.array(final)


# ------------------------------------------------------------------------ the runs
def check_accuracy(quats, omega, steps):
    """The attitude error angle at T against the tight reference, per method (rad)."""
    T = steps * DT
    reference = quaternion_matrix(scipy_run(quats, omega, T, REFERENCE_TOL))
    R_ours = np.asarray(sphere_mech_run(quats, omega, steps)[0][:, -1])
    R_mujoco = {}
    for integrator in MUJOCO_INTEGRATORS:
        mj = MuJoCo(integrator)
        R_mujoco[mj.name] = quaternion_matrix(mj.run(mj.states(quats, omega), steps))
    R_scipy = quaternion_matrix(scipy_run(quats, omega, T, OPTS.scipy_rtol))
    errors = {
        OURS: angle_between(R_ours, reference),
        **{name: angle_between(R, reference) for name, R in R_mujoco.items()},
        SCIPY: angle_between(R_scipy, reference),
    }
    between = float(np.max(angle_between(R_ours, R_mujoco[PEER])))
    # A wrong model (frame of Omega, inertia, sign of gravity) is off by O(1) rad, the
    # second-order Variational at dt = 0.01 by up to about 1e-2 (truncation); MuJoCo's
    # first-order Euler is only reported.
    checked = (OURS, PEER)
    assert all(float(np.max(errors[name])) < 0.1 for name in checked), errors
    return errors, between


def measure(quats, omega, steps, scipy_samples):
    """`{method: (seconds, samples x steps per second, note)}`, the load averages,
    sphere_mech's `Timing` (its result: the states at the spread times) and MuJoCo's final
    attitudes."""
    batch, T = len(quats), steps * DT
    loads, results = [load()], {}
    times = [f * T for f in SPREAD_TIMES]

    ours = None
    for count in OPTS.devices or sorted({1, jax.device_count()}):
        run = functools.partial(sphere_mech_run, quats, omega, steps, times, count)
        t = timing(run, repeats=2, slow=30.0, what=OURS)
        loads.append(load())
        name = f"{OURS}, {count} device{'s' * (count > 1)}"
        note = f"compiled in {t.compile:.1f} s (first call, not counted)"
        results[name] = (t.median, batch * steps / t.median, note, OURS)
        ours = ours or t

    final_mujoco = None
    for integrator in MUJOCO_INTEGRATORS:
        mj = MuJoCo(integrator)
        states = mj.states(quats, omega)
        run = functools.partial(mj.run, states, steps)
        warmup = functools.partial(mj.run, states[: 4 * CORES], steps)
        t = timing(run, repeats=1, warmup=warmup, what=mj.name)
        loads.append(load())
        results[mj.name] = (t.median, batch * steps / t.median, "", mj.name)
        final_mujoco = quaternion_matrix(t.result) if mj.name == PEER else final_mujoco

    start = time.perf_counter()
    scipy_run(quats[:scipy_samples], omega[:scipy_samples], T, OPTS.scipy_rtol)
    seconds = (time.perf_counter() - start) * batch / scipy_samples
    loads.append(load())
    results[SCIPY] = (
        seconds,
        batch * steps / seconds,
        f"{scipy_samples} samples, extrapolated",
        SCIPY,
    )
    return results, loads, ours, final_mujoco


def report(results, loads, errors, between, spread, R_mujoco, batch, steps):
    peer = PEER
    base = results[peer][1]
    rows = [
        (
            name,
            f"{seconds:.3g}",
            f"{rate:.3g}",
            f"{rate / base:.2f}",
            f"{np.max(errors[key]):.1e}",
            f"{np.median(errors[key]):.1e}",
            note,
        )
        for name, (seconds, rate, note, key) in results.items()
    ]
    setting = f"{machine(loads)}, {OPTS.dtype}"
    if OPTS.device == "gpu":  # MuJoCo and scipy still run on the host's cores
        setting = f"sphere_mech on one {jax.devices()[0].device_kind}, the rest on {setting}"
    text = (
        f"\n3-D pendulum Monte Carlo (FDCL setup): {batch} samples x {steps} steps of "
        f"dt = {DT} (T = {steps * DT:g} s), {setting}.\n\n"
        + table(
            [
                "method",
                f"time for {batch} samples (s)",
                "samples x steps / s",
                f"ratio to {peer}",
                "max error at T (rad)",
                "median error (rad)",
                "note",
            ],
            rows,
            "lrrrrrl",
        )
        + f"\n\nErrors: the attitude error angle at T against scipy DOP853 at rtol = atol = "
        f"{REFERENCE_TOL:g} on {len(next(iter(errors.values())))} samples; sphere_mech and "
        f"MuJoCo differ by {between:.1e} rad at most there. Times: sphere_mech's median of "
        "repeats after the first call (which compiles), MuJoCo's one call after a warm-up on a "
        "few samples.\n"
    )
    publish(text, f"{STEM}.md")

    R, _ = spread
    R = np.asarray(R)
    heights = R @ RHO  # (batch, times, 3): the direction R rho; e3 . R rho its height
    plt = pyplot()
    fig, (ax0, ax1, ax2) = plt.subplots(1, 3, figsize=(15, 4.4))
    names = list(results)
    ax0.barh(
        names,
        [results[n][1] for n in names],
        color=[
            "C0" if n.startswith(OURS) else "C3" if n == PEER else "C2" if n == SCIPY else "C1"
            for n in names
        ],
    )
    ax0.set(xscale="log", xlabel="samples x steps per second", title="Throughput")
    bins = np.linspace(-1, 1, 61)
    T = steps * DT
    for k, fraction in enumerate(SPREAD_TIMES):
        ax1.hist(
            heights[:, k, 2], bins, histtype="step", color=f"C{k}", label=f"t = {fraction * T:g} s"
        )
    ax1.hist(
        (R_mujoco @ RHO)[:, 2],
        bins,
        histtype="step",
        color="k",
        ls=":",
        label=f"MuJoCo, t = {T:g} s",
    )
    ax1.set(xlabel="e3 . R rho (height of the centre of mass)", ylabel="samples", title="Spread")
    ax1.legend(fontsize=8)
    few = slice(0, min(batch, 2000))
    for k, fraction in enumerate(SPREAD_TIMES):
        v = heights[few, k]  # Lambert's equal-area map about -e3: +e3 at radius 2
        x, y = (np.sqrt(2 / np.maximum(1 - v[:, 2], 1e-12))[:, None] * v[:, :2]).T
        ax2.scatter(x, y, s=2, alpha=0.5, color=f"C{k}", label=f"t = {fraction * T:g} s")
    ax2.add_patch(plt.Circle((0, 0), 2, fill=False, color="0.6"))
    ax2.set(
        xlim=(-2.05, 2.05),
        ylim=(-2.05, 2.05),
        xlabel="e1 (equal-area map of R rho about -e3)",
        ylabel="e2",
        title=f"Direction R rho ({few.stop} samples)",
    )
    ax2.set_aspect("equal")
    ax2.legend(fontsize=8, markerscale=5)
    save_figure(fig, f"{STEM}.png")


def main():
    require_device(OPTS)
    quick = OPTS.quick
    batch = OPTS.samples or (2000 if quick else 100_000)
    steps = OPTS.steps or (20 if quick else 50)
    check = OPTS.check_samples or (8 if quick else 32)
    scipy_samples = OPTS.scipy_samples or (5 if quick else 40)
    print(f"devices: {jax.devices()}; {batch} samples, {steps} steps, solver {SOLVER_NAME}")
    quats, omega = initial_states(batch, OPTS.seed)
    errors, between = check_accuracy(quats[:check], omega[:check], steps)
    for name, e in errors.items():
        print(f"{name}: error at T {np.max(e):.1e} rad (max of {check})", flush=True)
    results, loads, ours, R_mujoco = measure(quats, omega, steps, scipy_samples)
    report(results, loads, errors, between, ours.result, R_mujoco, batch, steps)


if __name__ == "__main__":
    main()
