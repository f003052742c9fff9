"""Shared test helpers: comparisons, the solvers the suite runs its common checks over,
the models and data several test modules use, and the cross-check of the four forms.
Test modules import from here, never from each other."""

import os

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax.flatten_util import ravel_pytree
from scipy.integrate import solve_ivp

import sphere_mech as sm

# ----------------------------------------------------------------------------------------
# Comparisons.
# ----------------------------------------------------------------------------------------


def tree_allclose(x, y, *, rtol=1e-5, atol=1e-8):
    """Whether two PyTrees have the same structure and allclose leaves."""
    if jtu.tree_structure(x) != jtu.tree_structure(y):
        return False
    return all(
        jnp.shape(a) == jnp.shape(b) and bool(jnp.allclose(a, b, rtol=rtol, atol=atol))
        for a, b in zip(jtu.tree_leaves(x), jtu.tree_leaves(y), strict=True)
    )


def max_rel_error(x, y):
    """`max |x - y| / max |y|` (relative error in the max norm); a dict (a state on a
    mixed space) counts as all its leaves, flattened."""
    x, y = (np.asarray(ravel_pytree(a)[0] if isinstance(a, dict) else a) for a in (x, y))
    return float(np.max(np.abs(x - y)) / max(np.max(np.abs(y)), 1e-300))


def fitted_order(step_sizes, errors):
    """Slope of log(error) against log(step size): the measured order of convergence."""
    return float(np.polyfit(np.log(step_sizes), np.log(errors), 1)[0])


def central_differences(f, x, h=1e-5):
    """Central differences of `f` at the 1-D array `x`, step `h` along each coordinate:
    the derivative along coordinate i in `[..., i]` (the last axis; `(x.size,)` for a
    scalar `f`)."""
    return jnp.stack([(f(x + e) - f(x - e)) / (2 * h) for e in h * jnp.eye(x.size)], -1)


def jaxpr_equations(jaxpr):
    """All equations of a jaxpr, including those of nested jaxprs (pjit, custom_jvp...)."""
    for eqn in jaxpr.eqns:
        yield eqn
        for param in eqn.params.values():
            for sub in param if isinstance(param, list | tuple) else [param]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    yield from jaxpr_equations(inner)


# ----------------------------------------------------------------------------------------
# The solvers: one of each family (projected Runge-Kutta, Lie-group Runge-Kutta,
# variational), with fixed steps. A check that holds for every solver runs over these.
# ----------------------------------------------------------------------------------------

SOLVERS = (sm.Projected(sm.RK4()), sm.LieRK4(), sm.Variational())
SOLVER_IDS = ("Projected(RK4)", "LieRK4", "Variational")


def fixed_steps(system, solver, dt, y0, *, t0=0.0, t1=1.0, args=None, **options):
    """`sm.simulate` with fixed steps of `dt` from `t0` to `t1` (a negative `dt` steps
    back). The times are arrays, so every step size, direction and interval shares one
    compilation. `options` go to `sm.simulate` (`saveat`, `throw`, `max_steps`...)."""
    return sm.simulate(
        system,
        y0,
        jnp.asarray(t1),
        t0=jnp.asarray(t0),
        args=args,
        solver=solver,
        dt0=jnp.asarray(dt),
        **options,
    )


def steps_taken(sol):
    """`(ts, ys)` over the steps taken, of a run saved with `diffrax.SaveAt(steps=True)`
    (the rest of its arrays is padding)."""
    k = int(sol.stats["num_steps"])
    return sol.ts[:k], jax.tree_util.tree_map(lambda x: x[:k], sol.ys)


def last(tree):
    """The last entry along the leading (time) axis of each leaf: the final state."""
    return jax.tree_util.tree_map(lambda x: x[-1], tree)


def exact_observations(system, y0, ts, observe):
    """`observe(system, t, q, v)` at times `ts` `(T,)` of a run from `y0` at `ts[0] = 0`
    integrated to rounding (`Projected(Dopri8)` at 1e-12): the data fits are given."""
    sol = sm.simulate(
        system,
        y0,
        float(ts[-1]),
        solver=sm.Projected(diffrax.Dopri8()),
        rtol=1e-12,
        atol=1e-12,
        saveat=diffrax.SaveAt(ts=jnp.asarray(ts)),
    )
    return jax.jit(jax.vmap(lambda t, q, v: observe(system, t, q, v)))(sol.ts, *sol.ys)


