"""Events: `simulate` and `simulate_batch` stop where a `diffrax.Event` fires; periods of a
spherical pendulum located by events against their closed forms."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from scipy.special import ellipk

import sphere_mech as sm

G, LENGTH = 9.81, 0.7
PENDULUM = sm.chain_pendulum([1.0], [LENGTH], G)
TOL = dict(rtol=1e-12, atol=1e-12)
NEWTON = optx.Newton(rtol=1e-13, atol=1e-13)


def crossing(axis):
    """An event: the mass crosses the plane `x_axis = 0` downward."""
    return diffrax.Event(
        lambda t, y, args, **kw: y[0][0, axis], root_finder=NEWTON, direction=False
    )


def planar(theta0):
    q = jnp.array([[jnp.sin(theta0), 0.0, -jnp.cos(theta0)]])
    return q, jnp.zeros_like(q)


def quarter_period(theta0):
    """Released at rest at angle `theta0`: a quarter period, `sqrt(l/g) K(sin^2(theta0/2))`."""
    return np.sqrt(LENGTH / G) * ellipk(np.sin(theta0 / 2) ** 2)


@pytest.mark.parametrize("theta0", [0.05, 1.0])
def test_planar_period(theta0):
    sol = sm.simulate(PENDULUM, planar(theta0), 10.0, event=crossing(0), **TOL)
    assert sol.result == sm.RESULTS.event_occurred
    t = float(sol.ts[-1])
    assert abs(t / quarter_period(theta0) - 1) < 1e-9
    if theta0 < 0.1:  # small oscillations: 2 pi sqrt(l/g) (1 + theta0^2/16 + ...)
        assert abs(4 * t / (2 * np.pi * np.sqrt(LENGTH / G)) - 1) < theta0**2 / 16 * 1.01
    np.testing.assert_allclose(sol.ys[0][-1, 0, 0], 0.0, atol=1e-12)  # on the plane


def test_conical_orbit_period():
    """At polar angle `alpha` from the downward vertical with rate `Omega`,
    `Omega^2 = g / (l cos alpha)`: the mass comes back to the plane y = 0 after pi / Omega."""
    alpha = 0.6
    omega = np.sqrt(G / (LENGTH * np.cos(alpha)))
    q = jnp.array([[np.sin(alpha), 0.0, -np.cos(alpha)]])
    qdot = omega * jnp.cross(jnp.array([0.0, 0.0, 1.0]), q)
    sol = sm.simulate(PENDULUM, (q, qdot), 10.0, event=crossing(1), **TOL)
    assert abs(float(sol.ts[-1]) * omega / np.pi - 1) < 1e-9
    np.testing.assert_allclose(sol.ys[0][-1, 0, 2], -np.cos(alpha), atol=1e-10)  # stays


def test_batch_of_periods_and_saved_states():
    """Every trajectory stops at its own event; saves past it are `inf`; no error. With
    `ts` and `t1=True` in one `SubSaveAt`, the stop state follows the last save time
    reached (as `simulate`'s docs say), not at the end."""
    thetas = jnp.linspace(0.2, 2.0, 4)
    y0 = jax.vmap(planar)(thetas)
    ts = jnp.linspace(0.0, 2.0, 41)
    subs = [diffrax.SubSaveAt(ts=ts), diffrax.SubSaveAt(t1=True), diffrax.SubSaveAt(ts=ts, t1=True)]
    saveat = diffrax.SaveAt(subs=subs)
    sol = sm.simulate_batch(
        PENDULUM, y0, 2.0, event=crossing(0), batch_args=False, saveat=saveat, **TOL
    )
    assert np.all(np.asarray(sol.result == sm.RESULTS.event_occurred))
    expected = np.array([quarter_period(float(th)) for th in thetas])
    t_event = np.asarray(sol.ts[1])[:, 0]
    np.testing.assert_allclose(t_event, expected, rtol=1e-9)
    q = np.asarray(sol.ys[0][0])
    for k, t in enumerate(t_event):
        assert np.all(np.isfinite(q[k][np.asarray(ts) < t]))
        assert np.all(np.isinf(q[k][np.asarray(ts) > t]))
        reached = int(np.sum(np.asarray(ts) <= t))
        assert float(sol.ts[2][k, reached]) == t
        np.testing.assert_array_equal(sol.ys[2][0][k, reached], sol.ys[1][0][k, 0])
        assert np.all(np.isinf(np.asarray(sol.ys[2][0][k, reached + 1 :])))


def test_wrong_number_of_spheres_names_both_sizes(getkey):
    chain = sm.chain_pendulum([1.0, 1.0], [1.0, 1.0])
    q, v = sm.random_state(getkey(), 3)
    message = r"the state has 3 spheres but the system has 2: q must have shape \(2, 3\)"
    with pytest.raises(ValueError, match=message):
        sm.simulate(chain, (q, v), 1.0)
    with pytest.raises(ValueError, match=message):
        chain.acceleration(0.0, q, v)
    with pytest.raises(ValueError, match=message):
        sm.simulate_batch(chain, (q[None], v[None]), 1.0, batch_args=False)
    fast = sm.ConstantInertiaLagrangian(jnp.eye(2), lambda t, q, args: jnp.sum(q[:, 2]))
    with pytest.raises(ValueError, match=message):
        sm.simulate(fast, (q, v), 1.0)


def test_root_finder_failure_is_named():
    """An event whose root finder cannot converge (a cube root defeats Newton) gets its
    own code and message, not the implicit step's, and no max_steps in it."""
    q0 = jnp.array([[jnp.sin(0.5), 0.0, -jnp.cos(0.5)]])
    cross = diffrax.Event(
        lambda t, y, args, **kw: jnp.cbrt(y[0][0, 0]),
        root_finder=optx.Newton(rtol=1e-13, atol=1e-13),
    )
    system = sm.chain_pendulum([1.0], [0.7])
    sol = sm.simulate(system, (q0, jnp.zeros_like(q0)), 10.0, event=cross, throw=False)
    assert bool(sol.result == sm.RESULTS.event_root_failed)
    # Told apart by whether the event fired, not by the solver's class: the same event
    # under an implicit step, and an implicit step (Variational's Newton, 3 iterations at
    # most) failing with an event that never fires.
    implicit = sm.Projected(diffrax.Kvaerno5())
    sol = sm.simulate(
        system, (q0, jnp.zeros_like(q0)), 1.0, event=cross, solver=implicit, throw=False
    )
    assert bool(sol.result == sm.RESULTS.event_root_failed)
    never = diffrax.Event(lambda t, y, args, **kw: y[0][0, 2] - 5.0, root_finder=NEWTON)
    fast = jnp.array([[0.0, 8.0, 0.0]])
    q1 = jnp.array([[jnp.sin(2.5), 0.0, -jnp.cos(2.5)]])
    variational = dict(solver=sm.Variational(root_find_max_steps=3), dt0=0.3, throw=False)
    sol = sm.simulate(system, (q1, fast), 3.0, event=never, **variational)
    assert bool(sol.result == sm.RESULTS.nonlinear_max_steps_reached)
    with pytest.raises(
        RuntimeError,
        match=r"^simulate: The root finder of `event` did not "
        r"converge.* \(with throw=False nothing is raised",
    ):
        sm.simulate(system, (q0, jnp.zeros_like(q0)), 10.0, event=cross)


def test_nan_state_is_nonfinite_not_an_event():
    """Fixed steps accept a NaN step. A NaN state "fired" an event (the sign of NaN differs
    from any) and fed its root finder (lineax's `nonfinite_input`, at a NaN time): both are
    `nonfinite`, the event not fired, nothing NaN saved (`inf`)."""
    height = lambda t, q, qdot, args: 9.81 * jnp.sum(q[:, 2]) - jnp.sqrt(0.5 - q[0, 2])
    system = sm.Lagrangian(
        lambda t, q, qdot, args: 0.5 * jnp.sum(qdot**2) - height(t, q, qdot, args)
    )
    y0 = (jnp.array([[0.0, 0.0, -1.0]]), jnp.array([[6.0, 0.0, 0.0]]))  # NaN once z > 0.5
    never = lambda t, y, args, **kw: y[0][0, 1] - 5.0
    fixed = dict(solver=sm.Projected(sm.RK4()), dt0=0.01, throw=False)
    for event in (diffrax.Event(never), diffrax.Event(never, root_finder=NEWTON)):
        sol = sm.simulate(system, y0, 1.0, event=event, **fixed)
        assert sol.result == sm.RESULTS.nonfinite
        assert not bool(sol.event_mask)
        assert np.all(np.isinf(np.asarray(sol.ts))) and np.all(np.isinf(np.asarray(sol.ys[0])))


def test_backward_event_sees_the_physical_time():
    """diffrax integrates in -t backwards and passed that to the condition: an event at
    t = -0.2 never fired. Events as a pytree of conditions too; the event time reported."""
    at = lambda time: lambda t, y, args, **kw: t - time
    sol = sm.simulate(PENDULUM, planar(1.0), -1.0, event=diffrax.Event(at(-0.2), NEWTON))
    assert sol.result == sm.RESULTS.event_occurred
    np.testing.assert_allclose(sol.ts, [-0.2], rtol=1e-12)
    tree = diffrax.Event({"late": at(-0.5), "early": at(-0.3)}, root_finder=NEWTON)
    sol = sm.simulate(PENDULUM, planar(1.0), -1.0, event=tree)
    np.testing.assert_allclose(sol.ts, [-0.3], rtol=1e-12)
    assert bool(sol.event_mask["early"]) and not bool(sol.event_mask["late"])


def test_float32_state_with_root_finder_under_x64():
    """diffrax's root find puts the condition beside a float64 `0.0` under x64: a float32
    condition raised a TypeError. The state and times stay float32."""
    q = planar(1.0)[0].astype(jnp.float32)
    event = diffrax.Event(lambda t, y, args, **kw: y[0][0, 0], optx.Newton(1e-5, 1e-5))
    sol = sm.simulate(PENDULUM, (q, jnp.zeros_like(q)), 1.0, event=event)
    assert sol.result == sm.RESULTS.event_occurred
    assert sol.ys[0].dtype == sol.ts.dtype == jnp.float32
    np.testing.assert_allclose(sol.ts, [quarter_period(1.0)], rtol=1e-4)


def test_boolean_condition_float32_with_root_finder_under_x64():
    """A boolean condition fires at the end of its step, root finder or not: a float32
    state under x64 raised diffrax's TypeError (its root find mixed float32 times with a
    float64 `0.0`). With a float condition beside it the error names the problem."""
    q = planar(1.0)[0].astype(jnp.float32)
    y0 = (q, jnp.zeros_like(q))
    below = lambda t, y, args, **kw: y[0][0, 2] < -0.9  # released at z = -cos(1) = -0.54
    runs = [
        sm.simulate(PENDULUM, y0, 1.0, event=diffrax.Event(below, finder))
        for finder in (optx.Newton(1e-5, 1e-5), None)
    ]
    assert runs[0].result == sm.RESULTS.event_occurred
    assert runs[0].ts.dtype == jnp.float32
    np.testing.assert_array_equal(runs[0].ts, runs[1].ts)
    # the end of the step that crossed z = -0.9, before the bottom
    assert float(runs[0].ys[0][0, 0, 2]) < -0.9
    assert 0 < float(runs[0].ts[0]) < quarter_period(1.0)
    # a condition's parameters may have other names: called positionally, as diffrax's
    # steps call it (its root find names them t, y, args: `_PhysicalCondition` does not)
    renamed = diffrax.Event(lambda time, state, params, **kw: state[0][0, 2] < -0.9)
    np.testing.assert_array_equal(sm.simulate(PENDULUM, y0, 1.0, event=renamed).ts, runs[1].ts)
    both = {"bool": below, "float": lambda t, y, args, **kw: y[0][0, 0]}
    with pytest.raises(ValueError, match=r"^event: boolean and float conditions .* float32"):
        sm.simulate(PENDULUM, y0, 1.0, event=diffrax.Event(both, optx.Newton(1e-5, 1e-5)))


def test_condition_nan_at_a_finite_state_is_a_root_failure():
    """A condition undefined past its root (NaN at a finite state) was lineax's
    `nonfinite_input` at a NaN time: the root finder's failure, no NaN saved."""
    root = lambda t, y, args, **kw: jnp.sqrt(y[0][0, 0]) - 0.1
    event = diffrax.Event(root, root_finder=NEWTON)
    sol = sm.simulate(PENDULUM, planar(1.0), 1.0, event=event, throw=False)
    assert sol.result == sm.RESULTS.event_root_failed
    assert bool(sol.event_mask)  # it fired; its time was not found
    assert not np.any(np.isnan(np.asarray(sol.ts))) and not np.any(np.isnan(sol.ys[0]))
