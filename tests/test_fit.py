"""Gradients through `simulate` and parameter fitting with `fit`."""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np
import optimistix as optx
import pytest
from helpers import SIM, DampedChain, central_differences, chain_initial_states, max_rel_error

import sphere_mech as sm

# ----------------------------------------------------------------------------------------
# Gradients through simulate.

P0 = jnp.array([1.0, 0.5, 1.0, 0.7, 9.81])  # m1, m2, l1, l2, g
TOL = dict(rtol=1e-12, atol=1e-12)


def _quantity(p, y0, adjoint, solver=None, dt0=None, tol=TOL):
    """A weighted sum of the tip position after 1 s."""
    chain = sm.chain_pendulum(p[:2], p[2:4], p[4])
    sol = sm.simulate(chain, y0, 1.0, adjoint=adjoint, solver=solver, dt0=dt0, **tol)
    return jnp.dot(chain.positions(sol.ys[0][-1])[-1], jnp.array([1.0, 2.0, 3.0]))


@pytest.fixture(scope="module")
def adaptive():
    """Value, reverse-mode gradient and forward-mode Jacobian with adaptive steps, each
    vmapped over three initial conditions (compiled once for the module)."""
    rev = lambda p, y: _quantity(p, y, diffrax.RecursiveCheckpointAdjoint())
    fwd = lambda p, y: _quantity(p, y, diffrax.ForwardMode())
    batch = lambda f: eqx.filter_jit(jax.vmap(f, in_axes=(None, 0)))
    return batch(rev), batch(jax.grad(rev)), batch(jax.jacfwd(fwd)), chain_initial_states(3)


def test_gradient_adaptive_matches_finite_differences(adaptive):
    value, grad, _, y0 = adaptive
    fd = central_differences(lambda p: value(p, y0), P0, 1e-5)
    g = grad(P0, y0)
    assert g.shape == (3, 5)
    assert max_rel_error(g, fd) < 1e-6
    # vmap changes nothing: each row is the gradient of its own initial condition
    assert not np.allclose(g[0], g[1], rtol=1e-3)


def test_forward_mode_matches_reverse_mode(adaptive):
    _, grad, jacfwd, y0 = adaptive
    assert max_rel_error(jacfwd(P0, y0), grad(P0, y0)) < 1e-10


def test_gradient_fixed_steps_and_initial_state():
    """RK4 with fixed steps: gradient with respect to the parameters and a directional
    derivative with respect to the initial velocity, against finite differences."""
    y0 = jax.tree.map(lambda x: x[0], chain_initial_states(1))
    kw = dict(solver=sm.Projected(sm.RK4()), dt0=0.01, tol={})

    @eqx.filter_jit
    def f(p, v0):
        return _quantity(p, (y0[0], v0), diffrax.RecursiveCheckpointAdjoint(), **kw)

    g_p, g_v = jax.jit(jax.grad(f, argnums=(0, 1)))(P0, y0[1])
    assert max_rel_error(g_p, central_differences(lambda p: f(p, y0[1]), P0, 1e-5)) < 1e-6
    direction = sm.project(y0[0], jnp.array([[0.3, -0.2, 0.5], [0.1, 0.4, -0.2]]))
    eps = 1e-5
    fd = (f(P0, y0[1] + eps * direction) - f(P0, y0[1] - eps * direction)) / (2 * eps)
    assert abs(jnp.sum(g_v * direction) - fd) < 1e-6 * abs(fd)


# ----------------------------------------------------------------------------------------
# Fitting a damped double spherical pendulum.


def damped_chain(p):
    masses = jnp.stack([jnp.ones_like(p["ratio"]), p["ratio"]])
    lengths = jnp.stack([p["l1"], p["l2"]])
    return DampedChain(sm.chain_pendulum(masses, lengths, 9.81), p["c"])


def mass_positions(system, t, q, v):
    """The observation: positions of both masses (the tips of the two links)."""
    return system.chain.positions(q)


TRUE = dict(ratio=jnp.array(0.5), l1=jnp.array(1.0), l2=jnp.array(0.7), c=jnp.array(0.1))
START = {k: 1.3 * v for k, v in TRUE.items()}