# ----------------------------------------------------------------------------------------
# The four forms (Lagrangian, angular, Hamiltonian, angular Hamiltonian) on a random
# configuration-dependent, time-dependent Lagrangian with random forces, with v = qdot and
# x = q flattened to 3n:
#   L = 1/2 v . A(t, q) v + (1 + c0 t) g(q) . v - (1 + c1 sin t) U(q)
#       + k4 quartic(v) - kr sum_i (sqrt(1 - |v_i|^2) - 1) + ka (terms vanishing on TS^2)
#   A(t, q) = A0 + W(q) W(q)^T + (1 + c2 t^2) I   (positive definite)
# Forces f(t, q, v) = D v + E x + e sin t. Every coefficient is passed through `args`.
# ----------------------------------------------------------------------------------------


def random_params(
    seed, n, *, quartic=0.0, relativistic=0.0, augment=0.0, time=True, forced=True
) -> dict:
    rng = np.random.default_rng(seed)
    m = 3 * n
    R = rng.normal(size=(m, m)) / np.sqrt(m)
    p = dict(
        A0=R @ R.T,
        B=rng.normal(size=(m, m, 2)) / np.sqrt(m),  # W(q)[a, k] = sum_b B[a, b, k] x_b
        G=rng.normal(size=(m, m)),
        G2=rng.normal(size=(m,)),
        S=rng.normal(size=(m, m)),
        s=rng.normal(size=(m,)),
        D=rng.normal(size=(m, m)),
        E=rng.normal(size=(m, m)),
        e=rng.normal(size=(m,)),
        time=rng.uniform(0.1, 0.5, size=(3,)),
        phi=rng.normal(size=(n, m)),
        psi=rng.normal(size=(n, m)),
    )
    p["coef"] = np.array([quartic, relativistic, augment], dtype=float)
    p["coef"] *= rng.uniform(0.5, 1.0, size=3)
    if not time:
        p["time"] = np.zeros(3)
    if not forced:
        p["D"], p["E"], p["e"] = np.zeros((m, m)), np.zeros((m, m)), np.zeros(m)
    return p


def vanishing_terms(q, qdot, p):
    """`sum_i phi_i(q, qdot) (q_i . qdot_i) + psi_i(q, qdot) (|q_i|^2 - 1)`."""
    x, v = q.reshape(-1), qdot.reshape(-1)
    phi = jnp.tanh(p["phi"] @ (x + v)) + jnp.sum(v**2)
    psi = jnp.cos(p["psi"] @ x) * (1.0 + jnp.sum(v**2))
    return jnp.sum(phi * jnp.sum(q * qdot, axis=-1)) + jnp.sum(psi * (jnp.sum(q * q, -1) - 1.0))


def random_lagrangian(t, q, qdot, p):
    x, v = q.reshape(-1), qdot.reshape(-1)
    W = jnp.einsum("abk,b->ak", p["B"], x)
    A = p["A0"] + W @ W.T + (1.0 + p["time"][2] * t**2) * jnp.eye(x.shape[0], dtype=x.dtype)
    gyro = (1.0 + p["time"][0] * t) * (p["G"] @ x + p["G2"] * jnp.sin(x)) @ v
    potential = 0.5 * x @ p["S"] @ x + p["s"] @ jnp.cos(x)
    v2 = jnp.sum(qdot**2, axis=-1)
    quartic = 0.25 * jnp.sum(v2**2 + v2 * v2[::-1])
    k4, kr, ka = p["coef"]
    # c^2 sum_i (1 - sqrt(1 - |v_i|^2 / c^2)) with 1 / c^2 = kr, and 0 when kr = 0
    relativistic = jnp.sum(1.0 - jnp.sqrt(1.0 - kr * v2)) / jnp.where(kr > 0, kr, 1.0)
    return (
        0.5 * v @ A @ v
        + gyro
        - (1.0 + p["time"][1] * jnp.sin(t)) * potential
        + k4 * quartic
        + relativistic
        + ka * vanishing_terms(q, qdot, p)
    )


def random_forces(t, q, qdot, p):
    x, v = q.reshape(-1), qdot.reshape(-1)
    return (p["D"] @ v + p["E"] @ x + p["e"] * jnp.sin(t)).reshape(q.shape)


# The reference each form's second rate is compared with (forms keyed as in `evaluate_forms`).
SECOND = dict(
    lag="qddot", ang="omegadot", ham="mudot", ang_ham="pidot", ham_ang="pidot", ham_newton="mudot"
)


