"""The one solve core: `simulate` and `simulate_batch` give the same codes and raise the
same messages; Python floats do not recompile; `MechanicsTerm` with diffrax directly."""

import diffrax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import SOLVER_IDS, SOLVERS

import sphere_mech as sm

Q0 = sm.normalize(jnp.array([[1.0, 0.0, -1.0], [0.0, 1.0, -0.5]]))
V0 = sm.project(Q0, jnp.array([[0.0, 1.5, 0.0], [1.5, 0.0, 0.3]]))
FIXED = dict(solver=sm.Projected(sm.RK4()), dt0=0.05)
TRACES = {"count": 0}


def pendulum(t, q, qdot, g):
    """A double pendulum; `g` is the `args`. Counts its traces (once per compilation of
    every function that evaluates it)."""
    TRACES["count"] += 1
    x1, x2 = q[0], q[0] + 0.8 * q[1]
    v1, v2 = qdot[0], qdot[0] + 0.8 * qdot[1]
    return 0.5 * (v1 @ v1 + v2 @ v2) - g * (x1[2] + x2[2])


def height(t, q, g):
    """A potential, `g` times the summed heights; `g` is the `args`. Counts its traces."""
    TRACES["count"] += 1
    return g * jnp.sum(q[:, 2])


SYSTEM = sm.Lagrangian(pendulum)
DEGENERATE = sm.Lagrangian(lambda t, q, qdot, g: 0.5 * jnp.sum(qdot[0] ** 2) - g * q[1, 2])


def batch(y, size=2):
    return tuple(jnp.broadcast_to(x, (size,) + x.shape) for x in y)


@pytest.mark.parametrize(
    "case, code",
    [("max_steps", sm.RESULTS.max_steps_reached), ("initial", sm.RESULTS.nonfinite_initial)],
)
def test_throw_means_the_same_in_both_entry_points(case, code):
    system, kwargs = (SYSTEM, dict(max_steps=3)) if case == "max_steps" else (DEGENERATE, {})
    kwargs.update(args=9.81, **FIXED)
    one = sm.simulate(system, (Q0, V0), 1.0, throw=False, **kwargs)
    many = sm.simulate_batch(system, batch((Q0, V0)), 1.0, throw=False, batch_args=False, **kwargs)
    assert one.result == code
    assert np.all(np.asarray(many.result == code))
    with pytest.raises(RuntimeError) as single:
        sm.simulate(system, (Q0, V0), 1.0, **kwargs)
    with pytest.raises(RuntimeError) as batched:
        sm.simulate_batch(system, batch((Q0, V0)), 1.0, batch_args=False, **kwargs)
    message = str(single.value).removeprefix("simulate: ")
    assert sm.RESULTS[code] in message
    assert str(batched.value).startswith("simulate_batch: 2 of 2 trajectories failed")
    assert str(batched.value).endswith(message)


def test_new_float_args_compile_once():
    sm.simulate(SYSTEM, (Q0, V0), 1.0, args=0.5)
    before = TRACES["count"]
    sol = sm.simulate(SYSTEM, (Q0, V0), 1.0, args=0.6)
    assert TRACES["count"] == before  # no new trace: no new compilation
    reference = sm.simulate(SYSTEM, (Q0, V0), 1.0, args=jnp.asarray(0.6))
    np.testing.assert_array_equal(sol.ys[0], reference.ys[0])
    system = sm.ConstantInertiaLagrangian(jnp.eye(2), height)
    before = TRACES["count"]
    sm.simulate_batch(system, batch((Q0, V0)), 1.0, args=0.5, batch_args=False)
    assert TRACES["count"] > before  # the counter sees simulate_batch's traces
    before = TRACES["count"]
    sm.simulate_batch(system, batch((Q0, V0)), 1.0, args=0.7, batch_args=False)
    assert TRACES["count"] == before  # no new trace: no new compilation


# order 4 (slow: 20 s) passes `args` and the term through the same code as order 2
@pytest.mark.parametrize("order", [2, pytest.param(4, marks=pytest.mark.slow)])
def test_variational_through_diffeqsolve_with_user_args(order):
    solver = sm.Variational(order)
    ours = sm.simulate(SYSTEM, (Q0, V0), 1.0, args=jnp.asarray(9.81), solver=solver, dt0=0.1)
    theirs = diffrax.diffeqsolve(
        sm.MechanicsTerm(SYSTEM), solver, 0.0, 1.0, 0.1, (Q0, V0), args=jnp.asarray(9.81)
    )
    for a, b in zip(ours.ys, theirs.ys, strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)  # rounding
    with pytest.raises(ValueError, match="MechanicsTerm"):
        diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, a: SYSTEM.rates(t, y, a)),
            solver,
            0.0,
            1.0,
            0.1,
            (Q0, V0),
            args=jnp.asarray(9.81),
        )


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
def test_every_solver_family_reaches_the_reference(solver):
    """Each family (`helpers.SOLVERS`) integrates the same double pendulum through
    `simulate` with fixed steps to a Dopri8 reference at tight tolerances: within its
    order's error (order 4 for the Runge-Kutta families, 2 for `Variational`, at dt =
    1e-3 over 0.5 s), on the spheres to rounding, at the save times between the ends
    too."""
    chain = sm.chain_pendulum([1.0, 0.6], [1.0, 0.8])
    q0 = sm.normalize(jnp.array([[1.0, 0.2, -1.0], [0.6, -0.4, -1.0]]))
    v0 = sm.project(q0, jnp.array([[0.0, 1.0, 0.0], [0.5, 0.0, 0.3]]))
    saveat = diffrax.SaveAt(ts=jnp.linspace(0.1, 0.5, 5))
    ref = sm.simulate(
        chain,
        (q0, v0),
        0.5,
        solver=sm.Projected(diffrax.Dopri8()),
        rtol=1e-13,
        atol=1e-13,
        saveat=saveat,
    )
    fixed = diffrax.ConstantStepSize()  # LieRK4 would adapt from dt0 without it
    sol = sm.simulate(
        chain, (q0, v0), 0.5, solver=solver, dt0=1e-3, stepsize_controller=fixed, saveat=saveat
    )
    assert int(sol.stats["num_steps"]) == 500
    # measured: 6.6e-12 and 7.1e-12 (Projected(RK4), LieRK4), 1.9e-6 (Variational)
    tolerance = 1e-5 if isinstance(solver, sm.Variational) else 1e-10
    np.testing.assert_allclose(sol.ys[0], ref.ys[0], rtol=0, atol=tolerance)
    np.testing.assert_allclose(sol.ys[1], ref.ys[1], rtol=0, atol=10 * tolerance)
    assert float(sm.constraint_error(sol.ys[0])) < 1e-13
