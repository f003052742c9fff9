"""The methods the MuJoCo comparisons (throughput.py, mixed_throughput.py) time, each
written once: sphere_mech's `simulate_batch`, the bare scan of the same RK4 step, MuJoCo
(C, `mujoco.rollout`) and MJX on a chain of ball joints carrying point masses, optionally
hanging from a base moved by slide joints; and the timing itself.

A method has a `name`, `prepare(q, v)` (a batch of sphere_mech states to its own),
`run(y, nsteps)` (returns its output and the steps taken) and `positions(out)` (the
point masses' positions at the end, `(batch, points, 3)`). Import after JAX is set up
(`_options.parse_options`, then x64)."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from _harness import timing
from _options import CORES
from mujoco import rollout

import sphere_mech as sm

try:
    from mujoco import mjx

    HAVE_MJX = True
except ImportError:
    HAVE_MJX = False

DT, G = 1e-3, 9.81


# ------------------------------------------------------------------------ sphere_mech
def rk4_step(f, y, dt=DT):
    """One classic RK4 step of `y' = f(y)` with step `dt`."""
    k1 = f(y)
    k2 = f(jax.tree.map(lambda a, b: a + 0.5 * dt * b, y, k1))
    k3 = f(jax.tree.map(lambda a, b: a + 0.5 * dt * b, y, k2))
    k4 = f(jax.tree.map(lambda a, b: a + dt * b, y, k3))
    return jax.tree.map(
        lambda a, b1, b2, b3, b4: a + dt / 6 * (b1 + 2 * b2 + 2 * b3 + b4), y, k1, k2, k3, k4
    )


def fixed_step_loop(step):
    """`solve(y, nsteps)`: `step` applied `nsteps` times to each element of a batch."""

    @jax.jit
    def solve(y, nsteps):
        return jax.vmap(lambda y_: jax.lax.fori_loop(0, nsteps, lambda i, x: step(x), y_))(y)

    return solve


class SphereMech:
    """`sm.simulate_batch` with `sm.Projected(sm.RK4())` at the fixed step DT; `positions`
    maps one configuration to its point masses' positions."""

    def __init__(self, system, positions, name="sphere_mech"):
        self.system, self.points, self.name = system, positions, name
        self.solver = sm.Projected(sm.RK4())

    def prepare(self, q, v):
        return q, v

    def run(self, y, nsteps):
        sol = sm.simulate_batch(
            self.system, y, nsteps * DT, solver=self.solver, dt0=DT, max_steps=100_000
        )
        jax.block_until_ready(sol.ys)
        return sol, int(np.max(sol.stats["num_steps"]))

    def positions(self, sol):
        final = jax.tree.map(lambda a: a[:, -1], sol.ys[0])
        return np.asarray(jax.vmap(self.points)(final))


class BareScan:
    """`Projected(RK4())`'s arithmetic with no diffrax loop: RK4 over the same
    `system.rates`, then the same retraction, in a `fori_loop` under `jax.vmap`."""

    name = "bare scan"

    def __init__(self, system, positions):
        self.points = positions
        rates = lambda y: system.rates(0.0, y, None)
        self.solve = fixed_step_loop(lambda y: system.space.retract(*rk4_step(rates, y)))

    def prepare(self, q, v):
        return q, v

    def run(self, y, nsteps):
        out = self.solve(y, nsteps)
        jax.block_until_ready(out)
        return out, nsteps

    def positions(self, out):
        return np.asarray(jax.vmap(self.points)(out[0]))


# ------------------------------------------------------------------------------ MuJoCo
def chain_xml(lengths, masses, base_mass=None, slides=(), actuators="", inertia=1e-10):
    """A MuJoCo model: a chain of ball joints with point masses `masses` (rotational
    inertia `inertia`) at the ends of links `lengths`, hanging along -e3 in its reference
    pose, RK4 at DT, gravity G, no contacts. With `slides` (joint axes such as "1 0 0"),
    the chain hangs from a base of mass `base_mass` moved by slide joints `slide0`,
    `slide1`, ... (before the ball joints); `actuators` is XML added to the model."""
    diag = f'diaginertia="{inertia} {inertia} {inertia}"'

    def body(i):
        if i == len(lengths):
            return ""
        pos = "0 0 0" if i == 0 else f"0 0 {-float(lengths[i - 1])!r}"
        return (
            f'<body pos="{pos}"><joint type="ball"/>'
            f'<inertial pos="0 0 {-float(lengths[i])!r}" mass="{float(masses[i])!r}" '
            f"{diag}/>{body(i + 1)}</body>"
        )

    tree = body(0)
    if slides:
        joints = "".join(
            f'<joint name="slide{k}" type="slide" axis="{axis}"/>' for k, axis in enumerate(slides)
        )
        tree = (
            f'<body>{joints}<inertial pos="0 0 0" mass="{float(base_mass)!r}" {diag}/>{tree}</body>'
        )
    return (
        f'<mujoco><option timestep="{DT}" integrator="RK4" gravity="0 0 {-G}">'
        '<flag contact="disable" constraint="disable"/></option>'
        f"<worldbody>{tree}</worldbody>{actuators}</mujoco>"
    )


def hanging_links(rng, batch, n):
    """Random chain states: links within 60 degrees of -e3 (uniform in the cap), tangent
    velocities of about 0.5 rad/s a component. **Returns:** `(q, v)`, `(batch, n, 3)` each."""
    cos_t = rng.uniform(np.cos(np.pi / 3), 1.0, (batch, n))
    phi = rng.uniform(0.0, 2 * np.pi, (batch, n))
    sin_t = np.sqrt(1 - cos_t**2)
    q = np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), -cos_t], axis=-1)
    return q, sm.project(jnp.asarray(q), jnp.asarray(rng.normal(0.0, 0.5, (batch, n, 3))))


