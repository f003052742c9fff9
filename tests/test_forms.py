"""The four forms of the equations of motion agree on random configuration-dependent,
time-dependent Lagrangians with random forces (hypothesis); terms that vanish on the
tangent bundle change nothing; energy balances the power of the forces in every form.

One family of Lagrangians, with every coefficient passed through `args`, serves all the
tests: each set of systems below compiles once."""

import equinox as eqx
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import form_outputs, max_rel_error
from hypothesis import given, settings

import sphere_mech as sm

SETTINGS = settings(max_examples=8, deadline=None, derandomize=True)
TOL = 1e-12
SEEDS = st.integers(0, 2**31 - 1)
TIMES = st.floats(-2.0, 2.0)


# ----------------------------------------------------------------------------------------
# The random Lagrangian, with v = qdot and x = q flattened to 3n:
#   L = 1/2 v . A(t, q) v + (1 + c0 t) g(q) . v - (1 + c1 sin t) U(q)
#       + k4 quartic(v) - kr sum_i (sqrt(1 - |v_i|^2) - 1) + ka (terms vanishing on TS^2)
#   A(t, q) = A0 + W(q) W(q)^T + (1 + c2 t^2) I   (positive definite)
# Forces f(t, q, v) = D v + E x + e sin t.
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


def lagrangian(t, q, qdot, p):
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


def forces(t, q, qdot, p):
    x, v = q.reshape(-1), qdot.reshape(-1)
    return (p["D"] @ v + p["E"] @ x + p["e"] * jnp.sin(t)).reshape(q.shape)


LAG = sm.Lagrangian(lagrangian, forces=forces, quadratic_in_velocity=True)
LINEAR = dict(  # Legendre transform by one linear solve: valid for quadratic L only
    lag=LAG,
    ang=sm.angular(LAG),
    ham=sm.legendre(LAG),
    ang_ham=sm.legendre(sm.angular(LAG)),
    ham_ang=sm.angular(sm.legendre(LAG)),
)
NEWTON = dict(  # Legendre transform by Newton's method: any L
    lag=LAG,
    ang=sm.angular(LAG),
    ham=sm.legendre(LAG, quadratic=False),
    ang_ham=sm.legendre(sm.angular(LAG), quadratic=False),
)
SECOND = dict(lag="qddot", ang="omegadot", ham="mudot", ang_ham="pidot", ham_ang="pidot")


@eqx.filter_jit
def evaluate(systems, t, q, qdot, p):
    """Everything the tests compare, for each form at the same physical state:
    `rates` (qdot, dv/dt), `energy`, `dE/dt` along the rates (jvp), `power`; and the
    references computed from form 1."""
    lag = systems["lag"]
    qddot = lag.acceleration(t, q, qdot, p)
    mu = lag.momentum(t, q, qdot, p)
    _, mudot = jax.jvp(
        lambda t_, q_, v_: lag.momentum(t_, q_, v_, p),
        (t, q, qdot),
        (jnp.ones_like(t), qdot, qddot),
    )
    pi = sm.pi_from_mu(q, mu)
    ref = dict(
        qdot=qdot,
        qddot=qddot,
        omegadot=jnp.cross(q, qddot),
        mudot=mudot,
        pidot=jnp.cross(qdot, mu) + jnp.cross(q, mudot),
        pi=pi,
        dL_dt=jax.grad(lambda t_: lag.lagrangian(t_, q, qdot, p))(t),
    )
    variables = dict(lag=qdot, ang=sm.omega_from_qdot(q, qdot), ham=mu, ang_ham=pi, ham_ang=pi)
    out = form_outputs(systems, variables, t, q, qdot, qddot, p)
    out["lag"]["power_method"] = lag.power(t, q, qdot, p)
    out["ang"]["momentum"] = systems["ang"].momentum(t, q, variables["ang"], p)
    return ref, out


def state(seed, n, speed=1.0):
    return sm.random_state(jax.random.PRNGKey(seed % 2**32), n, speed=speed)


def assert_forms_agree(systems, t, q, qdot, p, tol=TOL):
    ref, out = evaluate(systems, as_time(t), q, qdot, p)
    assert np.all(np.isfinite(ref["qddot"]))
    energy = out["lag"]["energy"]
    for name, o in out.items():
        qdot_k, vdot_k = o["rates"]
        assert max_rel_error(qdot_k, qdot) < tol, name
        assert max_rel_error(vdot_k, ref[SECOND[name]]) < tol, name
        assert abs(float(o["energy"] - energy)) < tol * (1 + abs(float(energy))), name
    assert max_rel_error(out["ang"]["momentum"], ref["pi"]) < tol
    return ref, out