def _record(y0, t1, num, key, truth=TRUE, noise=1e-3):
    """Noisy observed positions (noise 1e-3 of the first link's length)."""
    ts = jnp.linspace(0.0, t1, num)
    system = damped_chain(truth)
    sol = sm.simulate(system, y0, t1, saveat=diffrax.SaveAt(ts=ts), rtol=1e-10, atol=1e-12)
    x = jax.vmap(system.chain.positions)(sol.ys[0])
    return ts, x + noise * truth["l1"] * jr.normal(key, x.shape)


def _states_from_data(ts, x):
    """Rough states from observed positions: link directions, finite-difference rates."""
    q = sm.normalize(jnp.concatenate([x[:, :1], x[:, 1:] - x[:, :-1]], 1))
    return sm.retract(q, jnp.gradient(q, ts, axis=0))


def _rel_errors(params, truth=TRUE):
    return {k: abs(float(params[k] / truth[k]) - 1.0) for k in truth}


def test_fit_recovers_parameters(getkey):
    y0 = jax.tree.map(lambda x: x[0], chain_initial_states(1))
    ts, obs = _record(y0, 5.0, 51, getkey())
    result = sm.fit(
        damped_chain, START, ts, obs, mass_positions, y0=y0, positive=True, simulate_options=SIM
    )
    assert bool(result.converged)
    assert result.result == optx.RESULTS.successful
    assert 0 < int(result.num_steps) < 100
    assert max(_rel_errors(result.params).values()) < 0.01, result.params
    assert result.loss < 1e-3 * result.initial_loss
    # the losses are those of the fitted and the initial parameters, computed here anew
    assert np.isclose(result.loss, _loss(result.params, y0, ts, obs), rtol=1e-8)
    assert np.isclose(result.initial_loss, _loss(START, y0, ts, obs), rtol=1e-8)


@eqx.filter_jit
def _loss(params, y0, ts, obs):
    system = damped_chain(params)
    sol = sm.simulate(system, y0, ts[-1], saveat=diffrax.SaveAt(ts=ts), **SIM)
    return 0.5 * jnp.sum((jax.vmap(system.chain.positions)(sol.ys[0]) - obs) ** 2)


# A chaotic record: the lightly damped double pendulum thrown hard from above the
# horizontal (nearby trajectories separate by 1e7 in 8 s).
TRUE_CHAOS = dict(TRUE, c=jnp.array(0.01))
START_CHAOS = {k: 1.3 * v for k, v in TRUE_CHAOS.items()}
Q_CHAOS = sm.normalize(jnp.array([[1.0, 0.0, 0.3], [0.0, 1.0, 0.5]]))
V_CHAOS = sm.project(Q_CHAOS, jnp.array([[0.0, 10.0, 0.0], [5.0, 0.0, 10.0]]))


def _shooting(t1, segments, key, single_steps=30):
    ts, obs = _record((Q_CHAOS, V_CHAOS), t1, int(20 * t1) + 1, key, TRUE_CHAOS)
    q, v = _states_from_data(ts, obs)
    bounds = np.round(np.linspace(0, len(ts) - 1, segments + 1)).astype(int)
    fit = functools.partial(
        sm.fit,
        damped_chain,
        START_CHAOS,
        ts,
        obs,
        mass_positions,
        y0=(q[0], v[0]),
        positive=True,
        fit_initial_state=True,
        simulate_options=SIM,
    )
    multiple = fit(
        segments=segments, segment_states=(q[bounds[1:-1]], v[bounds[1:-1]]), max_steps=60
    )
    single = fit(max_steps=single_steps)
    return multiple, single


def _check_shooting(multiple, single):
    assert bool(multiple.converged)
    assert max(_rel_errors(multiple.params, TRUE_CHAOS).values()) < 0.01, multiple.params
    # single shooting from the same start stalls in a local minimum far from the truth
    assert max(_rel_errors(single.params, TRUE_CHAOS).values()) > 0.05, single.params
    assert single.loss > 100 * multiple.loss


