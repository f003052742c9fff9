"""LieRK's dense output between steps: as accurate as its steps (within a small factor)
for Dopri5, Tsit5 and Dopri8 against an independent scipy solve; exactly on the tangent
bundle for both actions, on (S^2)^n and on a mixed space; continuous at the steps; event
times located on it as accurately as with Projected(Dopri8); jit, vmap and grad."""

import importlib.util
import sys
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import ellipk

import sphere_mech as sm

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "dense_output.py"
_SPEC = importlib.util.spec_from_file_location("dense_output_benchmark", _PATH)
bench = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = bench
_SPEC.loader.exec_module(bench)

T1 = 1.5
TS = jnp.linspace(0.0, T1, 61)
TOL = 1e-9


@pytest.fixture(scope="module")
def reference():
    return bench.reference()


def _pendulum_state():
    return tuple(jnp.asarray(x)[None] for x in bench.initial_state())


def _stacked(sol_ys):
    """`(q, qdot)` of a one-sphere solution as rows of 6 numbers."""
    return np.concatenate([np.asarray(sol_ys[0])[:, 0], np.asarray(sol_ys[1])[:, 0]], 1)


@pytest.mark.parametrize(
    "inner, factor",
    [(diffrax.Dopri5(), 3), (diffrax.Tsit5(), 6), (diffrax.Dopri8(), 20)],
    ids=["Dopri5", "Tsit5", "Dopri8"],
)
def test_between_steps_as_accurate_as_at_steps(reference, inner, factor):
    """The largest error at `SaveAt(ts)` (61 times, nearly all between steps) is within a
    small factor of the largest error at the steps: 3 for Dopri5, 6 for Tsit5 (its
    interpolant is of order 4), 20 for Dopri8,
    whose diffrax interpolant is of lower order than its steps (the same factor, 17, for
    `Projected(Dopri8)`: benchmarks/dense_output.py). The cubic Hermite it replaces was
    130x off for Dopri5, 1200x for Tsit5 and 3e5x for Dopri8 at this tolerance."""
    saveat = diffrax.SaveAt(subs=[diffrax.SubSaveAt(steps=True), diffrax.SubSaveAt(ts=TS)])
    sol = sm.simulate(
        bench.PENDULUM,
        _pendulum_state(),
        T1,
        solver=sm.LieRK(inner),
        rtol=TOL,
        atol=TOL,
        saveat=saveat,
    )
    steps_t, ts = (np.asarray(t) for t in sol.ts)
    keep = np.isfinite(steps_t)
    at_steps = np.max(np.abs(_stacked(sol.ys[0])[keep] - reference(steps_t[keep])))
    at_ts = np.max(np.abs(_stacked(sol.ys[1]) - reference(ts)))
    gaps = np.min(np.abs(ts[:, None] - steps_t[keep][None]), axis=1)
    assert np.mean(gaps > 1e-3) > 0.5  # the saved times are mostly between steps
    assert at_steps < 100 * TOL
    assert at_ts < factor * at_steps, (at_ts, at_steps)


def cart_lagrangian(t, q, qdot, args):
    """A cart on a line carrying a pendulum: a mixed space R x S^2."""
    xd, p, pd = qdot["cart"][0], q["bob"][0], qdot["bob"][0]
    bob_v = jnp.array([xd, 0.0, 0.0]) + 0.8 * pd
    return 0.5 * 1.5 * xd**2 + 0.5 * 0.7 * bob_v @ bob_v - 0.7 * 9.81 * 0.8 * p[2]


CART = sm.Lagrangian(cart_lagrangian, space={"cart": sm.Euclidean(1), "bob": sm.Spheres(1)})
CART_Y0 = (
    {"cart": jnp.zeros(1), "bob": sm.normalize(jnp.array([[1.0, 0.3, -1.0]]))},
    {"cart": jnp.array([0.3]), "bob": jnp.array([[0.0, 1.2, 0.36]])},
)
CHAIN = sm.chain_pendulum(jnp.array([1.0, 1.5]), jnp.array([1.0, 0.8]))
CHAIN_Y0 = sm.random_state(jax.random.PRNGKey(3), 2, speed=1.0)


@pytest.mark.parametrize("action", ["SE3", "SO3xR3"])
@pytest.mark.parametrize(
    "system, y0, inner",
    [
        (CHAIN, CHAIN_Y0, diffrax.Tsit5()),
        (CART, CART_Y0, diffrax.Tsit5()),
        (CHAIN, CHAIN_Y0, diffrax.Heun()),
    ],
    ids=["spheres", "mixed", "spheres-Heun"],
)
def test_dense_points_on_tangent_bundle_and_continuous(system, y0, inner, action):
    """Straight from `diffrax.diffeqsolve` (no retraction by `simulate`): every dense
    point has `|q_i| = 1` and `q_i . v_i = 0` to rounding, and the dense output equals
    the steps' end points at the steps (from the left and from the right). A loose
    tolerance, so the steps are long. Heun (not first-same-as-last) takes the cubic
    Hermite in the algebra."""
    solver = sm.LieRK(inner, action=action)
    sol = diffrax.diffeqsolve(
        sm.MechanicsTerm(system),
        solver,
        0.0,
        2.0,
        0.05,
        y0,
        stepsize_controller=diffrax.PIDController(rtol=1e-4, atol=1e-4),
        saveat=diffrax.SaveAt(steps=True, dense=True),
    )
    n = int(sol.stats["num_accepted_steps"])
    steps = np.asarray(sol.ts)[:n]
    q, v = jax.jit(jax.vmap(sol.evaluate))(jnp.linspace(0.0, 2.0, 201))
    spheres = lambda tree: tree["bob"] if isinstance(tree, dict) else tree
    q_s, v_s = spheres(q), spheres(v)
    assert float(jnp.max(jnp.abs(jnp.linalg.norm(q_s, axis=-1) - 1))) < 1e-14
    assert float(jnp.max(jnp.abs(jnp.sum(q_s * v_s, -1)))) < 1e-13
    for left in (True, False):
        dense = jax.vmap(lambda t, left=left: sol.evaluate(t, left=left))(jnp.asarray(steps))
        for a, b in zip(jax.tree.leaves(dense), jax.tree.leaves(sol.ys), strict=True):
            np.testing.assert_allclose(a, np.asarray(b)[:n], rtol=0, atol=1e-13)


