"""Scenes: each effect against an independent check (statics, small oscillations,
energy identities, closed forms), the Kapitza pendulum, the work-energy balance, and the
evidence that a scene compiles only the effects it lists."""

from pathlib import Path

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import CART_SCENE, jaxpr_equations

import sphere_mech as sm

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
E3 = jnp.array([0.0, 0.0, 1.0])


@eqx.filter_jit
def at_rest_acceleration(scene, q, t=0.0):
    return scene.acceleration(t, jnp.asarray(q), jnp.zeros_like(jnp.asarray(q)))


def unit(x):
    x = jnp.asarray(x, dtype=float)
    return x / jnp.linalg.norm(x)


# ---- kinetic terms ---------------------------------------------------------------------


def test_chain_matches_chain_pendulum(getkey):
    """`chain_pendulum` (a Scene of Chain, Gravity, BaseTorque, TipForce) against the
    generic autodiff `Lagrangian` of the chain's L written out here, with the generalized
    forces derived by hand from virtual work: the base torque acts on link 1 only,
    `f_1 = tau x q_1`, and the tip force `d` at `x_n = sum_j l_j q_j` gives `f_j = l_j d`."""
    m, ell, g = jnp.array([1.0, 2.0, 0.5]), jnp.array([1.0, 0.7, 1.3]), 9.81
    tau, d = jnp.array([0.1, 0.2, -0.4]), jnp.array([0.3, -0.2, 0.1])
    q, qdot = sm.random_state(getkey(), 3)

    def L(t, q, qdot, args):
        x, xdot = (jnp.cumsum(ell[:, None] * a, axis=0) for a in (q, qdot))
        return 0.5 * jnp.sum(m * jnp.sum(xdot**2, axis=-1)) - g * jnp.sum(m * x[:, 2])

    def forces(t, q, qdot, args):
        return (ell[:, None] * d).at[0].add(jnp.cross(tau, q[0]))

    reference = sm.Lagrangian(L, forces=forces)
    chain = sm.chain_pendulum(m, ell, g, torque=tau, tip_force=d)
    assert isinstance(chain, sm.Scene)
    accel = eqx.filter_jit(lambda system: system.acceleration(0.0, q, qdot))
    np.testing.assert_allclose(accel(chain), accel(reference), rtol=0, atol=1e-11)
    np.testing.assert_allclose(
        chain.energy(0.0, q, qdot), reference.energy(0.0, q, qdot), rtol=1e-14
    )
    np.testing.assert_allclose(
        chain.generalized_force(0.0, q, qdot), forces(0.0, q, qdot, None), atol=1e-15
    )
    np.testing.assert_allclose(chain.positions(q), jnp.cumsum(ell[:, None] * q, axis=0), atol=1e-15)
    # callables for the torque and the tip force give the same forces
    driven = sm.chain_pendulum(
        m, ell, g, torque=lambda t, q, v, a: tau, tip_force=lambda t, q, v, a: d
    )
    np.testing.assert_allclose(accel(driven), accel(reference), rtol=0, atol=1e-11)


def test_batched_and_differentiated_chains(getkey):
    """Parameters are array leaves: `filter_vmap(chain_pendulum)` builds a batch of
    chains (the checks skip traced values), and gradients w.r.t. the masses agree with
    central differences."""
    q, qdot = sm.random_state(getkey(), 2)
    masses = jnp.array([[1.0, 2.0], [0.5, 1.5], [2.0, 0.3]])
    lengths = jnp.array([[1.0, 0.7], [0.4, 1.1], [0.9, 0.9]])
    chains = eqx.filter_vmap(sm.chain_pendulum)(masses, lengths)
    batched = eqx.filter_vmap(lambda c: c.acceleration(0.0, q, qdot))(chains)
    for k in range(3):
        single = sm.chain_pendulum(masses[k], lengths[k]).acceleration(0.0, q, qdot)
        np.testing.assert_allclose(batched[k], single, rtol=0, atol=1e-13)

    def loss(m):
        return jnp.sum(sm.chain_pendulum(m, lengths[0]).acceleration(0.0, q, qdot) ** 2)

    grad = jax.grad(loss)(masses[0])
    eps = 1e-6
    fd = [
        (loss(masses[0].at[i].add(eps)) - loss(masses[0].at[i].add(-eps))) / (2 * eps)
        for i in range(2)
    ]
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


@pytest.mark.parametrize("kind", ["chain", "particles", "shared"])
def test_kinetic_energy_identity(kind, getkey):
    """T = 1/2 sum m_i |xdot_i|^2 with xdot from autodiff of the positions."""
    q, qdot = sm.random_state(getkey(), 3)
    m = jnp.array([1.0, 2.0, 0.5])
    kinetic = {
        "chain": sm.Chain(m, [0.5, 1.0, 2.0], base=[1.0, 0.0, 2.0]),
        "particles": sm.Particles(m, [0.5, 1.0, 2.0], centers=jnp.ones((3, 3))),
        "shared": sm.SharedSphere(m, 1.7, center=[0.0, 1.0, 0.0]),
    }[kind]
    scene = sm.Scene(kinetic)
    _, xdot = jax.jvp(scene.positions, (q,), (qdot,))
    expected = 0.5 * jnp.sum(m * jnp.sum(xdot**2, axis=-1))
    np.testing.assert_allclose(scene.energy(0.0, q, qdot), expected, rtol=1e-13)
    # the O(n) kinetic energy equals the one of the dense inertia matrix
    dense = 0.5 * jnp.sum(scene.inertia() * (qdot @ qdot.T))
    np.testing.assert_allclose(scene.kinetic_energy(q, qdot), dense, rtol=1e-13)


def test_particle_on_sphere_is_a_pendulum_of_length_r():
    """At rest at angle theta from the bottom: tangential acceleration (g/r) sin(theta)."""
    r, g, theta = 0.4, 9.81, 0.3
    scene = sm.Scene(sm.Particles([2.0], [r], centers=[[1.0, 2.0, 3.0]]), sm.Gravity(g))
    q = jnp.array([[np.sin(theta), 0.0, -np.cos(theta)]])
    a = at_rest_acceleration(scene, q)[0]
    tangent_down = jnp.array([-np.cos(theta), 0.0, -np.sin(theta)])
    np.testing.assert_allclose(a, g / r * np.sin(theta) * tangent_down, atol=1e-13)


# ---- potentials ------------------------------------------------------------------------


