"""Scenes with a `Base`: a cart, a trolley or a drone carrying a chain, on the O(n) fast
path of R^m x (S^2)^n (state keys "base" and "spheres"), against the general path, the
Cartesian reference of `test_mixed` (helpers.py), the dense variational step and finite differences;
the fit of a payload mass and a cable's damping."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    T1,
    TIGHT,
    G,
    cart_pendulum,
    exact_observations,
    flying_chain,
    jaxpr_equations,
    mixed_initial_state,
)

import sphere_mech as sm
from sphere_mech._solvers.discrete_mechanics import substep


def base_scene(model, forced, *extra):
    """The model as a `Scene`: a `Base` moving along the columns of `E`, a `Chain`
    hanging from it, gravity and the model's drive as a `BaseForce`."""
    effects = [
        sm.Base(model.M, axes=np.asarray(model.E).T),
        sm.Chain(model.masses, model.lengths),
        sm.Gravity(G),
        *extra,
    ]
    if forced:
        effects.append(sm.BaseForce(lambda t, q, qdot, args: model.drive(t)))
    return sm.Scene(*effects)


def as_scene_state(y):
    return {"base": y["base"], "spheres": y["chain"]}


def general_twin(scene):
    """The same energies and forces through the general path (Hessians of `L`)."""
    lagrangian = lambda t, q, qdot, args: scene.kinetic_energy(q, qdot) - scene.potential(t, q)
    return sm.Lagrangian(lagrangian, scene.forces, space=scene.space)


DENSE_PRIMITIVES = {"lu", "cholesky", "triangular_solve", "lu_pivots_to_permutation"}


@pytest.mark.parametrize(
    "axes",
    [[[1.0, 0.0, 0.0]], [[0.6, 0.8, 0.0], [0.0, 0.0, 1.0]], np.eye(3)],
    ids=["line", "plane", "space"],
)
def test_base_scene_fast_path_equals_general_path(axes):
    """A cart (line), a trolley (tilted plane) and a drone (space) carrying a 3-link chain
    with a payload, with every force on bases and chains: the O(n) fast path gives the
    general path's rates (to 1e-12) and inverse Legendre map, with no dense solve."""
    m = len(axes)
    target = np.linspace(0.2, -0.3, m)
    scene = sm.Scene(
        sm.Base(1.3, axes=axes, position=(0.0, 0.1, 0.2)),
        sm.Chain([0.2, 0.3, 0.4], [0.5, 0.7, 0.6], base=(0.1, 0.0, 0.0), payload=0.25),
        sm.Gravity(G),
        sm.JointDamping(0.1),
        sm.Bending(0.3),
        sm.TipForce([0.0, 1.0, 0.5]),
        sm.BaseTorque(sm.Harmonic([0.0, 0.0, 1.0], 2.0)),
        sm.BaseForce(
            sm.PDPosition(20.0, 8.0, target=target, feedforward=2.0, step=0.5, step_time=0.2)
        ),
    )
    assert scene.space == sm.chain_space(m, 3)
    assert scene.space.factors == {"base": sm.Euclidean(m), "spheres": sm.Spheres(3)}
    k = jax.random.split(jax.random.PRNGKey(m), 4)
    s = sm.normalize(jax.random.normal(k[1], (3, 3)))
    q = {"base": jax.random.normal(k[0], (m,)), "spheres": s}
    v = {
        "base": jax.random.normal(k[2], (m,)),
        "spheres": sm.project(s, jax.random.normal(k[3], (3, 3))),
    }
    twin = general_twin(scene)
    for t in (0.1, 0.3):  # before and after the controller's step
        fast, general = scene.rates(t, (q, v), None), twin.rates(t, (q, v), None)
        assert max_abs_diff(fast, general) < 1e-12
    p = scene.momentum(0.3, q, v)
    assert max_abs_diff(scene.velocity_from_momentum(0.3, q, p)[0], v) < 1e-13
    two = {"base": q["base"], "spheres": s[:2]}
    with pytest.raises(ValueError, match="the state has 2 spheres but the system has 3"):
        scene.acceleration(0.0, two, {"base": v["base"], "spheres": v["spheres"][:2]})
    assert abs(float(scene.energy(0.3, q, v) - twin.energy(0.3, q, v))) < 1e-12
    eqns = jaxpr_equations(jax.make_jaxpr(lambda y: scene.rates(0.3, y, None))((q, v)).jaxpr)
    assert not DENSE_PRIMITIVES & {e.primitive.name for e in eqns}


def max_abs_diff(a, b):
    return max(
        float(jnp.max(jnp.abs(x - y)))
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    )


@pytest.mark.parametrize("make", [cart_pendulum, flying_chain])
def test_base_scene_against_cartesian_reference(make):
    """The scenes of the driven cart pendulum and of the (pushed) flying chain follow
    the Cartesian reference to 1e-8 over 2 s; without forces the energy is conserved."""
    model = make()
    scene = base_scene(model, forced=True)
    y0 = mixed_initial_state(model)
    sol = sm.simulate(scene, tuple(map(as_scene_state, y0)), T1, **TIGHT)
    x_ref, r_ref = model.reference(*y0, forced=True)
    q = sol.ys[0]
    assert np.max(np.abs(q["base"] - x_ref)) < 1e-8
    assert np.max(np.abs(jax.vmap(scene.positions)(q) - r_ref)) < 1e-8
    free = base_scene(model, forced=False)
    sol = sm.simulate(free, tuple(map(as_scene_state, y0)), T1, **TIGHT)
    energy = jax.vmap(lambda q, v: free.energy(0.0, q, v))(*sol.ys)
    assert np.max(np.abs(energy - energy[0])) < 1e-9 * (1 + abs(float(energy[0])))


