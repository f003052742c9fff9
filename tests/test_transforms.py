"""jit, vmap and grad (with respect to args, a system's own array leaves, and the state)
agree with the unjitted path and with finite differences; float32 works."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import max_rel_error

import sphere_mech as sm

CENTERS = jnp.array([[0.0, 0.0, 0.0], [1.5, 0.2, 0.0]])


def spring_lagrangian(t, q, qdot, args):
    """Two masses on spheres of radii r around fixed centers, joined by a spring, with a
    velocity-dependent (gyroscopic) term so that everything is exercised."""
    m, r, k = args["m"], args["r"], args["k"]
    x = CENTERS.astype(q.dtype) + r[:, None] * q
    v = r[:, None] * qdot
    stretch = jnp.linalg.norm(x[0] - x[1]) - 1.0
    gyro = 0.3 * jnp.sum(jnp.cross(q, qdot) * jnp.array([0.0, 0.0, 1.0], dtype=q.dtype))
    return (
        0.5 * jnp.sum(m * jnp.sum(v * v, -1)) + gyro - 0.5 * k * stretch**2 - 9.81 * (m @ x[:, 2])
    )


def damping(t, q, qdot, args):
    return -args["c"] * qdot


def make_args(dtype=jnp.float64):
    return dict(
        m=jnp.array([1.0, 2.0], dtype),
        r=jnp.array([1.0, 0.7], dtype),
        k=jnp.asarray(5.0, dtype),
        c=jnp.asarray(0.2, dtype),
    )


SYSTEM = sm.Lagrangian(spring_lagrangian, forces=damping)
NEWTON = sm.legendre(SYSTEM, quadratic=False)


@pytest.fixture(scope="module")
def state():
    return sm.random_state(jax.random.PRNGKey(3), 2)


def central_difference(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


def test_jit_matches_unjitted(state):
    q, qdot = state
    args = make_args()
    eager = SYSTEM.acceleration(0.2, q, qdot, args)
    jitted = eqx.filter_jit(SYSTEM.acceleration)(0.2, q, qdot, args)
    assert max_rel_error(jitted, eager) < 1e-13


ACCELERATION = eqx.filter_jit(SYSTEM.acceleration)


def test_vmap_over_states_and_parameters(getkey):
    keys = jax.random.split(getkey(), 4)
    q, qdot = jax.vmap(lambda k: sm.random_state(k, 2))(keys)
    args = make_args()
    batched = jax.jit(jax.vmap(ACCELERATION, (None, 0, 0, None)))(0.0, q, qdot, args)
    for i in range(4):
        assert max_rel_error(batched[i], ACCELERATION(0.0, q[i], qdot[i], args)) < 1e-13
    # a batch of chains (masses are array leaves)
    masses = jnp.array([[1.0, 2.0], [0.5, 0.5], [3.0, 1.0], [1.0, 1.0]])
    acc = lambda m, q_, v_: sm.chain_pendulum(m, jnp.ones(2)).acceleration(0.0, q_, v_)
    batched = jax.jit(jax.vmap(acc))(masses, q, qdot)
    acc = jax.jit(acc)
    for i in range(4):
        assert max_rel_error(batched[i], acc(masses[i], q[i], qdot[i])) < 1e-13


def test_grad_wrt_args_matches_finite_differences(state):
    """Through form 1 and through the Hamiltonian from Newton's Legendre map (implicit
    differentiation and the envelope-theorem derivative of H, to second order)."""
    q, qdot = state
    w = jax.random.normal(jax.random.PRNGKey(0), q.shape)
    mu = SYSTEM.momentum(0.0, q, qdot, make_args())

    @jax.jit
    def objectives(k):
        args = dict(make_args(), k=k)
        return jnp.stack(
            [
                jnp.sum(w * SYSTEM.acceleration(0.0, q, qdot, args)),
                jnp.sum(w * NEWTON.vector_field(0.0, q, mu, args)[1]),
                NEWTON.energy(0.0, q, mu, args),
            ]
        )

    k0 = jnp.asarray(5.0)
    grad = jax.jit(jax.jacrev(objectives))(k0)
    fd = central_difference(objectives, k0, 1e-5)
    np.testing.assert_allclose(grad, fd, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(objectives))(k0), grad, rtol=1e-12)


def test_filter_grad_wrt_chain_leaves(state):
    q, qdot = state
    chain = sm.chain_pendulum(
        jnp.array([1.0, 2.0]), jnp.array([0.8, 1.1]), 9.81, tip_force=jnp.array([0.5, 0.0, 1.0])
    )
    w = jax.random.normal(jax.random.PRNGKey(1), q.shape)

    @eqx.filter_grad
    def grad(chain):
        return jnp.sum(w * chain.acceleration(0.0, q, qdot))

    g = grad(chain)
    parameters = {  # where the chain scene keeps them
        "masses": lambda c: c.kinetic[0].masses,
        "lengths": lambda c: c.kinetic[0].lengths,
        "g": lambda c: c.potentials[0].g,
        "tip_force": lambda c: c.force_effects[0].force,
    }
    for where in parameters.values():
        leaf = where(chain)
        direction = jax.random.normal(jax.random.PRNGKey(2), jnp.shape(leaf))

        def f(h, where=where, leaf=leaf, direction=direction):
            moved = eqx.tree_at(where, chain, leaf + h * direction)
            return jnp.sum(w * moved.acceleration(0.0, q, qdot))

        fd = central_difference(f, 0.0, 1e-5)
        assert abs(float(jnp.sum(where(g) * direction) - fd)) < 1e-7 * (1 + abs(fd))


def test_grad_wrt_state_forward_and_reverse(state):
    """Directional derivative along a rotation of the state (which stays on the tangent
    bundle) against central differences; reverse mode against forward mode."""
    q, qdot = state
    args = make_args()
    w = jax.random.normal(jax.random.PRNGKey(4), q.shape)
    axis = jax.random.normal(jax.random.PRNGKey(5), q.shape)
    f = lambda q_, v_: jnp.sum(w * SYSTEM.acceleration(0.0, q_, v_, args))
    gq, gv = jax.jit(jax.grad(f, argnums=(0, 1)))(q, qdot)
    analytic = jnp.sum(gq * jnp.cross(axis, q)) + jnp.sum(gv * jnp.cross(axis, qdot))
    rotated = jax.jit(lambda h: f(sm.rotate(h * axis, q), sm.rotate(h * axis, qdot)))
    fd = central_difference(rotated, 0.0, 1e-5)
    assert abs(float(analytic - fd)) < 1e-7 * (1 + abs(float(fd)))
    acc = lambda v_: SYSTEM.acceleration(0.0, q, v_, args)
    forward, reverse = jax.jit(jax.jacfwd(acc))(qdot), jax.jit(jax.jacrev(acc))(qdot)
    np.testing.assert_allclose(forward, reverse, atol=1e-12)


def test_float32(state):
    q64, v64 = state
    q, v = q64.astype(jnp.float32), v64.astype(jnp.float32)
    args = make_args(jnp.float32)
    acc = ACCELERATION(0.0, q, v, args)
    assert acc.dtype == jnp.float32
    assert max_rel_error(acc, ACCELERATION(0.0, q64, v64, make_args())) < 1e-4
    mu = SYSTEM.momentum(0.0, q, v, args)
    qdot, mudot = eqx.filter_jit(sm.legendre(SYSTEM).vector_field)(0.0, q, mu, args)
    assert qdot.dtype == mudot.dtype == jnp.float32
    assert max_rel_error(qdot, v) < 1e-4
    chain = sm.chain_pendulum(jnp.array([1.0, 2.0], jnp.float32), jnp.array([1.0, 0.5]))
    assert chain.acceleration(0.0, q, v).dtype == jnp.float32
    ts = jnp.linspace(0.0, 1.0, 11, dtype=jnp.float32)
    sol = sm.simulate(chain, (q, v), 1.0, saveat=diffrax.SaveAt(ts=ts))
    qs, vs = sol.ys
    assert qs.dtype == vs.dtype == jnp.float32
    energy = jax.vmap(lambda q_, v_: chain.energy(0.0, q_, v_))(qs, vs)
    assert energy.dtype == jnp.float32
    assert float(jnp.max(jnp.abs(energy - energy[0]))) < 1e-4 * float(jnp.max(jnp.abs(energy)))
    assert float(sm.constraint_error(qs)) < 1e-6