def form_outputs(systems, variables, t, q, qdot, qddot, p):
    """For each form in `systems` (keys as in `variables`, the state variable of each at
    the same physical state): its rates (qdot, dv/dt) through the checked public entry
    points, its energy, dE/dt along the rates (jvp) and the power of its own forces.
    Plain `(n, 3)` arrays or dicts of them (mixed spaces)."""
    out = {}
    for name, system in systems.items():
        v = variables[name]
        if name == "lag":
            rates = (qdot, qddot)
        elif name == "ang":
            rates = (system.to_linear(q, v), system.angular_acceleration(t, q, v, p))
        else:
            rates = system.vector_field(t, q, v, p)
        energy_fn = lambda t_, q_, v_, system=system: system.energy(t_, q_, v_, p)
        energy, dE = jax.jvp(energy_fn, (t, q, v), (jnp.ones_like(t), *rates))
        f = system.generalized_force(t, q, v, p)
        power = sum(
            jnp.sum(a * b)
            for a, b in zip(jtu.tree_leaves(f), jtu.tree_leaves(rates[0]), strict=True)
        )
        out[name] = dict(rates=rates, energy=energy, dE=dE, power=power)
    return out


def evaluate_forms(systems, t, q, qdot, p, angular=jnp.cross):
    """`_evaluate_forms` with every argument passed positionally: `filter_jit` keys its
    cache on how the arguments were passed, and a default left out compiled the same
    program again (12 to 28 s)."""
    return _evaluate_forms(systems, t, q, qdot, p, angular)


@eqx.filter_jit
def _evaluate_forms(systems, t, q, qdot, p, angular):
    """Everything the cross-check compares, for each form in `systems` (keys `lag`,
    `ang`, and any of `ham`, `ang_ham`, `ham_ang`, `ham_newton`) at the same physical
    state: `rates` (qdot, dv/dt), `energy`, `dE/dt` along the rates (jvp), `power`; and
    the references computed from the Lagrangian form. `angular(q, v)` maps velocities
    and momenta to their angular forms (`q_i x v_i` on the spheres)."""
    lag = systems["lag"]
    qddot = lag.acceleration(t, q, qdot, p)
    mu = lag.momentum(t, q, qdot, p)
    _, mudot = jax.jvp(
        lambda t_, q_, v_: lag.momentum(t_, q_, v_, p),
        (t, q, qdot),
        (jnp.ones_like(t), qdot, qddot),
    )
    pi, pidot = jax.jvp(angular, (q, mu), (qdot, mudot))
    ref = dict(
        qdot=qdot,
        qddot=qddot,
        omegadot=angular(q, qddot),
        mudot=mudot,
        pidot=pidot,
        pi=pi,
        dL_dt=jax.grad(lambda t_: lag.lagrangian(t_, q, qdot, p))(t),
    )
    omega = angular(q, qdot)
    variables = dict(lag=qdot, ang=omega, ham=mu, ang_ham=pi, ham_ang=pi, ham_newton=mu)
    out = form_outputs(systems, variables, t, q, qdot, qddot, p)
    out["lag"]["power_method"] = lag.power(t, q, qdot, p)
    out["ang"]["momentum"] = systems["ang"].momentum(t, q, omega, p)
    return ref, out


def assert_forms_agree(systems, t, q, qdot, p, tol, angular=jnp.cross):
    """The form cross-check: every form has the same velocity, the same second rate (as
    the Lagrangian form's, mapped) and the same energy to `tol`, and the angular form's
    momentum is `pi`. Returns `evaluate_forms`' references and outputs."""
    ref, out = evaluate_forms(systems, t, q, qdot, p, angular)
    assert all(np.all(np.isfinite(x)) for x in jtu.tree_leaves(ref["qddot"]))
    energy = out["lag"]["energy"]
    for name, o in out.items():
        qdot_k, vdot_k = o["rates"]
        assert max_rel_error(qdot_k, qdot) < tol, name
        assert max_rel_error(vdot_k, ref[SECOND[name]]) < tol, name
        assert abs(float(o["energy"] - energy)) < tol * (1 + abs(float(energy))), name
    assert max_rel_error(out["ang"]["momentum"], ref["pi"]) < tol
    return ref, out


def assert_energy_balance(ref, out, tol):
    """dE/dt = power - dL/dt along the vector field of every form."""
    dL_dt = float(ref["dL_dt"])
    for name, o in out.items():
        power = float(o["power"])
        assert abs(float(o["dE"]) - (power - dL_dt)) < tol * (1 + abs(power) + abs(dL_dt)), name


# ----------------------------------------------------------------------------------------
# Mixed spaces R^m x (S^2)^n: a base of mass M at E x (E: 3 x m, orthonormal columns),
# links of lengths l_i with point masses m_i at r_i = E x + sum_{j <= i} l_j q_j, gravity
# -g e3 on every mass, and an optional force F(t) on the base (virtual work F . delta x).
# The independent reference: Cartesian coordinates with the link lengths imposed by
# Lagrange multipliers (the index-1 DAE reduced to an ODE by solving for the
# multipliers), integrated by scipy's DOP853 at tight tolerances.
# ----------------------------------------------------------------------------------------