def rotation_to(q):
    """The rotation matrix turning -e3 into the unit vector q (about -e3 x q)."""
    a = np.array([0.0, 0.0, -1.0])
    axis, c = np.cross(a, q), float(a @ q)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def joint_state(q, v, base=None, base_v=None, parent=None, parent_omega=None):
    """Joint coordinates `(qpos, qvel)` of a batch of chain states `(q, v)`: one
    quaternion per ball joint (relative to its parent link) and the relative angular
    velocity in the child's frame; before them the slide joints' positions `base` and
    velocities `base_v` (`(batch, m)`) when the chain hangs from a sliding base, which
    translates only, so the first link's parent frame is the world's. A chain hanging
    from a rotating body: its rotation `parent` `(batch, 3, 3)` and world angular velocity
    `parent_omega` `(batch, 3)` (the body's own joint is the caller's)."""
    q, v = np.asarray(q, dtype=float), np.asarray(v, dtype=float)
    batch, n = q.shape[:2]
    qpos, qvel = np.zeros((batch, 4 * n)), np.zeros((batch, 3 * n))
    for b in range(batch):
        R_prev = np.eye(3) if parent is None else np.asarray(parent[b], dtype=float)
        w_prev = np.zeros(3) if parent_omega is None else np.asarray(parent_omega[b], float)
        for i in range(n):
            R = rotation_to(q[b, i])
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, (R_prev.T @ R).reshape(-1))
            w = np.cross(q[b, i], v[b, i])  # angular velocity of link i (no spin)
            qpos[b, 4 * i : 4 * i + 4] = quat
            qvel[b, 3 * i : 3 * i + 3] = R.T @ (w - w_prev)  # ball joint: child frame
            R_prev, w_prev = R, w
    if base is None:
        return qpos, qvel
    return (
        np.concatenate([np.asarray(base, dtype=float), qpos], axis=1),
        np.concatenate([np.asarray(base_v, dtype=float), qvel], axis=1),
    )


def mass_positions(model, qpos):
    """The bodies' centres of mass, `(batch, bodies, 3)`, for a batch of joint positions:
    the point masses (the base first when there is one)."""
    d = mujoco.MjData(model)
    result = []
    for row in np.asarray(qpos, dtype=float):
        d.qpos[:] = row
        mujoco.mj_kinematics(model, d)
        result.append(d.xipos[1:].copy())
    return np.array(result)


class MuJoCo:
    """The model `xml` stepped by `mujoco.rollout` on `nthread` threads; `to_joints(q, v)`
    turns a batch of sphere_mech states into `(qpos, qvel)`."""

    name = "MuJoCo"

    def __init__(self, xml, to_joints, nthread=CORES):
        self.model, self.to_joints = mujoco.MjModel.from_xml_string(xml), to_joints
        self.data = [mujoco.MjData(self.model) for _ in range(nthread)]
        self.spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.size = mujoco.mj_stateSize(self.model, self.spec)

    def prepare(self, q, v):
        d, nq, nv = self.data[0], self.model.nq, self.model.nv
        mujoco.mj_resetData(self.model, d)
        state = np.zeros(self.size)
        mujoco.mj_getState(self.model, d, state, self.spec)
        qpos, qvel = self.to_joints(q, v)
        states = np.tile(state, (len(qpos), 1))
        states[:, 1 : 1 + nq] = qpos  # after the time
        states[:, 1 + nq : 1 + nq + nv] = qvel
        return states

    def run(self, states, nsteps):
        data = self.data[: len(states)]  # no idle threads for tiny batches
        out, _ = rollout.rollout(self.model, data, states, nstep=nsteps)
        return out, nsteps

    def positions(self, out):
        return mass_positions(self.model, out[:, -1, 1 : 1 + self.model.nq])


class MJX:
    """The model `xml` on `mujoco.mjx` (JAX): `mjx.step` (RK4) in a loop under vmap."""

    name = "MJX"

    def __init__(self, xml, to_joints):
        self.model, self.to_joints = mujoco.MjModel.from_xml_string(xml), to_joints
        mx = mjx.put_model(self.model)
        data = mjx.make_data(mx)

        def step(y):
            d = mjx.step(mx, data.replace(qpos=y[0], qvel=y[1]))
            return d.qpos, d.qvel

        self.solve = fixed_step_loop(step)

    def prepare(self, q, v):
        dtype = jnp.zeros(()).dtype  # float32 unless x64 is on
        return tuple(jnp.asarray(x, dtype) for x in self.to_joints(q, v))

    def run(self, y, nsteps):
        out = self.solve(y, nsteps)
        jax.block_until_ready(out)
        return out, nsteps

    def positions(self, out):
        return mass_positions(self.model, out[0])


# --------------------------------------------------------------------------- measuring
def final_positions(methods, y, nsteps):
    """`{name: positions (batch, points, 3)}` of each method after `nsteps` steps from the
    batch of sphere_mech states `y`."""
    return {m.name: m.positions(m.run(m.prepare(*y), nsteps)[0]) for m in methods}


def throughput(method, y, budget, repeats):
    """`(system-steps per second (median of repeats), compile time, seconds per step)`
    of `method` on the batch of states `y`, with about `budget` system-steps a run
    (one repeat when the first call takes over 5 s); a repeat must not compile again."""
    batch = jax.tree.leaves(y)[0].shape[0]
    y = method.prepare(*y)
    nsteps = int(np.clip(budget // batch, 5, 2000))
    t = timing(lambda: method.run(y, nsteps), repeats, slow=5.0, what=method.name)
    steps = t.result[1]
    return batch * steps / t.median, t.compile, t.median / steps