N_LINEAR, N_NEWTON = 2, 3  # spheres: one compilation per set of systems and n


def as_time(t):
    return jnp.asarray(t, dtype=jnp.float64)  # one dtype and weak type: no recompilation


@SETTINGS
@given(seed=SEEDS, t=TIMES, augment=st.booleans())
def test_four_forms_agree_quadratic(seed, t, augment):
    q, qdot = state(seed, N_LINEAR)
    assert_forms_agree(LINEAR, t, q, qdot, random_params(seed, N_LINEAR, augment=augment))


@SETTINGS
@given(seed=SEEDS, t=TIMES, kind=st.sampled_from(["quadratic", "quartic", "relativistic"]))
def test_four_forms_agree_newton(seed, t, kind):
    """Newton's Legendre map, on quadratic and on genuinely non-quadratic Lagrangians."""
    speed = 0.3 if kind == "relativistic" else 1.0  # keeps |qdot_i| < c
    q, qdot = state(seed, N_NEWTON, speed=speed)
    p = random_params(
        seed, N_NEWTON, quartic=kind == "quartic", relativistic=kind == "relativistic"
    )
    assert_forms_agree(NEWTON, t, q, qdot, p)


def test_linear_legendre_is_wrong_for_non_quadratic_L():
    """The linear-solve Legendre map is exact only for quadratic L: on the quartic L it
    differs, so the Newton comparison is not vacuous."""
    q, qdot = state(1, N_LINEAR, speed=1.5)
    p = random_params(1, N_LINEAR, quartic=1.0)
    ref, out = evaluate(LINEAR, as_time(0.3), q, qdot, p)
    assert max_rel_error(out["ham"]["rates"][0], qdot) > 1e-3


@SETTINGS
@given(seed=SEEDS, t=TIMES)
def test_terms_vanishing_on_tangent_bundle_change_nothing(seed, t):
    q, qdot = state(seed, N_NEWTON)
    t = as_time(t)
    p, p_aug = (random_params(seed, N_NEWTON, quartic=1.0, augment=a) for a in (0.0, 1.0))
    # the added terms do change L's derivatives (off the tangent directions)
    dL, dL_aug = (jax.grad(lagrangian, argnums=2)(t, q, qdot, p_) for p_ in (p, p_aug))
    assert max_rel_error(dL_aug, dL) > 1e-3
    plain, augmented = (evaluate(NEWTON, t, q, qdot, p_) for p_ in (p, p_aug))
    leaves = jax.tree.leaves(plain)
    for a, b in zip(jax.tree.leaves(augmented), leaves, strict=True):
        assert max_rel_error(a, b) < TOL


@SETTINGS
@given(seed=SEEDS, t=TIMES)
def test_energy_balance_forced_time_dependent(seed, t):
    """dE/dt = sum_i f_i . qdot_i - dL/dt along the vector field of every form."""
    q, qdot = state(seed, N_LINEAR)
    ref, out = evaluate(LINEAR, as_time(t), q, qdot, random_params(seed, N_LINEAR))
    dL_dt = float(ref["dL_dt"])
    assert abs(dL_dt) > 1e-3
    assert abs(float(out["lag"]["power_method"] - out["lag"]["power"])) < 1e-13
    for name, o in out.items():
        power = float(o["power"])
        assert abs(power) > 1e-3
        assert abs(float(o["dE"]) - (power - dL_dt)) < TOL * (1 + abs(power) + abs(dL_dt)), name


@pytest.mark.parametrize("kind", ["quadratic", "quartic"])
def test_energy_conserved_unforced_time_independent(kind):
    q, qdot = state(7, N_NEWTON)
    p = random_params(7, N_NEWTON, quartic=kind == "quartic", time=False, forced=False)
    ref, out = evaluate(NEWTON, as_time(0.7), q, qdot, p)
    assert float(ref["dL_dt"]) == 0.0
    for name, o in out.items():
        assert float(o["power"]) == 0.0
        assert abs(float(o["dE"])) < TOL * (1 + abs(float(o["energy"]))), name