def test_gravity_any_direction_statics():
    d = unit([1.0, -2.0, 0.5])
    scene = sm.Scene(sm.Chain([1.5], [0.8]), sm.Gravity(3.0, d))
    np.testing.assert_allclose(at_rest_acceleration(scene, d[None]), 0.0, atol=1e-13)
    # at angle theta from d the angular acceleration is (g/l) sin(theta)
    e = unit(jnp.cross(d, jnp.array([0.0, 0.0, 1.0])))
    theta = 0.7
    q = (np.cos(theta) * d + np.sin(theta) * e)[None]
    a = at_rest_acceleration(scene, q)[0]
    np.testing.assert_allclose(jnp.linalg.norm(a), 3.0 / 0.8 * np.sin(theta), rtol=1e-13)


def test_spring_statics_closed_form():
    """Zero-rest-length spring to an anchor A plus gravity on a particle of radius r:
    U = -r q . (k A - m g e3) + const, so the equilibrium is q* = unit(k A - m g e3)."""
    k, m, g, r, A = 5.0, 0.3, 9.81, 0.6, jnp.array([1.0, 0.5, 0.2])
    scene = sm.Scene(sm.Particles([m], [r]), sm.Gravity(g), sm.Spring(0, A, k))
    q_star = unit(k * A - m * g * E3)[None]
    np.testing.assert_allclose(at_rest_acceleration(scene, q_star), 0.0, atol=1e-12)
    # and a spring with rest length between two masses: U = k/2 (d - L0)^2
    two = sm.Scene(
        sm.Particles([1.0, 1.0], [1.0, 2.0], centers=[[0, 0, 0], [3.0, 0, 0]]),
        sm.Spring(0, 1, 4.0, rest_length=0.5),
    )
    q = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    d = np.linalg.norm(np.array([1.0, 0, 0]) - np.array([3.0, 2.0, 0]))
    np.testing.assert_allclose(two.potential(0.0, q), 2.0 * (d - 0.5) ** 2, rtol=1e-14)


def test_bending_relative_mode_frequency():
    """Two links in zero gravity with bending stiffness k: the relative mode oscillates
    with omega^2 = k u^T M^{-1} u, u = (1, -1), M the planar inertia (numpy, not
    sphere_mech). Released bent by 1e-3 rad at rest, the bend is reversed after half a
    period and restored after a full period."""
    m, ell, k, eps = np.array([1.0, 0.5]), np.array([1.0, 0.6]), 2.0, 1e-3
    M = np.array(
        [
            [(m[0] + m[1]) * ell[0] ** 2, m[1] * ell[0] * ell[1]],
            [m[1] * ell[0] * ell[1], m[1] * ell[1] ** 2],
        ]
    )
    u = np.array([1.0, -1.0])
    period = 2 * np.pi / np.sqrt(k * u @ np.linalg.solve(M, u))
    scene = sm.Scene(sm.Chain(m, ell), sm.Bending(k))
    q0 = jnp.array([[1.0, 0.0, 0.0], [np.cos(eps), np.sin(eps), 0.0]])
    ts = jnp.array([0.0, 0.5 * period, period])
    sol = sm.simulate(
        scene,
        (q0, jnp.zeros_like(q0)),
        period,
        saveat=diffrax.SaveAt(ts=ts),
        rtol=1e-11,
        atol=1e-13,
    )
    q = sol.ys[0]
    bend = np.arcsin(np.cross(q[:, 0], q[:, 1])[:, 2])
    np.testing.assert_allclose(bend, [eps, -eps, eps], rtol=0, atol=2e-3 * eps)


def test_pair_interaction_beads_settle_to_tetrahedron(getkey):
    """Four repelling charges with drag on a sphere of radius R relax to a regular
    tetrahedron: U = 6 k / (R sqrt(8/3)) (Thomson problem, N = 4)."""
    R, k = 1.5, 0.7
    scene = sm.Scene(sm.SharedSphere(jnp.ones(4), R), sm.PairInteraction(k), sm.JointDamping(1.0))
    q0 = sm.random_points(getkey(), 4)
    sol = sm.simulate(scene, (q0, jnp.zeros_like(q0)), 40.0)
    q = sol.ys[0][-1]
    np.testing.assert_allclose(scene.potential(0.0, q), 6 * k / (R * np.sqrt(8 / 3)), rtol=1e-7)
    gram = q @ q.T
    np.testing.assert_allclose(gram[np.triu_indices(4, 1)], -1.0 / 3.0, atol=1e-3)


# ---- forces ----------------------------------------------------------------------------


def test_joint_damping_power_against_least_squares(getkey):
    """Power of joint damping = -sum_i c_i |r_i|^2, `r_i = w_i + s_i q_i - w_{i-1} -
    s_{i-1} q_{i-1}` (`w_i = q_i x qdot_i`, the pivot's zero) with the links' free spins
    `s` minimizing it: numpy's least squares over `s`. Parallel links with an undamped
    pivot leave a spin free (a singular solve without regularization); zero damping is
    zero force (not NaN)."""

    def reference(q, qdot, c):
        q, qdot, n = np.asarray(q), np.asarray(qdot), len(q)
        w, A, r = np.cross(q, qdot), np.zeros((3 * n, n)), np.zeros(3 * n)
        for i in range(n):
            rows, root = slice(3 * i, 3 * i + 3), np.sqrt(c[i])
            r[rows], A[rows, i] = root * (w[i] - (w[i - 1] if i else 0.0)), root * q[i]
            if i:
                A[rows, i - 1] = -root * q[i - 1]
        s = np.linalg.lstsq(A, -r, rcond=None)[0]
        return -np.sum((r + A @ s) ** 2)

    chain = sm.Chain(jnp.ones(3), jnp.ones(3))
    q, qdot = sm.random_state(getkey(), 3)
    c = np.array([0.37, 0.2, 0.55])
    power = sm.Scene(chain, sm.JointDamping(c)).power(0.0, q, qdot, None)
    np.testing.assert_allclose(power, reference(q, qdot, c), rtol=1e-13)
    down = jnp.tile(jnp.array([[0.0, 0.0, -1.0]]), (3, 1))
    qdot = jnp.array([[1.0, 0.0, 0.0], [0.5, 0.2, 0.0], [0.0, 1.0, 0.0]])
    c = np.array([0.0, 0.3, 0.2])
    power = sm.Scene(chain, sm.JointDamping(c)).power(0.0, down, qdot, None)
    np.testing.assert_allclose(power, reference(down, qdot, c), rtol=1e-13)
    undamped = sm.Scene(chain, sm.JointDamping(0.0)).forces(0.0, q, qdot, None)
    np.testing.assert_array_equal(undamped, 0.0)