@pytest.mark.slow  # 72 s; multiple shooting stays in test_fit_models and test_mixed
def test_multiple_shooting_chaotic(getkey):
    multiple, single = _shooting(8.0, 16, getkey(), single_steps=12)
    _check_shooting(multiple, single)
    assert multiple.loss < 1e-5 * multiple.initial_loss
    # single shooting is still far off when it runs out of steps: reported, not raised
    assert not bool(single.converged)
    assert single.result == optx.RESULTS.nonlinear_max_steps_reached


@pytest.mark.slow
def test_multiple_shooting_chaotic_20s(getkey):
    _check_shooting(*_shooting(20.0, 40, getkey()))


def test_fit_errors():
    y0 = jax.tree.map(lambda x: x[0], chain_initial_states(1))
    ts = jnp.linspace(0.0, 1.0, 11)
    obs = jnp.zeros((11, 2, 3))
    with pytest.raises(ValueError, match="observations must have shape"):
        sm.fit(damped_chain, START, ts, obs[:5], mass_positions, y0=y0)
    with pytest.raises(ValueError, match="observe"):
        sm.fit(damped_chain, START, ts, obs, lambda s, t, q, v: q[0], y0=y0)
    with pytest.raises(ValueError, match="y0"):
        sm.fit(damped_chain, START, ts, obs, mass_positions, y0=y0[0])
    with pytest.raises(ValueError, match="segments"):
        sm.fit(damped_chain, START, ts, obs, mass_positions, y0=y0, segments=11)
    with pytest.raises(ValueError, match="positive"):
        sm.fit(damped_chain, dict(START, c=-1.0), ts, obs, mass_positions, y0=y0, positive=True)
    two_segments = lambda states: sm.fit(
        damped_chain, START, ts, obs, mass_positions, y0=y0, segments=2, segment_states=states
    )
    with pytest.raises(ValueError, match="segment_states"):
        two_segments((y0[0], y0[1]))
    with pytest.raises(ValueError, match="model"):
        sm.fit(lambda p: p, START, ts, obs, mass_positions, y0=y0)
    with pytest.raises(TypeError, match="Gauss-Newton-type"):
        best = optx.BestSoFarLeastSquares(optx.LevenbergMarquardt(rtol=1e-6, atol=1e-9))
        sm.fit(damped_chain, START, ts, obs, mass_positions, y0=y0, solver=best)
    with pytest.raises(ValueError, match="max_steps must be a positive integer"):
        sm.fit(damped_chain, START, ts, obs, mass_positions, y0=y0, max_steps=0)
    # simulate's check and words, before tracing (before: diffrax's runtime error after
    # compiling the fit, its times traced)
    backwards = dict(solver=sm.Projected(sm.RK4()), dt0=-0.05)
    with pytest.raises(ValueError, match=r"^dt0 must have the sign of t1 - t0"):
        sm.fit(damped_chain, START, ts, obs, mass_positions, y0=y0, simulate_options=backwards)
    with pytest.raises(ValueError, match=r"^rtol must be a real number \(got '1e-6'\)$"):
        sm.fit(
            damped_chain, START, ts, obs, mass_positions, y0=y0, simulate_options={"rtol": "1e-6"}
        )
    for continuity in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="continuity must be a finite number > 0"):
            sm.fit(damped_chain, START, ts, obs, mass_positions, y0=y0, continuity=continuity)
    short = lambda s, t, q, v: mass_positions(s, t, q, v)[:-1]
    with pytest.raises(ValueError, match=r"observe\(system, t, q, v\) returns \(1, 3\) but each"):
        sm.fit(damped_chain, START, ts, obs, short, y0=y0)
    as_dict = lambda s, t, q, v: {"x": mass_positions(s, t, q, v)}
    with pytest.raises(ValueError, match=r"observe\(system, t, q, v\) returns dict but"):
        sm.fit(damped_chain, START, ts, obs, as_dict, y0=y0)
    nan_observe = lambda s, t, q, v: mass_positions(s, t, q, v) * jnp.nan
    with pytest.raises(ValueError, match="observe.* is NaN or infinite at the first record"):
        sm.fit(damped_chain, START, ts, obs, nan_observe, y0=y0)
    # the data, before any solve: y0 as simulate_batch checks it, observations finite
    with pytest.raises(ValueError, match=r"^fit: q is not on the spheres"):
        sm.fit(damped_chain, START, ts, obs, mass_positions, y0=(2 * y0[0], y0[1]))
    nan = obs.at[4, 1, 2].set(jnp.nan)
    with pytest.raises(ValueError, match=r"^fit: observation 4 is NaN or infinite"):
        sm.fit(damped_chain, START, ts, nan, mass_positions, y0=y0)
    batch = jax.tree.map(lambda x: jnp.stack([x, x, x]), y0)
    message = r"^fit: 1 of 3 records have a non-finite observation \(indices 2\); record 2: "
    with pytest.raises(ValueError, match=message + "observation 4 is NaN"):
        sm.fit(damped_chain, START, ts, jnp.stack([obs, obs, nan]), mass_positions, y0=batch)
    # the starting point: parameters and segment states finite (a NaN one returned loss 0.0)
    with pytest.raises(ValueError, match=r"^fit: params0\['c'\] is not finite: nan"):
        sm.fit(damped_chain, dict(START, c=jnp.nan), ts, obs, mass_positions, y0=y0)
    nan_states = (y0[0][None].at[0, 1, 2].set(jnp.nan), y0[1][None])
    with pytest.raises(ValueError, match=r"^fit: segment_states: q contains NaN or infinite"):
        two_segments(nan_states)
    # the times: finite and strictly increasing (in each record's row)
    with pytest.raises(ValueError, match=r"^fit: ts must be finite and strictly increasing"):
        sm.fit(damped_chain, START, ts.at[3].set(ts[2]), obs, mass_positions, y0=y0)
    rows = jnp.stack([ts, ts.at[1].set(jnp.nan), ts])
    message = r"^fit: 1 of 3 records have times that are not finite and increasing \(indices 1\)"
    with pytest.raises(ValueError, match=message):
        sm.fit(damped_chain, START, rows, jnp.stack([obs] * 3), mass_positions, y0=batch)


