"""Independent references: textbook angle equations (planar double pendulum, spherical
pendulum), small-oscillation frequencies of the chain from the classical generalized
eigenproblem, statics under a tip force and a base torque, and the chain's fast path
against the general autodiff path."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import max_rel_error

import sphere_mech as sm

G = 9.81


def cartesian_chain_lagrangian(masses, lengths, g):
    """The chain's L written directly from the mass positions (not from sm's chain)."""

    def L(t, q, qdot, args):
        x = jnp.cumsum(lengths[:, None] * q, axis=0)
        v = jnp.cumsum(lengths[:, None] * qdot, axis=0)
        return 0.5 * jnp.sum(masses * jnp.sum(v * v, axis=-1)) - g * jnp.sum(masses * x[:, 2])

    return L


# ----------------------------------------------------------------------------------------
# Planar double pendulum: q_i = (sin th_i, 0, -cos th_i).
# ----------------------------------------------------------------------------------------


def double_pendulum_angles(th, dth, m1, m2, l1, l2, g, xp=np):
    """Textbook: theta'' of the planar double pendulum (point masses, massless rods);
    `xp` is numpy or jax.numpy."""
    d = th[0] - th[1]
    A = xp.array([[(m1 + m2) * l1, m2 * l2 * xp.cos(d)], [l1 * xp.cos(d), l2]])
    b = -xp.array(
        [
            m2 * l2 * dth[1] ** 2 * xp.sin(d) + (m1 + m2) * g * xp.sin(th[0]),
            -l1 * dth[0] ** 2 * xp.sin(d) + g * xp.sin(th[1]),
        ]
    )
    return xp.linalg.solve(A, b)


def planar(th, dth, ddth=None):
    """q, qdot (and qddot) of links at angles th from the downward vertical, x-z plane."""
    s, c, z = np.sin(th), np.cos(th), np.zeros_like(th)
    q = np.stack([s, z, -c], axis=-1)
    qdot = dth[:, None] * np.stack([c, z, s], axis=-1)
    if ddth is None:
        return q, qdot
    qddot = ddth[:, None] * np.stack([c, z, s], axis=-1) + (dth**2)[:, None] * q * -1.0
    return q, qdot, qddot


@eqx.filter_jit
def accelerations(system, q, qdot):
    return system.acceleration(0.0, q, qdot, None)


def test_planar_double_pendulum_matches_textbook():
    m, ell = np.array([1.3, 0.7]), np.array([0.9, 1.4])
    chain = sm.chain_pendulum(m, ell, G)
    general = sm.Lagrangian(cartesian_chain_lagrangian(jnp.asarray(m), jnp.asarray(ell), G))
    rng = np.random.default_rng(0)
    for _ in range(5):
        th, dth = rng.uniform(-3, 3, 2), rng.normal(size=2) * 2
        ddth = double_pendulum_angles(th, dth, *m, *ell, G)
        q, qdot, qddot = planar(th, dth, ddth)
        for system in (chain, general):
            got = accelerations(system, jnp.asarray(q), jnp.asarray(qdot))
            assert max_rel_error(got, qddot) < 1e-12


def test_planar_double_pendulum_trajectory():
    """A simulated planar motion stays in its plane and follows the angle equations."""
    m, ell = np.array([1.0, 2.0]), np.array([1.0, 0.5])
    th0, dth0 = np.array([2.0, -1.0]), np.array([0.0, 1.5])
    t1 = 3.0
    ts = jnp.linspace(0.0, t1, 7)
    chain = sm.chain_pendulum(m, ell, G)
    sol = sm.simulate(
        chain, planar(th0, dth0), t1, rtol=1e-11, atol=1e-12, saveat=diffrax.SaveAt(ts=ts)
    )

    def angle_rates(t, y, args):
        th, dth = y
        ddth = jnp.asarray(double_pendulum_angles(th, dth, *m, *ell, G, xp=jnp))
        return dth, ddth

    ref = diffrax.diffeqsolve(
        diffrax.ODETerm(angle_rates),
        diffrax.Tsit5(),
        0.0,
        t1,
        1e-3,
        (jnp.asarray(th0), jnp.asarray(dth0)),
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=diffrax.PIDController(rtol=1e-11, atol=1e-12),
        max_steps=100_000,
    )
    q_ref = jax.vmap(lambda th: jnp.stack([jnp.sin(th), 0 * th, -jnp.cos(th)], -1))(ref.ys[0])
    q = sol.ys[0]
    assert float(jnp.max(jnp.abs(q[..., 1]))) < 1e-14  # stays in the x-z plane
    assert float(jnp.max(jnp.abs(q - q_ref))) < 1e-7


# ----------------------------------------------------------------------------------------
# Spherical pendulum: q = (sin th cos ph, sin th sin ph, -cos th), with a tip force.
# ----------------------------------------------------------------------------------------


def spherical_q(angles):
    th, ph = angles
    return jnp.array([[jnp.sin(th) * jnp.cos(ph), jnp.sin(th) * jnp.sin(ph), -jnp.cos(th)]])


def spherical_pendulum_angles(angles, rates, m, ell, g, d):
    """Textbook equations in spherical angles, with the generalized forces of a tip force
    `d` computed from `Q_k = d . dx/dangle_k` (x = ell q)."""
    th, ph = angles
    dth, dph = rates
    J = jax.jacfwd(lambda a: ell * spherical_q(a)[0])(angles)  # (3, 2)
    Q = d @ J
    ddth = jnp.sin(th) * jnp.cos(th) * dph**2 - g / ell * jnp.sin(th) + Q[0] / (m * ell**2)
    ddph = (-2.0 * jnp.cos(th) * dth * dph + Q[1] / (m * ell**2 * jnp.sin(th))) / jnp.sin(th)
    return jnp.array([ddth, ddph])


def test_spherical_pendulum_matches_angle_equations():
    m, ell = 1.7, 0.8
    d = jnp.array([0.4, -1.1, 0.6])
    chain = sm.chain_pendulum(jnp.array([m]), jnp.array([ell]), G, tip_force=d)
    L = cartesian_chain_lagrangian(jnp.array([m]), jnp.array([ell]), G)
    general = sm.Lagrangian(L, forces=lambda t, q, qdot, args: ell * d[None, :])
    rng = np.random.default_rng(1)
    for _ in range(5):
        angles = jnp.array([rng.uniform(0.3, np.pi - 0.3), rng.uniform(-np.pi, np.pi)])
        rates = jnp.asarray(rng.normal(size=2))
        acc = spherical_pendulum_angles(angles, rates, m, ell, G, d)
        q, qdot = jax.jvp(spherical_q, (angles,), (rates,))
        # qddot = J ddangles + (d/ds)^2 q along the rates
        velocity = lambda a, r=rates: jax.jvp(spherical_q, (a,), (r,))[1]
        second = jax.jvp(velocity, (angles,), (rates,))[1]
        qddot = jax.jvp(spherical_q, (angles,), (acc,))[1] + second
        for system in (chain, general):
            assert max_rel_error(accelerations(system, q, qdot), qddot) < 1e-12


# ----------------------------------------------------------------------------------------
# Small oscillations about the hanging equilibrium.
# ----------------------------------------------------------------------------------------


@eqx.filter_jit
def linearized_accelerations(chain):
    """d(horizontal accelerations)/d(horizontal displacements) at the hanging state."""
    n = chain.n

    def acc(a):
        a = a.reshape(n, 2)
        q = sm.normalize(jnp.concatenate([a, -jnp.ones((n, 1))], axis=-1))
        return chain.acceleration(0.0, q, jnp.zeros_like(q))[:, :2].reshape(-1)

    return jax.jacfwd(acc)(jnp.zeros(2 * n))


@pytest.mark.parametrize("n", [2, 5])
def test_small_oscillation_frequencies(n):
    rng = np.random.default_rng(n)
    m, ell = rng.uniform(0.5, 2.0, n), rng.uniform(0.5, 2.0, n)
    tail = np.cumsum(m[::-1])[::-1]  # sum_{k >= i} m_k
    idx = np.arange(n)
    M = np.outer(ell, ell) * tail[np.maximum(idx[:, None], idx[None, :])]
    K = np.diag(G * ell * tail)
    C = np.linalg.inv(np.linalg.cholesky(M))  # K v = w^2 M v  <=>  (C K C^T) u = w^2 u
    w2 = np.linalg.eigvalsh(C @ K @ C.T)
    J = np.asarray(linearized_accelerations(sm.chain_pendulum(m, ell, G)))
    got = np.sort(np.linalg.eigvals(-J).real)
    np.testing.assert_allclose(got, np.sort(np.repeat(w2, 2)), rtol=1e-10)


# ----------------------------------------------------------------------------------------
# Statics: equilibria found by Newton's method on the accelerations (zero velocity),
# against the closed form.
# ----------------------------------------------------------------------------------------


@eqx.filter_jit
def equilibrium(system):
    """The equilibrium reached by Newton from the hanging state (links along -e3)."""
    n = system.n
    q0 = jnp.tile(jnp.array([0.0, 0.0, -1.0]), (n, 1))
    T0 = sm.tangent_basis(q0)
    config = lambda a: sm.normalize(q0 + jnp.einsum("ica,ia->ic", T0, a.reshape(n, 2)))

    def residual(a, _):
        q = config(a)
        return jnp.einsum("ica,ic->ia", T0, system.acceleration(0.0, q, jnp.zeros_like(q)))

    sol = optx.root_find(
        residual, optx.Newton(rtol=1e-13, atol=1e-13), jnp.zeros(2 * n), max_steps=50
    )
    return config(sol.value)


def test_statics_tip_force():
    """Link j carries the weight of the masses below it plus the tip force, so it points
    along F_j = d - g e3 sum_{k >= j} m_k."""
    m, ell = np.array([1.0, 0.5, 2.0]), np.array([1.2, 0.7, 1.0])
    d = np.array([3.0, -1.5, 0.8])
    chain = sm.chain_pendulum(m, ell, G, tip_force=jnp.asarray(d))
    F = d[None, :] - G * np.cumsum(m[::-1])[::-1][:, None] * np.array([0.0, 0.0, 1.0])
    expected = F / np.linalg.norm(F, axis=-1, keepdims=True)
    np.testing.assert_allclose(equilibrium(chain), expected, atol=1e-11)
    # and the general path agrees that this is an equilibrium
    general = sm.Lagrangian(chain.lagrangian, forces=chain.generalized_force)
    q = jnp.asarray(expected)
    assert float(jnp.max(jnp.abs(general.acceleration(0.0, q, jnp.zeros_like(q))))) < 1e-12


def test_statics_base_torque():
    """A base torque tau = tau_y e2 on link 1 tilts link 1 to sin(theta) = -tau_y /
    (g l_1 sum_k m_k) (moment balance about the base); the other links hang vertically."""
    m, ell = np.array([1.0, 0.5, 2.0]), np.array([1.2, 0.7, 1.0])
    tau_y = 9.0
    chain = sm.chain_pendulum(m, ell, G, torque=jnp.array([0.0, tau_y, 0.0]))
    s = -tau_y / (G * ell[0] * m.sum())
    expected = np.array([[s, 0.0, -np.sqrt(1 - s**2)], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    np.testing.assert_allclose(equilibrium(chain), expected, atol=1e-11)


# ----------------------------------------------------------------------------------------
# The chain's fast path equals the general autodiff path.
# ----------------------------------------------------------------------------------------


def time_dependent_torque(t, q, qdot, args):
    return jnp.array([jnp.sin(t), 0.3 * qdot[0, 2], jnp.cos(2 * t)])


@eqx.filter_jit
def chain_outputs(system, t, q, qdot):
    mu = system.momentum(t, q, qdot, None)
    return dict(
        qddot=system.acceleration(t, q, qdot, None),
        energy=system.energy(t, q, qdot, None),
        mu=mu,
        power=system.power(t, q, qdot, None),
        hamilton=sm.legendre(system).vector_field(t, q, mu, None),
    )


@pytest.mark.parametrize("n", [1, 4])
def test_chain_fast_path_equals_general_path(n, getkey):
    rng = np.random.default_rng(n)
    chain = sm.chain_pendulum(
        rng.uniform(0.5, 2.0, n),
        rng.uniform(0.5, 2.0, n),
        G,
        torque=time_dependent_torque,
        tip_force=jnp.asarray(rng.normal(size=3)),
    )
    general = sm.Lagrangian(chain.lagrangian, forces=chain.generalized_force)
    for _ in range(3):
        q, qdot = sm.random_state(getkey(), n)
        t = jnp.asarray(rng.uniform(0, 3))
        fast, slow = chain_outputs(chain, t, q, qdot), chain_outputs(general, t, q, qdot)
        for a, b in zip(jax.tree.leaves(fast), jax.tree.leaves(slow), strict=True):
            assert max_rel_error(a, b) < 1e-12
        mu = fast["mu"]
        velocity, result = chain.velocity_from_momentum(t, q, mu)
        assert max_rel_error(velocity, qdot) < 1e-12 and result == diffrax.RESULTS.successful