def test_base_torque_statics():
    """Constant torque tau e_y on a pendulum: equilibrium at sin(theta) = tau / (m g l),
    q* = (-sin theta, 0, -cos theta). A PD torque toward d: q* = unit(kp d - m g l e3)."""
    m, g, ell, tau = 0.5, 9.81, 1.2, 2.0
    s = tau / (m * g * ell)
    scene = sm.Scene(sm.Chain([m], [ell]), sm.Gravity(g), sm.BaseTorque(jnp.array([0, tau, 0])))
    q_star = jnp.array([[-s, 0.0, -np.sqrt(1 - s**2)]])
    np.testing.assert_allclose(at_rest_acceleration(scene, q_star), 0.0, atol=1e-12)
    d, kp = unit([1.0, 1.0, 0.0]), 8.0
    pd = sm.Scene(sm.Chain([m], [ell]), sm.Gravity(g), sm.BaseTorque(sm.PDTorque(kp, 1.0, d)))
    q_star = unit(kp * d - m * g * ell * E3)[None]
    np.testing.assert_allclose(at_rest_acceleration(pd, q_star), 0.0, atol=1e-12)


def test_tip_force_statics():
    """Two-link chain with gravity and a tip force F: each link points along the force
    it carries, q2* = unit(F - m2 g e3), q1* = unit(F - (m1 + m2) g e3)."""
    m, g, F = jnp.array([1.0, 0.4]), 9.81, jnp.array([3.0, -1.0, 0.5])
    scene = sm.Scene(sm.Chain(m, [1.0, 0.5]), sm.Gravity(g), sm.TipForce(F))
    q_star = jnp.stack([unit(F - (m[0] + m[1]) * g * E3), unit(F - m[1] * g * E3)])
    np.testing.assert_allclose(at_rest_acceleration(scene, q_star), 0.0, atol=1e-12)


def test_vibrating_support_force_closed_form(getkey):
    """Single link: f = -m l s''(t), s''(t) = -a w^2 cos(w t) dir."""
    q, qdot = sm.random_state(getkey(), 1)
    a, w, m, ell, t = 0.02, 50.0, 0.3, 0.7, 0.123
    direction = unit([0.0, 1.0, 1.0])
    scene = sm.Scene(sm.Chain([m], [ell]), sm.VibratingSupport(a, w, direction))
    expected = m * ell * a * w**2 * np.cos(w * t) * direction
    np.testing.assert_allclose(scene.generalized_force(t, q, qdot)[0], expected, rtol=1e-13)


# ---- the Kapitza pendulum --------------------------------------------------------------


@pytest.fixture(scope="module")
def kapitza():
    return sm.load_scene(EXAMPLES / "kapitza.toml")


def _polar_deg(q):
    return np.degrees(np.arccos(np.clip(np.asarray(q)[..., 0, 2], -1, 1)))


def test_kapitza_documented_parameters(kapitza):
    """The file's parameters satisfy the documented criterion a^2 w^2 > 2 g l."""
    chain, gravity, support = kapitza.scene.effects
    a, w = float(support.amplitude), float(support.angular_frequency)
    assert a**2 * w**2 > 2 * float(gravity.g) * float(chain.lengths[0])


def test_kapitza_stays_inverted_and_falls_without_vibration(kapitza):
    ts = jnp.linspace(0.0, 1.5, 301)
    kw = dict(saveat=diffrax.SaveAt(ts=ts), rtol=1e-8, atol=1e-10)
    sol = sm.simulate(kapitza.scene, kapitza.y0, 1.5, **kw)
    assert np.max(_polar_deg(sol.ys[0])) < 25.0  # started at 15 degrees from upright
    chain, gravity, _ = kapitza.scene.effects
    still = sm.Scene(chain, gravity)
    sol = sm.simulate(still, kapitza.y0, 1.5, **kw)
    assert np.max(_polar_deg(sol.ys[0])) > 150.0  # fell through the bottom


# ---- energy bookkeeping -------------------------------------------------------------------


def test_work_energy_balance_of_a_driven_damped_chain(getkey):
    """With damping, a PD torque and a time-dependent tip force, E changes by O(1) but
    E - E(0) - int power dt stays at the integration tolerance."""
    scene = sm.Scene(
        sm.Chain([1.0, 0.5], [1.0, 0.8]),
        sm.Gravity(),
        sm.JointDamping(0.2),
        sm.BaseTorque(sm.PDTorque(5.0, 0.5, unit([1.0, 0.0, 0.3]))),
        sm.TipForce(lambda t, q, v, args: jnp.array([jnp.sin(3 * t), 0.0, 0.0])),
    )
    q0, v0 = sm.random_state(getkey(), 2)
    saveat = diffrax.SaveAt(t0=True, steps=True)
    sol = sm.simulate(scene, (q0, v0), 3.0, saveat=saveat, rtol=1e-10, atol=1e-12)
    keep = np.isfinite(np.asarray(sol.ts))
    ts, q, v = (np.asarray(a)[keep] for a in (sol.ts, *sol.ys))
    energy, W, balance = sm.work_energy_balance(scene, ts, q, v)
    assert np.max(np.abs(energy - energy[0])) > 1.0
    assert np.max(np.abs(balance)) < 1e-7 * np.max(np.abs(energy))


def test_effect_parameters_are_differentiable_and_vmappable(getkey):
    q, qdot = sm.random_state(getkey(), 2)

    @jax.jit
    def accel(g, c):
        scene = sm.Scene(sm.Chain([1.0, 1.0], [1.0, 1.0]), sm.Gravity(g), sm.JointDamping(c))
        return scene.acceleration(0.0, q, qdot)

    batched = jax.vmap(accel)(jnp.array([1.0, 9.81]), jnp.array([0.0, 0.5]))
    np.testing.assert_allclose(batched[1], accel(9.81, 0.5), atol=1e-14)
    grad = jax.grad(lambda g: jnp.sum(accel(g, 0.5) ** 2))(9.81)
    eps = 1e-6
    fd = (jnp.sum(accel(9.81 + eps, 0.5) ** 2) - jnp.sum(accel(9.81 - eps, 0.5) ** 2)) / (2 * eps)
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


# ---- only what is called for --------------------------------------------------------------


def _vector_field_jaxpr(scene, n):
    q = jnp.tile(jnp.array([[0.0, 0.6, -0.8]]), (n, 1))
    y = (q, jnp.zeros_like(q).at[:, 0].set(1.0))
    return jax.make_jaxpr(lambda t, y: scene.rates(t, y, None))(0.0, y).jaxpr