def test_shooting_segment_end_is_inf_where_the_solve_stops_early():
    """A segment's end state (the solve's own, not an interpolated save) is the state at
    `t1` when the solve gets there and `inf` when it stops before (here `max_steps`), as
    are the observation times it does not reach: a continuity jump never hides a failure.
    Each observation time holds its state or `inf`, never the state where the solve
    stopped (which diffrax saves into the first unreached slot: before, `learn` and
    `refine` trained on it as if it were the state at that time)."""
    from sphere_mech._fit.shooting import simulate_at

    system = sm.ConstantInertiaLagrangian(jnp.eye(1), lambda t, q, a: 9.81 * q[0, 2])
    q0 = sm.normalize(jnp.array([[1.0, 0.0, -1.0]]))
    y0 = (q0, jnp.array([[0.0, 1.0, 0.0]]))
    ts = jnp.array([0.1, 0.5])
    sim = dict(solver=sm.Projected(diffrax.Dopri5()), rtol=1e-10, atol=1e-10)
    (q, v), (q1, v1) = simulate_at(system, None, y0, 0.0, 1.0, ts, sim)
    full = sm.simulate(system, y0, 1.0, saveat=diffrax.SaveAt(ts=jnp.array([1.0])), **sim)
    np.testing.assert_allclose(q1, full.ys[0][0], rtol=1e-12, atol=1e-14)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(v))
    reference = sm.simulate(system, y0, 1.0, saveat=diffrax.SaveAt(ts=ts), **sim).ys
    for max_steps in (3, 6):
        (q, v), (q1, v1) = simulate_at(
            system, None, y0, 0.0, 1.0, ts, dict(sim, max_steps=max_steps)
        )
        assert np.all(np.isinf(q1)) and np.all(np.isinf(v1)) and np.all(np.isinf(q[1]))
        reached = np.all(np.isfinite(q[0]))
        assert not reached or np.allclose(q[0], reference[0][0], rtol=1e-12, atol=1e-14)
        assert not reached or np.allclose(v[0], reference[1][0], rtol=1e-10, atol=1e-12)