G = 9.81
T1 = 2.0
TS = np.linspace(0.0, T1, 11)
TIGHT = dict(
    solver=sm.Projected(diffrax.Dopri8()),
    rtol=1e-12,
    atol=1e-12,
    saveat=diffrax.SaveAt(ts=jnp.asarray(TS)),
)


class MixedModel:
    """A base of mass `M` moving along the columns of `E` carrying a chain (`masses`,
    `lengths`), pushed by `drive(t)`: its `sphere_mech` system and its Cartesian
    reference."""

    def __init__(self, M, masses, lengths, E, drive):
        self.M, self.masses, self.lengths = M, np.asarray(masses), np.asarray(lengths)
        self.E, self.drive = np.asarray(E, dtype=float), drive
        self.m, self.n = self.E.shape[1], len(masses)
        self.space = {"base": sm.Euclidean(self.m), "chain": sm.Spheres(self.n)}

    # --- sphere_mech: L on R^m x (S^2)^n ---------------------------------------------

    def positions(self, q):
        E, lengths = jnp.asarray(self.E), jnp.asarray(self.lengths)
        return E @ q["base"] + jnp.cumsum(lengths[:, None] * q["chain"], axis=0)

    def lagrangian(self, t, q, qdot, args):
        E, masses, e3 = jnp.asarray(self.E), jnp.asarray(self.masses), jnp.array([0, 0, 1.0])
        vb = E @ qdot["base"]
        kinetic = 0.5 * self.M * vb @ vb
        kinetic += 0.5 * jnp.sum(masses * jnp.sum(self.positions(qdot) ** 2, axis=-1))
        potential = self.M * G * (E @ q["base"]) @ e3 + G * masses @ (self.positions(q) @ e3)
        return kinetic - potential

    def forces(self, t, q, qdot, args):
        return {"base": self.drive(t), "chain": jnp.zeros_like(q["chain"])}

    def system(self, forced):
        return sm.Lagrangian(
            self.lagrangian, forces=self.forces if forced else None, space=self.space
        )

    # --- reference: Cartesian coordinates X = (x, r_1, ..., r_n) with multipliers ------

    def reference(self, q0, v0, forced, ts=TS):
        m, n, E = self.m, self.n, self.E
        inv_mass = np.concatenate([np.full(m, 1 / self.M), np.repeat(1 / self.masses, 3)])

        def rhs(t, y):
            X, V = y[: m + 3 * n], y[m + 3 * n :]
            r = X[m:].reshape(n, 3)
            rv = V[m:].reshape(n, 3)
            prev = np.vstack([E @ X[:m], r[:-1]])
            prev_v = np.vstack([E @ V[:m], rv[:-1]])
            d, dv = r - prev, rv - prev_v
            J = np.zeros((n, m + 3 * n))  # rows: gradients of |r_i - r_{i-1}|^2 / 2
            for i in range(n):
                J[i, m + 3 * i : m + 3 * i + 3] = d[i]
                if i == 0:
                    J[i, :m] = -E.T @ d[i]
                else:
                    J[i, m + 3 * i - 3 : m + 3 * i] = -d[i]
            F = np.zeros(m + 3 * n)
            F[:m] = -self.M * G * E.T @ np.array([0, 0, 1.0])
            if forced:
                F[:m] += np.asarray(self.drive(t))
            F[m:] = (-G * self.masses[:, None] * np.array([0, 0, 1.0])).reshape(-1)
            # d^2/dt^2 of the constraints = J A + |dv_i|^2 = 0, A = inv_mass (F - J^T lam)
            JM = J * inv_mass
            lam = np.linalg.solve(JM @ J.T, JM @ F + np.sum(dv**2, axis=1))
            return np.concatenate([V, inv_mass * (F - J.T @ lam)])

        x0, xd0 = np.asarray(q0["base"]), np.asarray(v0["base"])
        r0 = E @ x0 + np.cumsum(self.lengths[:, None] * np.asarray(q0["chain"]), axis=0)
        rd0 = E @ xd0 + np.cumsum(self.lengths[:, None] * np.asarray(v0["chain"]), axis=0)
        y0 = np.concatenate([x0, r0.reshape(-1), xd0, rd0.reshape(-1)])
        sol = solve_ivp(
            rhs, (ts[0], ts[-1]), y0, method="DOP853", t_eval=ts, rtol=1e-13, atol=1e-13
        )
        assert sol.success
        X = sol.y[: m + 3 * n].T
        return X[:, :m], X[:, m:].reshape(len(ts), n, 3)