def test_absent_effects_add_no_operation():
    chain = sm.Chain(jnp.ones(4), jnp.ones(4))
    gravity_only = sm.Scene(chain, sm.Gravity())
    driven = sm.Scene(
        chain, sm.Gravity(), sm.JointDamping(0.1), sm.BaseTorque(sm.PDTorque(2.0, 0.5))
    )
    small = list(jaxpr_equations(_vector_field_jaxpr(gravity_only, 4)))
    large = list(jaxpr_equations(_vector_field_jaxpr(driven, 4)))
    assert len(small) < len(large)
    stacks = lambda eqns: " ".join(str(e.source_info.name_stack) for e in eqns)
    assert "Gravity" in stacks(small) and "Gravity" in stacks(large)
    for absent in ("JointDamping", "BaseTorque"):
        assert absent not in stacks(small)
        assert absent in stacks(large)
    # at the top level the difference is exactly the equations tagged with the two force
    # effects, plus the few that sum f into the right-hand side
    top_small = _vector_field_jaxpr(gravity_only, 4).eqns
    top_large = _vector_field_jaxpr(driven, 4).eqns
    tagged = [
        e
        for e in top_large
        if any(n in str(e.source_info.name_stack) for n in ("JointDamping", "BaseTorque"))
    ]
    assert len(top_small) + len(tagged) <= len(top_large) <= len(top_small) + len(tagged) + 4
    assert not sm.Scene(chain, sm.Gravity()).has_forces
    assert gravity_only.forces is None
    assert gravity_only.generalized_force(0.0, *_state(4)) is None
    assert driven.has_forces and driven.forces(0.0, *_state(4), None).shape == (4, 3)


def _state(n):
    q = jnp.tile(jnp.array([[0.0, 0.6, -0.8]]), (n, 1))
    return q, jnp.zeros_like(q)