def test_saved_states_retracted_in_any_tree_of_subs():
    """`simulate` and `simulate_batch` put the states saved by every `SubSaveAt` back on
    the tangent bundle whatever PyTree holds them (a dict, a list in a dict; before, only a
    bare one, a list or a tuple: a dict's were 3e-7 off the spheres here), leave a custom
    `fn`'s output alone, and return the same states as a plain `SaveAt(ts=...)`."""
    ts = jnp.linspace(0.1, 1.9, 7) + 0.0123  # between the (long) steps
    saveat = diffrax.SaveAt(
        subs={
            "a": diffrax.SubSaveAt(ts=ts),
            "b": [diffrax.SubSaveAt(t1=True), diffrax.SubSaveAt(ts=ts, fn=lambda t, y, a: y[0])],
        }
    )
    kw = dict(rtol=1e-6, atol=1e-6)
    plain = sm.simulate(CHAIN, CHAIN_Y0, 2.0, saveat=diffrax.SaveAt(ts=ts), **kw).ys
    single = sm.simulate(CHAIN, CHAIN_Y0, 2.0, saveat=saveat, **kw).ys
    batched = sm.simulate_batch(
        CHAIN, jax.tree.map(lambda x: x[None], CHAIN_Y0), 2.0, saveat=saveat, **kw
    ).ys
    for ys in (single, jax.tree.map(lambda x: x[0], batched)):
        for q, v in (ys["a"], ys["b"][0]):
            assert float(sm.constraint_error(q)) < 1e-14
            assert float(jnp.max(jnp.abs(jnp.sum(q * v, axis=-1)))) < 1e-14
        for a, b in zip(ys["a"], plain, strict=True):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)  # other programs: rounding
        raw = ys["b"][1]  # the solver's own states: off the spheres by the local error
        assert 1e-10 < float(sm.constraint_error(raw)) < 1e-4


def test_event_time_with_lierk_dopri8():
    """A planar release at 1 rad crosses the vertical after a quarter period,
    `sqrt(l/g) K(sin^2(1/2))`: located on LieRK(Dopri8)'s dense output at tol 1e-8 within
    1e-8 s (it was 7e-5 s off with the cubic Hermite)."""
    exact = np.sqrt(bench.LENGTH / bench.G) * ellipk(np.sin(0.5) ** 2)
    assert abs(bench.event_time(sm.LieRK(diffrax.Dopri8())) - exact) < 1e-8


def test_jit_vmap_grad_through_dense_output():
    """`d q(t)/d q0` at a time between steps, through LieRK(Tsit5)'s dense output, vmapped
    over two initial speeds, against central differences."""
    q0 = _pendulum_state()[0]

    def q_at(speed):
        v0 = sm.project(q0, jnp.array([[0.0, speed, 0.0]]))
        sol = sm.simulate(
            bench.PENDULUM,
            (q0, v0),
            0.7,
            solver=sm.LieRK(diffrax.Tsit5()),
            rtol=1e-10,
            atol=1e-10,
            saveat=diffrax.SaveAt(ts=jnp.array([0.55])),
        )
        return sol.ys[0][0, 0, 0]

    speeds = jnp.array([1.0, 2.0])
    grads = jax.jit(jax.vmap(jax.grad(q_at)))(speeds)
    eps = 1e-5
    fd = (jax.vmap(q_at)(speeds + eps) - jax.vmap(q_at)(speeds - eps)) / (2 * eps)
    np.testing.assert_allclose(grads, fd, rtol=1e-6, atol=1e-8)


def test_simulate_with_dense_output_only():
    """`simulate` with `SaveAt(dense=True)` and nothing else to save (it raised "Need at
    least one array to stack"): `sol.evaluate` gives LieRK's dense points, the values
    that `SaveAt(ts)` saves at the same times, on the spheres."""
    kwargs = dict(solver=sm.LieRK(diffrax.Tsit5()), rtol=1e-9, atol=1e-9)
    dense = sm.simulate(
        bench.PENDULUM, _pendulum_state(), 0.7, saveat=diffrax.SaveAt(dense=True), **kwargs
    )
    saved = sm.simulate(
        bench.PENDULUM, _pendulum_state(), 0.7, saveat=diffrax.SaveAt(ts=TS[:20]), **kwargs
    )
    assert dense.result == sm.RESULTS.successful
    q, v = jax.jit(jax.vmap(dense.evaluate))(TS[:20])
    np.testing.assert_allclose(q, saved.ys[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(v, saved.ys[1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(jnp.linalg.norm(q, axis=-1), 1.0, rtol=0, atol=1e-14)