DRONE_TS = np.linspace(0.0, 2.0, 21)


def drone_scene(params):
    """A drone (1.5 kg) flying a 1 m step along x at t = 0 under a PD controller, with a
    payload on a damped 5-link cable (as in examples/drone_cable.toml)."""
    weight = (1.5 + 5 * 0.02 + 0.3) * G
    return sm.Scene(
        sm.Base(1.5),
        sm.Chain(0.02, 0.2, links=5, payload=params["payload"]),
        sm.Gravity(G),
        sm.JointDamping(params["damping"]),
        sm.BaseForce(
            sm.PDPosition(
                20.0,
                8.0,
                feedforward=jnp.array([0.0, 0.0, weight]),
                step=jnp.array([1.0, 0.0, 0.0]),
            )
        ),
    )


def observe_drone(scene, t, q, v):
    """The drone's and the payload's positions."""
    return jnp.concatenate([q["base"], scene.positions(q)[-1]])


@pytest.mark.slow  # 59 s; notebook 06 fits the same two parameters on the same scene (3 s
# of noisy data), test_gradient_through_base_scene_matches_finite_differences checks the
# derivatives in them
def test_fit_recovers_payload_and_cable_damping():
    """`fit` recovers the payload mass and the cable's damping (both started 50 % off)
    from the drone's and the payload's positions over a 2 s step, noise-free (from a
    Dopri8 run at 1e-12; the model integrates with RK4 at dt = 0.01)."""
    truth = {"payload": 0.3, "damping": 0.01}
    tilt = sm.normalize(jnp.array([0.1, 0.05, -1.0]))
    y0 = (
        {"base": jnp.zeros(3), "spheres": jnp.tile(tilt, (5, 1))},
        {"base": jnp.zeros(3), "spheres": jnp.zeros((5, 3))},
    )
    obs = exact_observations(drone_scene(truth), y0, DRONE_TS, observe_drone)
    result = sm.fit(
        drone_scene,
        {"payload": 0.45, "damping": 0.015},
        DRONE_TS,
        obs,
        observe_drone,
        y0=y0,
        positive=True,
        simulate_options=dict(solver=sm.Projected(sm.RK4()), dt0=0.01),
    )
    assert bool(result.converged)
    for name, value in truth.items():
        assert abs(float(result.params[name]) / value - 1) < 1e-2, name


def test_variational_step_on_base_scene_fast_path():
    """`Variational` on a cart and on a drone carrying a 3-link chain: the O(n) chord
    iteration with the base in the multiplier solve takes the same step as the general
    Newton path (to 1e-10: both solve to the Newton tolerance, eps^0.75 relative)."""
    for axes in ([[1.0, 0.0, 0.0]], np.eye(3)):
        m = len(axes)
        scene = sm.Scene(
            sm.Base(1.2, axes=axes),
            sm.Chain([0.3, 0.2, 0.4], [0.5, 0.6, 0.4]),
            sm.Gravity(G),
            sm.JointDamping(0.05),
            sm.BaseForce(sm.Harmonic(jnp.ones(m), 2.0)),
        )
        q_s, v_s = sm.random_state(jax.random.PRNGKey(7), 3, speed=1.0)
        y = ({"base": jnp.zeros(m), "spheres": q_s}, {"base": jnp.ones(m), "spheres": v_s})
        t = jnp.asarray(0.1)
        steps = [
            substep(scene, t, 0.05, *y, scene.rates(t, y, None), None, 1e-12, 32, fast)
            for fast in (True, False)
        ]
        assert all(result == diffrax.RESULTS.successful for _, _, result in steps)
        assert max_abs_diff(steps[0][0], steps[1][0]) < 1e-10
        assert max_abs_diff(steps[0][0], y) > 1e-3  # it moved


def test_gradient_through_base_scene_matches_finite_differences():
    """Reverse mode through `simulate` on the drone scene (the fast path with a base):
    the gradient of the payload's final x with respect to the payload mass and the
    cable damping equals central differences."""
    tilt = sm.normalize(jnp.array([0.1, 0.05, -1.0]))
    y0 = (
        {"base": jnp.zeros(3), "spheres": jnp.tile(tilt, (5, 1))},
        {"base": jnp.zeros(3), "spheres": jnp.zeros((5, 3))},
    )

    def payload_x(p):
        scene = drone_scene({"payload": p[0], "damping": p[1]})
        sol = sm.simulate(
            scene,
            y0,
            0.5,
            solver=sm.Projected(sm.RK4()),
            dt0=0.01,
            adjoint=diffrax.RecursiveCheckpointAdjoint(),
        )
        return scene.positions(jax.tree.map(lambda x: x[-1], sol.ys[0]))[-1, 0]

    p = jnp.array([0.3, 0.01])
    grad = jax.grad(payload_x)(p)
    eps = 1e-6
    fd = [
        (payload_x(p.at[i].add(eps)) - payload_x(p.at[i].add(-eps))) / (2 * eps) for i in range(2)
    ]
    np.testing.assert_allclose(grad, np.array(fd), rtol=1e-6, atol=1e-10)
    assert np.min(np.abs(np.array(fd))) > 1e-4