def test_scene_rejects_bad_structure():
    with pytest.raises(ValueError, match="kinetic term"):
        sm.Scene(sm.Gravity())
    with pytest.raises(ValueError, match=r"lengths must be a scalar or 2 values, one per sphere"):
        sm.Chain([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match=r"masses must be a scalar or 4 values"):
        sm.Chain([1.0, 2.0], 1.0, links=4)
    with pytest.raises(ValueError, match="effects"):
        sm.Scene(sm.Chain([1.0], [1.0]), "gravity")


TWO = sm.Chain([1.0, 1.0], [1.0, 1.0])
TAU = jnp.array([0.0, 0.0, 1.0])


@pytest.mark.parametrize(
    "build, message",
    [
        (lambda: sm.Chain([1.0, -1.0], [1.0, 1.0]), "masses must be > 0 (kg), got [1.0, -1.0]"),
        (lambda: sm.Chain([1.0, 0.0], [1.0, 1.0]), "masses must be > 0 (kg), got [1.0, 0.0]"),
        (lambda: sm.Chain([1.0, 1.0], [0.0, 1.0]), "lengths must be > 0 (m), got [0.0, 1.0]"),
        (lambda: sm.Chain(1.0, -0.5, links=3), "lengths must be > 0 (m), got [-0.5, -0.5, -0.5]"),
        (
            lambda: sm.chain_pendulum([1.0, -1.0], [1.0, 1.0]),
            "masses must be > 0 (kg), got [1.0, -1.0]",
        ),
        (lambda: sm.chain_pendulum([1.0, 1.0], [1.0, 1.0], g=-9.81), "g must be >= 0 (m/s^2)"),
        (lambda: sm.Particles([1.0], [0.0]), "radii must be > 0 (m), got [0.0]"),
        (lambda: sm.SharedSphere(1.0, radius=-1.0, count=2), "radius must be > 0 (m), got -1.0"),
        (lambda: sm.Gravity(9.81, [0.0, 0.0, -2.0]), "direction must be a unit vector"),
        (lambda: sm.JointDamping(-0.1), "coefficient must be >= 0 (N m s), got -0.1"),
        (lambda: sm.Spring(0, 1, -2.0), "stiffness must be >= 0 (N/m), got -2.0"),
        (lambda: sm.PairInteraction(1.0, exponent=0.0), "exponent must be > 0, got 0.0"),
        (lambda: sm.PDTorque(-1.0), "kp must be >= 0 (N m), got -1.0"),
        (
            lambda: sm.Scene(TWO, sm.BaseTorque(TAU, link=7)),
            "BaseTorque.link must be an integer sphere index in [-2, 2) (the scene has 2 "
            "spheres), got 7",
        ),
        (lambda: sm.Scene(TWO, sm.BaseTorque(TAU, link=-3)), "BaseTorque.link must be"),
        (lambda: sm.Scene(TWO, sm.BaseTorque(sm.PDTorque(1.0, link=2))), "PDTorque.link must be"),
        (
            lambda: sm.Scene(TWO, sm.TipForce(TAU, point=2)),
            "TipForce.point must be an integer sphere",
        ),
        (lambda: sm.Scene(TWO, sm.Spring(0, 5, 1.0)), "Spring.b must be an integer sphere index"),
        (
            lambda: sm.Scene(TWO, sm.PairInteraction(1.0, masses=(0, 2))),
            "PairInteraction.masses must be an integer sphere index",
        ),
        (
            lambda: sm.Scene(TWO, sm.PairInteraction(1.0, charges=[1.0, 2.0, 3.0])),
            "charges must be one value per interacting mass (2)",
        ),
        (
            lambda: sm.Scene(sm.Chain([1.0], [1.0]), sm.Bending(1.0)),
            "Bending needs a Chain with at least two links",
        ),
        (
            lambda: sm.Scene(TWO, sm.JointDamping([0.1, 0.2, 0.3])),
            "coefficient must be a scalar or 2 values, one per sphere",
        ),
        # indices and counts are integers (a float or a bool is not truncated or taken)
        (
            lambda: sm.Scene(TWO, sm.TipForce(TAU, point=1.0)),
            "TipForce.point must be an integer sphere index in [-2, 2) (the scene has 2 "
            "spheres), got 1.0",
        ),
        (
            lambda: sm.Spring(1.0, 0, 1.0),
            "a must be an integer sphere index or a (3,) anchor point, got shape ()",
        ),
        (  # said "expected a number or an array of numbers", without the index
            lambda: sm.Spring(True, 0, 1.0),
            "a: expected an integer sphere index or a (3,) anchor point, got True",
        ),
        (lambda: sm.Chain(1.0, 1.0, links=True), "links must be an integer from 1 to 100000"),
        (lambda: sm.Chain(1.0, 1.0, links=2.0), "links must be an integer from 1 to 100000"),
        (
            lambda: sm.PairInteraction(1.0, masses=True),
            "PairInteraction.masses must be a sequence of integer sphere indices, got True",
        ),
        (
            lambda: sm.Scene(TWO, sm.PairInteraction(1.0, masses=(0.0, 1.0))),
            "PairInteraction.masses must be an integer sphere index",
        ),
        (
            lambda: sm.Scene(sm.Chain(1.0, 1.0, links=3), sm.PairInteraction(1.0, masses=(0, -3))),
            "PairInteraction.masses must name each mass once, got (0, -3) (mass 0 twice)",
        ),
        # the controller's model of the vehicle checked as RigidBase checks it
        (
            lambda: sm.GeometricControl(1.0, [-1.0, -1.0, -1.0], 1.0, 1.0, 1.0, 1.0),
            "inertia must be symmetric positive-definite (kg m^2)",
        ),
        (
            lambda: sm.GeometricControl(1.0, [0.01] * 3, 1.0, 1.0, 1.0, 1.0, command=[0, 0, 0]),
            "command must be an AbstractCommand (Hover, Line, Circle) or a function",
        ),
        (lambda: sm.Hover(heading=[0.0, 0.0, 1.0]), "heading must not be vertical"),
        (
            lambda: sm.RigidBase(0.5, [0.01, np.nan, 0.015]),
            "inertia must be finite and at most 1e+100 in magnitude, got nan",
        ),
        (lambda: sm.Line([0.0] * 3, [1.0, 0, 0], [0, 0, -1.0]), "heading must not be vertical"),
        (  # as in a scene file (before: True taken as 1.0, "1" a JAX TypeError)
            lambda: sm.Chain(True, 1.0),
            "masses: expected a number or an array of numbers, got True",
        ),
        (lambda: sm.Chain(1.0, "1"), "lengths: expected a number or an array of numbers, got '1'"),
        # a field's converter names it, as a scene file does (before: an unnamed TypeError
        # "expected a number ...", and raw NumPy errors for a ragged list or a string radius)
        (lambda: sm.Gravity("9.81"), "g: expected a number or an array of numbers, got '9.81'"),
        (lambda: sm.PDTorque(None), "kp: expected a number or an array of numbers, got None"),
        (
            lambda: sm.SharedSphere(1.0, radius="1", count=2),
            "radius: expected a number or an array of numbers, got '1'",
        ),
        (  # before: True taken as a mass of 1, "9.81" as 9.81
            lambda: sm.chain_pendulum([True, True], [1.0, 1.0]),
            "masses: expected a number or an array of numbers, got [True, True]",
        ),
        (
            lambda: sm.chain_pendulum([1.0], [1.0], g="9.81"),
            "g: expected a number or an array of numbers, got '9.81'",
        ),
        (
            lambda: sm.Chain([1.0, [2.0]], 1.0),
            "masses: expected a number or an array of numbers, got [1.0, [2.0]]",
        ),
        (  # as VibratingSupport's (before: accepted)
            lambda: sm.Harmonic(1.0, -2.0),
            "angular_frequency must be >= 0 (rad/s), got -2.0",
        ),
    ],
)
def test_invalid_parameters_raise_at_construction(build, message):
    with pytest.raises(ValueError) as info:
        build()
    assert message in str(info.value)


def test_spring_anchor_as_a_list():
    """A fixed end given as a list or tuple is a vector, as in a scene file."""
    anchor = jnp.array([0.0, 0.0, 1.0])
    for given in ([0.0, 0.0, 1.0], (0.0, 0.0, 1.0)):
        assert eqx.tree_equal(sm.Spring(given, 0, 1.0), sm.Spring(anchor, 0, 1.0))


def test_indices_count_from_the_end():
    """Negative indices follow Python: -1 is the last sphere."""
    scene = sm.Scene(TWO, sm.TipForce(TAU, point=-2), sm.BaseTorque(TAU, link=-1))
    assert scene.has_forces


def test_scalar_parameters_broadcast():
    """A scalar where one value per sphere is expected applies to every sphere."""
    same = lambda a, b: bool(eqx.tree_equal(a, b))
    assert same(sm.Chain(0.5, 0.25, links=4), sm.Chain([0.5] * 4, [0.25] * 4))
    assert same(sm.Chain([1.0, 2.0, 3.0], 0.25), sm.Chain([1.0, 2.0, 3.0], [0.25] * 3))
    assert same(
        sm.Particles(2.0, [0.5, 1.0], centers=[1.0, 0.0, 0.0]),
        sm.Particles([2.0, 2.0], [0.5, 1.0], centers=[[1.0, 0.0, 0.0]] * 2),
    )
    assert same(sm.SharedSphere(1.5, count=3), sm.SharedSphere([1.5] * 3))


def test_fast_path_matches_autodiff_lagrangian(getkey):
    """A mixed scene (chain, own spheres, shared sphere, every potential and force) on
    the O(n) fast path agrees with the generic autodiff form-1 `Lagrangian` of the same
    L and f, and M^-1 from the bands is the inverse of M."""
    scene = sm.Scene(
        sm.Chain([1.0, 0.5, 2.0], [0.7, 1.0, 0.4], base=[0.0, 0.0, 1.0]),
        sm.Particles([0.3], [0.5], centers=[[2.0, 0.0, 0.0]]),
        sm.SharedSphere([1.0, 1.5], 0.8, center=[0.0, 3.0, 0.0]),
        sm.Gravity(9.81, unit([0.1, 0.0, -1.0])),
        sm.Bending(0.3),
        sm.Spring(2, 3, 2.0, rest_length=0.5),
        sm.PairInteraction(0.2, masses=(4, 5)),
        sm.JointDamping(0.1),
        sm.BaseTorque(sm.PDTorque(1.0, 0.2)),
        sm.TipForce(jnp.array([0.0, 1.0, 0.0]), point=2),
        sm.VibratingSupport(0.05, 7.0),
    )
    q, qdot = sm.random_state(getkey(), 6)
    generic = sm.Lagrangian(scene.lagrangian, forces=scene.generalized_force)
    accel = eqx.filter_jit(lambda system: system.acceleration(0.3, q, qdot))
    np.testing.assert_allclose(accel(scene), accel(generic), rtol=0, atol=1e-11)
    d, e = scene.inverse_inertia_bands()
    Minv = jnp.diag(d) + jnp.diag(e, 1) + jnp.diag(e, -1)
    np.testing.assert_allclose(Minv @ scene.inertia(), jnp.eye(6), atol=1e-13)


# ---- scene files: the same Modules, the same checks, the same words ----------------------

TWO_LINKS = """
[[effects]]
type = "chain"
masses = [1.0, 1.0]
lengths = [1.0, 1.0]
[[effects]]
type = "gravity"
{extra}
[initial]
polar_deg = 90.0
azimuth_deg = [0.0, 90.0]
[simulate]
t1 = 1.0
{simulate}
"""


def _file(tmp_path, extra="", simulate="", replace=None, template=TWO_LINKS):
    text = template.format(extra=extra, simulate=simulate)
    for old, new in (replace or {}).items():
        assert old in text
        text = text.replace(old, new)
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


RIGID_SCENE = """
[[effects]]
type = "rigid_base"
mass = 0.5
inertia = [0.00557, 0.00557, 0.0105]
attach = [0.0, 0.0, -0.05]
[[effects]]
type = "chain"
masses = 0.02
lengths = 0.2
links = 3
[[effects]]
type = "gravity"
{extra}
[initial]
polar_deg = 170.0
azimuth_deg = 0.0
attitude = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
angular_velocity = [0.1, 0.2, 0.3]
[simulate]
t1 = 0.5
{simulate}
"""


TORQUE = '[[effects]]\ntype = "body_torque"\ntorque = {}'
M2, L2 = "masses = [1.0, 1.0]", "lengths = [1.0, 1.0]"
CART_BASE = lambda: sm.Base(1.0, axes=[[1.0, 0.0, 0.0]])  # noqa: E731
CART_CHAIN = sm.Chain(0.5, 0.8)
TAU_TOML = '[[effects]]\ntype = "{}"\n{}'
CASES = {  # name: (Python, what the file changes, the field the file error names)
    "negative mass": (
        lambda: sm.Chain([1.0, -1.0], [1.0, 1.0]),
        dict(replace={M2: "masses = [1.0, -1.0]"}),
        "effects[0].masses",
    ),
    "zero length": (
        lambda: sm.Chain([1.0, 1.0], [1.0, 0.0]),
        dict(replace={L2: "lengths = [1.0, 0.0]"}),
        "effects[0].lengths",
    ),
    "negative g": (lambda: sm.Gravity(-1.0), dict(extra="g = -1.0"), "effects[1].g"),
    "link out of range": (
        lambda: sm.Scene(TWO, sm.Gravity(), sm.BaseTorque(TAU, link=7)),
        dict(extra=TAU_TOML.format("base_torque", "torque = [0.0, 0.0, 1.0]\nlink = 7")),
        "effects[2].link",
    ),
    "point out of range": (
        lambda: sm.Scene(TWO, sm.Gravity(), sm.TipForce(TAU, point=-3)),
        dict(extra=TAU_TOML.format("tip_force", "force = [0.0, 0.0, 1.0]\npoint = -3")),
        "effects[2].point",
    ),
    "spring end out of range": (
        lambda: sm.Scene(TWO, sm.Gravity(), sm.Spring(0, 2, 1.0)),
        dict(extra=TAU_TOML.format("spring", "a = 0\nb = 2\nstiffness = 1.0")),
        "effects[2].b",
    ),
    "pd gain": (
        lambda: sm.BaseTorque(sm.PDTorque(-1.0)),
        dict(extra=TAU_TOML.format("base_torque", 'torque = { type = "pd_torque", kp = -1.0 }')),
        "effects[2].torque.kp",
    ),
    "non-unit target": (
        lambda: sm.PDTorque(1.0, target=[0.0, 0.0, 2.0]),
        dict(
            extra=TAU_TOML.format(
                "base_torque", 'torque = { type = "pd_torque", kp = 1.0, target = [0.0, 0.0, 2.0] }'
            )
        ),
        "effects[2].torque.target",
    ),
    "negative base mass": (
        lambda: sm.Base(mass=-1.0),
        dict(template=CART_SCENE, replace={"mass = 1.0": "mass = -1.0"}),
        "effects[0].mass",
    ),
    "non-orthonormal axes": (
        lambda: sm.Base(1.0, axes=[[1.0, 0.0, 0.0], [0.6, 0.7, 0.0]]),
        dict(
            template=CART_SCENE,
            replace={"axes = [[1.0, 0.0, 0.0]]": "axes = [[1.0, 0.0, 0.0], [0.6, 0.7, 0.0]]"},
        ),
        "effects[0].axes",
    ),
    "base force without a base": (
        lambda: sm.Scene(TWO, sm.Gravity(), sm.BaseForce([1.0])),
        dict(extra=TAU_TOML.format("base_force", "force = [1.0]")),
        "effects[2]",
    ),
    "base with two chains": (
        lambda: sm.Scene(CART_BASE(), CART_CHAIN, CART_CHAIN),
        dict(template=CART_SCENE, extra=TAU_TOML.format("chain", "masses = 0.5\nlengths = 0.8")),
        "effects[0]",
    ),
    "two bases": (
        lambda: sm.Scene(CART_BASE(), CART_BASE(), CART_CHAIN),
        dict(
            template=CART_SCENE,
            extra=TAU_TOML.format("base", "mass = 1.0\naxes = [[1.0, 0.0, 0.0]]"),
        ),
        "effects",
    ),
    "base force of the wrong size": (
        lambda: sm.Scene(CART_BASE(), CART_CHAIN, sm.BaseForce([1.0, 0.0])),
        dict(template=CART_SCENE, extra=TAU_TOML.format("base_force", "force = [1.0, 0.0]")),
        "effects[2].force",
    ),
    "pd target of the wrong size": (
        lambda: sm.Scene(
            CART_BASE(), CART_CHAIN, sm.BaseForce(sm.PDPosition(1.0, target=[0.0, 0.0]))
        ),
        dict(
            template=CART_SCENE,
            extra=TAU_TOML.format(
                "base_force", 'force = { type = "pd_position", kp = 1.0, target = [0.0, 0.0] }'
            ),
        ),
        "effects[2].force.target",
    ),
    "harmonic force of the wrong size": (
        lambda: sm.Scene(CART_BASE(), CART_CHAIN, sm.BaseForce(sm.Harmonic([1.0, 0.0], 2.0))),
        dict(
            template=CART_SCENE,
            extra=TAU_TOML.format(
                "base_force",
                'force = { type = "harmonic", amplitude = [1.0, 0.0], angular_frequency = 2.0 }',
            ),
        ),
        "effects[2].force",
    ),
    "inertia off the triangle inequality": (
        lambda: sm.RigidBase(0.5, [0.001, 0.001, 0.0105]),
        dict(
            template=RIGID_SCENE,
            replace={"inertia = [0.00557, 0.00557, 0.0105]": "inertia = [0.001, 0.001, 0.0105]"},
        ),
        "effects[0].inertia",
    ),
    "body torque without a rigid base": (
        lambda: sm.Scene(sm.Chain(1.0, 1.0, links=2), sm.Gravity(), sm.BodyTorque([0.0, 0.0, 1.0])),
        dict(extra=TORQUE.format("[0.0, 0.0, 1.0]")),
        "effects[2]",
    ),
    "no effects": (lambda: sm.Scene(), dict(template="effects = []\n{extra}{simulate}"), "effects"),
    # the file's own words before: "expected an integer or a number or ...", "an array of
    # integers", "invalid literal for int()"
    "a spring end neither an index nor a point": (
        lambda: sm.Spring(True, 0, 1.0),
        dict(extra=TAU_TOML.format("spring", "a = true\nb = 0\nstiffness = 1.0")),
        "effects[2].a",
    ),
    "pair interaction masses not a sequence": (
        lambda: sm.PairInteraction(1.0, masses=True),
        dict(extra=TAU_TOML.format("pair_interaction", "strength = 1.0\nmasses = true")),
        "effects[2].masses",
    ),
    "a flight command as a body torque": (
        lambda: sm.BodyTorque(sm.Hover()),
        dict(template=RIGID_SCENE, extra=TORQUE.format('{ type = "hover" }')),
        "effects[3].torque",
    ),
    "a drive as a flight command": (
        lambda: sm.GeometricControl(
            0.5, [0.00557, 0.00557, 0.0105], 4.0, 2.8, 0.5, 0.1, command=sm.PDTorque(1.0)
        ),
        dict(
            template=RIGID_SCENE,
            extra=TAU_TOML.format(
                "rotors",
                'arm = 0.17\ntorque_coefficient = 0.01\ncommand = { type = "geometric_control", '
                "mass = 0.5, inertia = [0.00557, 0.00557, 0.0105], kx = 4.0, kv = 2.8, kR = 0.5, "
                'kOmega = 0.1, command = { type = "pd_torque", kp = 1.0 } }',
            ),
        ),
        "effects[3].command.command",
    ),
    "pair interaction masses not indices": (
        lambda: sm.Scene(TWO, sm.PairInteraction(1.0, masses=("a", "b"))),
        dict(extra=TAU_TOML.format("pair_interaction", 'strength = 1.0\nmasses = ["a", "b"]')),
        "effects[2].masses",
    ),
    "negative pd gain": (
        lambda: sm.PDPosition(-1.0),
        dict(
            template=CART_SCENE,
            extra=TAU_TOML.format("base_force", 'force = { type = "pd_position", kp = -1.0 }'),
        ),
        "effects[2].force.kp",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_python_and_files_reject_with_the_same_words(case, tmp_path):
    build, change, field = CASES[case]
    with pytest.raises(ValueError) as python:
        build()
    path = _file(tmp_path, **change)
    with pytest.raises(sm.SceneFileError) as file:
        sm.load_scene(path)
    assert str(file.value) == f"{path}: {field}: {python.value}"


BASE_INITIAL = {  # name: (template, replacements, field, what the error says)
    "too many base coordinates": (
        CART_SCENE,
        {"base = [0.0]": "base = [0.0, 1.0]"},
        "initial.base",
        "the base's coordinates (m), one per axis of the Base: "
        "1 number (at most 1e+100 in magnitude), got [0.0, 1.0]",
    ),
    "base velocity not an array": (
        CART_SCENE,
        {"base = [0.0]": "base_velocity = 1.0"},
        "initial.base_velocity",
        "the base's velocity (m/s), one "
        "per axis of the Base: 1 number (at most 1e+100 in "
        "magnitude), got 1.0",
    ),
    "base without a Base": (
        TWO_LINKS,
        {"azimuth_deg = [0.0, 90.0]": "azimuth_deg = [0.0, 90.0]\nbase = [0.0]"},
        "initial.base",
        "no such field (expected q and qdot, or "
        "polar_deg and azimuth_deg with optional rates (base: the scene "
        "has no Base))",
    ),
}


@pytest.mark.parametrize("case", list(BASE_INITIAL))
def test_base_initial_state_errors(case, tmp_path):
    template, replace, field, expected = BASE_INITIAL[case]
    path = _file(tmp_path, replace=replace, template=template)
    with pytest.raises(sm.SceneFileError) as file:
        sm.load_scene(path)
    assert str(file.value) == f"{path}: {field}: {expected}"


def test_files_broadcast_scalars_like_python(tmp_path):
    spec = sm.load_scene(
        _file(tmp_path, replace={M2: "masses = 0.5\nlinks = 2", L2: "lengths = 0.25"})
    )
    assert bool(eqx.tree_equal(spec.scene.kinetic[0], sm.Chain([0.5, 0.5], [0.25, 0.25])))
    q, _ = spec.y0
    np.testing.assert_allclose(q, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], atol=1e-15)
    with pytest.raises(
        sm.SceneFileError,
        match=r"effects\[0\]\.masses: masses must be a "
        r"scalar or 3 values",
    ):
        sm.load_scene(
            _file(tmp_path, replace={M2: "masses = [1.0, 1.0]\nlinks = 3", L2: "lengths = 1.0"})
        )


def test_file_pd_torque_builds_the_python_controller(tmp_path):
    extra = TAU_TOML.format(
        "base_torque",
        'torque = { type = "pd_torque", kp = 2.0, kd = 0.5, target = [1.0, 0.0, 0.0] }\nlink = 1',
    )
    spec = sm.load_scene(_file(tmp_path, extra=extra))
    expected = sm.BaseTorque(sm.PDTorque(2.0, 0.5, [1.0, 0.0, 0.0]), link=1)
    assert bool(eqx.tree_equal(spec.scene.force_effects[0], expected))


SPELLINGS = {
    "Projected(Tsit5)": sm.Projected(diffrax.Tsit5()),
    "Projected(Kvaerno5)": sm.Projected(diffrax.Kvaerno5()),
    "Projected(RK4)": sm.Projected(sm.RK4()),
    "Projected(Projected(Dopri5))": sm.Projected(sm.Projected(diffrax.Dopri5())),
    "Tsit5": diffrax.Tsit5(),
    "RK4": sm.RK4(),
    "LieRK4": sm.LieRK4(),
    "LieRK(Tsit5)": sm.LieRK(diffrax.Tsit5()),
    "LieRK(RK4, action='SO3xR3')": sm.LieRK(sm.RK4(), action="SO3xR3"),
    "LieRK( Dopri8 , error='algebra', action='SE3')": sm.LieRK(diffrax.Dopri8(), error="algebra"),
    "Variational": sm.Variational(),
    "Variational(order=4)": sm.Variational(order=4),
    " Variational( order = 2 ) ": sm.Variational(order=2),
}


@pytest.mark.parametrize("spelling", list(SPELLINGS))
def test_solver_spellings_build_the_python_solver(spelling, tmp_path):
    fixed = not isinstance(SPELLINGS[spelling], diffrax.AbstractAdaptiveSolver)
    extra = "dt0 = 0.01" if fixed else "rtol = 1e-6"
    spec = sm.load_scene(_file(tmp_path, simulate=f'solver = "{spelling}"\n{extra}'))
    assert type(spec.solver) is type(SPELLINGS[spelling])
    assert bool(eqx.tree_equal(spec.solver, SPELLINGS[spelling]))


@pytest.mark.parametrize(
    "spelling",
    [
        "tsit5",
        "rk4",
        "Projected()",
        "Projected(Tsit5",
        "Variational(order=3)",
        "KenCarp3",
        "RK4(1)",
        "__import__('os')",
        "Projected(Tsit5) + 1",
        "LieRK(Kvaerno5)",
        "LieRK(Tsit5, action='SO3')",
        "LieRK(Tsit5, order=2)",
        "LieRK()",
    ],
)
def test_bad_solver_spellings_are_rejected(spelling, tmp_path):
    with pytest.raises(sm.SceneFileError, match=r"simulate\.solver: "):
        sm.load_scene(_file(tmp_path, simulate=f'solver = "{spelling}"'))


def test_fixed_step_solvers_need_dt0_only(tmp_path, getkey):
    """The scene file refuses what `simulate` refuses, with simulate's words."""
    chain, y0 = sm.chain_pendulum([1.0], [1.0]), sm.random_state(getkey(), 1)
    cases = [
        ('solver = "Projected(RK4)"', dict(solver=sm.Projected(sm.RK4()))),
        (
            'solver = "Variational"\ndt0 = 0.01\nrtol = 1e-6',
            dict(solver=sm.Variational(), dt0=0.01, rtol=1e-6),
        ),
    ]
    for text, kwargs in cases:
        with pytest.raises(ValueError) as python:
            sm.simulate(chain, y0, 1.0, **kwargs)
        assert "fixed steps" in str(python.value)
        with pytest.raises(sm.SceneFileError) as file:
            sm.load_scene(_file(tmp_path, simulate=text))
        assert str(file.value).endswith(f"simulate: {python.value}")


def test_simulate_keys_are_the_python_names(tmp_path):
    spec = sm.load_scene(_file(tmp_path, simulate="t0 = 0.5\ndt0 = 1e-3\nmax_steps = 7"))
    assert (spec.t0, spec.t1, spec.dt0, spec.max_steps) == (0.5, 1.0, 1e-3, 7)
    assert spec.solver_name == "Projected(Tsit5)" and spec.rtol is None
    assert spec.save_dt == pytest.approx(0.5 / 1000)
    for old in ('method = "tsit5"', "dt = 0.1", "duration = 1.0"):
        with pytest.raises(sm.SceneFileError, match=r"simulate\.\w+: no such field"):
            sm.load_scene(_file(tmp_path, simulate=old))


def test_parameters_out_of_range_are_refused_in_python_as_in_files():
    """The effects' own checks (scene files reach the same ones): every floating
    parameter finite and at most 1e100 in magnitude, counts from 1 to 100 000 named as
    the argument (checked before anything is allocated), and float32 parameters checked
    without overflow warnings."""
    import warnings

    with pytest.raises(
        ValueError,
        match=r"^masses must be finite and at most 1e\+100 in "
        r"magnitude, got 1e\+308$",
    ):
        sm.chain_pendulum([1.0, 1e308], [1.0, 1.0])
    with pytest.raises(ValueError, match=r"^kp must be finite .* got nan$"):
        sm.PDTorque(kp=float("nan"))
    for links in (-2, 2**63 - 1):
        with pytest.raises(
            ValueError,
            match=rf"^links must be an integer from 1 to 100000, "
            rf"got {links}$",
        ):
            sm.Chain(1.0, 1.0, links=links)
    with pytest.raises(ValueError, match="^count must be an integer from 1 to 100000"):
        sm.Particles(1.0, 1.0, count=10**9)
    with pytest.raises(
        ValueError,
        match=r"^PairInteraction sums over at most 1e\+07 pairs, "
        r"got 5000 masses \(1.25e\+07 pairs\)$",
    ):
        sm.Scene(sm.SharedSphere(1.0, count=5000), sm.PairInteraction(1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        chain = sm.Chain(jnp.full(2, 1e30, jnp.float32), jnp.ones(2, jnp.float32))
    assert chain.masses.dtype == jnp.float32


def test_values_beyond_float32_without_x64_name_the_overflow(tmp_path):
    """With x64 off, a finite parameter or initial value beyond float32's range is refused
    as such, in Python as in files (before: cast to inf first, then reported as "got inf"
    or as "contains NaN or infinite values")."""
    words = r"must be at most 3.4e\+38 in magnitude in float32 \(enable float64: .*\), got 1e\+50$"
    replace = {"angular_velocity = [0.1,": "angular_velocity = [1e50,"}
    path = _file(tmp_path, template=RIGID_SCENE, replace=replace)
    with jax.enable_x64(False):
        with pytest.raises(ValueError, match="^masses " + words):
            sm.chain_pendulum([1e50, 1.0], [1.0, 1.0])
        field = r"initial\.angular_velocity: angular_velocity "
        with pytest.raises(sm.SceneFileError, match=field + words):
            sm.load_scene(path)


def test_file_attitude_not_finite_or_not_a_rotation_in_simulates_words(tmp_path):
    """`[initial] attitude`: NaN, inf or 1e200 entries are refused in simulate's words (the
    file said it expected 3 rows of 3 numbers, which they were); a misshapen one by its
    shape."""
    good = "attitude = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]"
    for entry, words in (
        ("nan", "the attitude contains NaN or infinite values. Got [[nan"),
        ("inf", "the attitude contains NaN or infinite values. Got [[inf"),
        ("1e200", "the attitude is not a rotation: some R^T R differs from I"),
        ("0.0]]  #", "the body's rotation matrix (body to world), 3 rows of 3 numbers, got"),
    ):
        bad = good.replace("[[1.0", f"[[{entry}")  # the last: [[0.0]], the rest a comment
        path = _file(tmp_path, template=RIGID_SCENE, replace={good: bad})
        with pytest.raises(sm.SceneFileError) as file:
            sm.load_scene(path)
        assert str(file.value).startswith(f"{path}: initial.attitude: {words}")


def test_file_initial_values_not_finite_in_simulates_words(tmp_path):
    """`[initial]` NaN or inf entries are refused in simulate's words, naming the key (the
    file said it expected unit vectors, angles within [0, 180] or at most 1e+06 in
    magnitude, which they were not asked to be)."""
    for old, new, key, got in (
        ("polar_deg = 170.0", "polar_deg = nan", "polar_deg", "nan"),
        ("polar_deg = 170.0\nazimuth_deg = 0.0", "q = [0.0, 0.0, inf]", "q", "[0.0, 0.0, inf]"),
        ("angular_velocity = [0.1,", "angular_velocity = [nan,", "angular_velocity", "[nan, 0.2"),
    ):
        path = _file(tmp_path, template=RIGID_SCENE, replace={old: new})
        with pytest.raises(sm.SceneFileError) as file:
            sm.load_scene(path)
        message = f"{path}: initial.{key}: {key} contains NaN or infinite values. Got {got}"
        assert str(file.value).startswith(message)
    # the same words as simulate's, which names q
    spec = sm.load_scene(_file(tmp_path))
    q, qdot = spec.y0
    with pytest.raises(ValueError, match=r"q contains NaN or infinite values\.$"):
        sm.simulate(spec.scene, (q.at[0, 0].set(jnp.inf), qdot), 0.1)
