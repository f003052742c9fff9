"""A first end-to-end check: the four forms of a forced chain pendulum agree, and a
simulation conserves energy and stays on the spheres."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

import sphere_mech as sm


def test_forms_agree_on_forced_chain(getkey):
    q, qdot = sm.random_state(getkey(), 3)
    chain = sm.chain_pendulum(
        jnp.array([1.0, 2.0, 0.5]), jnp.array([1.0, 0.7, 1.3]),
        tip_force=jnp.array([0.3, -0.2, 0.1]), torque=jnp.array([0.1, 0.2, -0.4]),
    )
    qddot = chain.acceleration(0.0, q, qdot)
    general = sm.Lagrangian(chain.lagrangian, forces=chain.generalized_force)
    np.testing.assert_allclose(general.acceleration(0.0, q, qdot), qddot, rtol=0, atol=1e-12)
    omega = sm.omega_from_qdot(q, qdot)
    omegadot = sm.angular(chain).angular_acceleration(0.0, q, omega)
    np.testing.assert_allclose(omegadot, jnp.cross(q, qddot), rtol=0, atol=1e-12)
    mu = chain.momentum(0.0, q, qdot)
    _, mudot_ref = jax.jvp(lambda q_, v_: chain.momentum(0.0, q_, v_), (q, qdot), (qdot, qddot))
    qdot3, mudot = sm.legendre(chain).vector_field(0.0, q, mu)
    np.testing.assert_allclose(qdot3, qdot, rtol=0, atol=1e-12)
    np.testing.assert_allclose(mudot, mudot_ref, rtol=0, atol=1e-12)


def test_simulation_conserves_energy_on_spheres():
    q0 = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    v0 = jnp.array([[0.0, 0.5, 1.0], [0.0, 0.0, 2.0]])
    chain = sm.chain_pendulum(jnp.array([1.0, 1.0]), jnp.array([1.0, 1.0]))
    ts = jnp.linspace(0.0, 5.0, 51)
    sol = sm.simulate(chain, (q0, v0), 5.0, saveat=diffrax.SaveAt(ts=ts))
    q, v = sol.ys
    energy = jax.vmap(chain.energy, (None, 0, 0))(0.0, q, v)
    assert float(jnp.max(jnp.abs(energy - energy[0]))) < 1e-6
    assert float(sm.constraint_error(q)) < 1e-14
