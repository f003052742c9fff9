"""The inverse Legendre map of a Lagrangian defined on bounded velocities: a relativistic
particle on the sphere, `L = -m sqrt(1 - |qdot|^2) - m g z`, with momenta well above `m`
(the linear guess lands at `|v| > 1`, where `L` is NaN)."""

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest

import sphere_mech as sm

M = 1.0
SPEED = 0.9  # |mu| = m v / sqrt(1 - v^2) = 2.06 m
Q0 = jnp.array([[1.0, 0.0, 0.0]])
V0 = jnp.array([[0.0, SPEED * 0.6, SPEED * 0.8]])
TS = jnp.linspace(0.0, 20.0, 41)
TOL = dict(rtol=1e-12, atol=1e-12, saveat=diffrax.SaveAt(ts=TS), max_steps=200_000)


def relativistic(t, q, qdot, g):
    return -M * jnp.sqrt(1.0 - jnp.sum(qdot**2)) - M * g * q[0, 2]


LAGRANGIAN = sm.Lagrangian(relativistic)
HAMILTONIAN = sm.legendre(LAGRANGIAN)


@pytest.fixture(scope="module", params=[0.0, 1.0], ids=["free", "gravity"])
def runs(request):
    g = jnp.asarray(request.param)
    mu0 = LAGRANGIAN.momentum(0.0, Q0, V0, g)
    assert float(jnp.linalg.norm(mu0)) > 2 * M
    lag = sm.simulate(LAGRANGIAN, (Q0, V0), 20.0, args=g, **TOL)
    ham = sm.simulate(HAMILTONIAN, (Q0, mu0), 20.0, args=g, **TOL)
    return request.param, lag, ham


def test_legendre_velocity_beyond_the_linear_guess():
    mu = LAGRANGIAN.momentum(0.0, Q0, V0, 1.0)
    qdot, _ = HAMILTONIAN.vector_field(0.0, Q0, mu, 1.0)
    np.testing.assert_allclose(qdot, V0, rtol=0, atol=1e-13)


def test_forms_agree_over_20_s(runs):
    g, lag, ham = runs
    np.testing.assert_allclose(lag.ys[0], ham.ys[0], rtol=0, atol=1e-9)
    energy = np.asarray(
        [float(LAGRANGIAN.energy(0.0, q, v, g)) for q, v in zip(*lag.ys, strict=True)]
    )
    assert np.max(np.abs(energy - energy[0])) < 1e-10 * abs(energy[0])
    if g == 0.0:  # a great circle at constant speed: the closed form
        t = np.asarray(TS)[:, None, None]
        exact = np.cos(SPEED * t) * np.asarray(Q0) + np.sin(SPEED * t) * np.asarray(V0) / SPEED
        np.testing.assert_allclose(lag.ys[0], exact, rtol=0, atol=1e-9)
        np.testing.assert_allclose(ham.ys[0], exact, rtol=0, atol=1e-9)