def cart_pendulum():
    """A spherical pendulum on a cart on the x axis, driven by F(t) = 2 sin(3 t)."""
    drive = lambda t: 2.0 * jnp.sin(3.0 * t) * jnp.ones(1)
    return MixedModel(1.5, [0.7], [0.8], [[1.0], [0.0], [0.0]], drive)


def flying_chain():
    """A point mass in 3-D carrying a 2-link chain, pushed by a constant force."""
    drive = lambda t: jnp.array([0.4, -0.2, 1.5 * 1.0 * G])
    return MixedModel(1.0, [0.3, 0.2], [0.6, 0.4], np.eye(3), drive)


def mixed_initial_state(model, seed=0):
    """A random state of a `MixedModel`: the chain's by `sm.random_state`, the base's
    normal."""
    q_s, v_s = sm.random_state(jax.random.PRNGKey(seed), model.n, speed=1.5)
    rng = np.random.default_rng(seed)
    q0 = {"base": jnp.asarray(rng.normal(size=model.m)), "chain": q_s}
    v0 = {"base": jnp.asarray(rng.normal(size=model.m)), "chain": v_s}
    return q0, v0


def on_chain(fn, a, b):
    """`fn` on the chain factor, `b` unchanged on the base."""
    return {"base": b["base"], "chain": fn(a["chain"], b["chain"])}


def mixed_angular(q, v):
    """The angular variables on R^m x (S^2)^n: `q_i x v_i` on the chain, `v` on the base."""
    return on_chain(jnp.cross, q, v)


# ----------------------------------------------------------------------------------------
# A damped double spherical pendulum, for fitting.
# ----------------------------------------------------------------------------------------

SIM = dict(rtol=1e-7, atol=1e-9)  # simulate's tolerances while fitting


class DampedChain(sm.AbstractConstantInertiaLagrangian):
    """A chain pendulum with viscous joint damping, from the Rayleigh function
    `R = c/2 sum_i |omega_i - omega_{i-1}|^2` (`omega_0 = 0`): `f = -dR/dqdot`."""

    chain: sm.AbstractSystem  # sm.chain_pendulum(...)
    damping: jax.Array

    def inertia(self, args=None):
        return self.chain.inertia(args)

    def potential(self, t, q, args=None):
        return self.chain.potential(t, q, args)

    @property
    def forces(self):
        return self.damping_force

    def damping_force(self, t, q, qdot, args):
        def rayleigh(qdot_):
            w = jnp.cross(q, qdot_)
            rel = w - jnp.concatenate([jnp.zeros_like(w[:1]), w[:-1]])
            return 0.5 * self.damping * jnp.sum(rel**2)

        return -jax.grad(rayleigh)(qdot)


def chain_initial_states(num):
    """`num` states of a double pendulum, one state rotated by growing angles: leaves of
    leading axis `num`."""
    q = sm.normalize(jnp.array([[1.0, 0.2, -1.0], [0.6, -0.4, -1.0]]))
    v = sm.project(q, jnp.array([[0.0, 1.0, 0.0], [0.5, 0.0, 0.3]]))
    w = jnp.linspace(0.0, 1.0, num)[:, None, None] * jnp.array([0.0, 0.3, 0.2])
    return jax.vmap(
        lambda w_: (
            sm.rotate(jnp.broadcast_to(w_, (2, 3)), q),
            sm.rotate(jnp.broadcast_to(w_, (2, 3)), v),
        )
    )(w)


# ----------------------------------------------------------------------------------------
# Scene files.
# ----------------------------------------------------------------------------------------

# A cart on the x axis carrying a one-link pendulum; `{extra}` (more effects) and
# `{simulate}` (more simulate options) to be filled by `str.format`.
CART_SCENE = """
[[effects]]
type = "base"
mass = 1.0
axes = [[1.0, 0.0, 0.0]]
[[effects]]
type = "chain"
masses = 0.5
lengths = 0.8
{extra}
[initial]
polar_deg = 140.0
azimuth_deg = 90.0
base = [0.0]
[simulate]
t1 = 1.0
{simulate}
"""


def cpu_devices(count: int) -> dict:
    """The environment of a subprocess with `count` CPU devices that compiles as the suite's
    other processes do (../conftest.py's `XLA_FLAGS` kept, the device count added)."""
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={count}"
    return dict(JAX_PLATFORMS="cpu", XLA_FLAGS=flags.strip())
