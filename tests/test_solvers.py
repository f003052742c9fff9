"""Integrators on (S^2)^n: orders measured from data, |q_i| = 1 over 10^5 steps (and the
drift without projection), adaptive steps of LieRK4 and of Projected, gradients, dense
output, clear errors."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import fitted_order, max_rel_error

import sphere_mech as sm

CHAIN = sm.chain_pendulum(jnp.array([1.0, 1.0]), jnp.array([1.0, 1.0]))
Q0 = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
V0 = jnp.array([[0.0, 0.5, 1.0], [0.0, 0.0, 2.0]])
T1 = 1.0
CONSTANT = diffrax.ConstantStepSize()
# One save of the final state, and |q|-error after every step (a scalar per step).
SAVEAT = diffrax.SaveAt(
    subs=[
        diffrax.SubSaveAt(t1=True),
        diffrax.SubSaveAt(steps=True, fn=lambda t, y, args: sm.constraint_error(y[0])),
    ]
)


@eqx.filter_jit
def fixed_run(solver, y0, dt, t1):
    """Fixed steps with `diffrax.diffeqsolve` directly (no retraction of the output), one
    compilation per solver: `dt` and `t1` are traced."""
    return diffrax.diffeqsolve(
        sm.MechanicsTerm(CHAIN),
        solver,
        0.0,
        t1,
        dt,
        y0,
        saveat=SAVEAT,
        stepsize_controller=CONSTANT,
        max_steps=100_000,
        throw=False,
    )


def final_state(sol):
    q, v = sol.ys[0]
    return q[-1], v[-1]


def max_constraint_error(sol):
    c = np.asarray(sol.ys[1])
    return float(np.max(c[np.isfinite(c)]))


@pytest.fixture(scope="module")
def reference():
    # Projected(Tsit5) at dt = 5e-4 is accurate to ~3e-15 here (order 5, measured below);
    # it reuses the compilation of the order test.
    sol = fixed_run(sm.Projected(diffrax.Tsit5()), (Q0, V0), jnp.asarray(5e-4), jnp.asarray(T1))
    return final_state(sol)


def _error(y, y_ref):
    return max(max_rel_error(a, b) for a, b in zip(y, y_ref, strict=True))


@pytest.mark.parametrize(
    "solver, order, dts",
    [
        (sm.Projected(sm.RK4()), 4, (0.02, 0.01, 0.005, 0.0025)),
        (sm.Projected(diffrax.Tsit5()), 5, (0.005, 0.0025, 0.00125)),
        (sm.LieRK4(), 4, (0.02, 0.01, 0.005, 0.0025)),
    ],
    ids=["Projected(RK4)", "Projected(Tsit5)", "LieRK4"],
)
def test_order_of_convergence(reference, solver, order, dts):
    errors = []
    for dt in dts:
        sol = fixed_run(solver, (Q0, V0), jnp.asarray(dt), jnp.asarray(T1))
        errors.append(_error(final_state(sol), reference))
    assert min(errors) > 1e-13  # still above the reference's own error (~3e-15)
    assert abs(fitted_order(dts, errors) - order) < 0.3, errors


@pytest.mark.parametrize(
    "solver", [sm.Projected(sm.RK4()), sm.LieRK4()], ids=["Projected(RK4)", "LieRK4"]
)
def test_unit_length_over_1e5_steps(solver):
    """`| |q_i| - 1 |` and `q_i . v_i` stay at rounding: `Projected` restores both every
    step; `LieRK4`'s SE(3) action keeps them in exact arithmetic, so its rounding errors
    walk (measured over the run: 2.0e-14 and 1.5e-13; plain RK4: 3.8e-9 after 10 s)."""
    sol = fixed_run(solver, (Q0, V0), jnp.asarray(1e-3), jnp.asarray(100.0))
    assert int(sol.stats["num_steps"]) == 100_000
    assert sol.result == diffrax.RESULTS.successful
    assert max_constraint_error(sol) < 1e-13
    q, v = final_state(sol)
    assert float(jnp.max(jnp.abs(jnp.sum(q * v, axis=-1)))) < 1e-12  # v stays tangent


def test_plain_rk4_drifts_off_the_spheres():
    # Without projection |q_i| - 1 grows (it is unstable under the extended vector
    # field): ~1e-9 after 5000 steps here; the benchmark follows it to 10^5 steps.
    sol = fixed_run(sm.RK4(), (Q0, V0), jnp.asarray(1e-3), jnp.asarray(5.0))
    assert max_constraint_error(sol) > 1e-10


@pytest.fixture(scope="module")
def tight_reference():
    sol = sm.simulate(
        CHAIN, (Q0, V0), T1, solver=sm.Projected(diffrax.Dopri8()), rtol=1e-13, atol=1e-13
    )
    return sol.ys[0][-1], sol.ys[1][-1]


@pytest.mark.parametrize(
    "solver", [sm.LieRK4(), sm.Projected(diffrax.Dopri8())], ids=["LieRK4", "Projected(Dopri8)"]
)
def test_adaptive_run_meets_tolerance(tight_reference, solver):
    ts = jnp.linspace(0.0, T1, 7)
    errors = []
    for tol in (1e-6, 1e-9):
        sol = sm.simulate(
            CHAIN,
            (Q0, V0),
            T1,
            solver=solver,
            rtol=jnp.asarray(tol),
            atol=jnp.asarray(tol),
            saveat=diffrax.SaveAt(ts=ts),
        )
        q, v = sol.ys
        errors.append(_error((q[-1], v[-1]), tight_reference))
        # The global error of this chaotic double pendulum after 1 s is within a small
        # factor of the tolerance (measured, relative: about 4x for LieRK4, 0.2x for
        # Projected(Dopri8)).
        assert errors[-1] < 10 * tol, (tol, errors)
        # Dense output (cubic Hermite for LieRK4), retracted by simulate.
        assert float(sm.constraint_error(q)) < 1e-14
        assert float(jnp.max(jnp.abs(jnp.sum(q * v, axis=-1)))) < 1e-13
        energy = jax.vmap(CHAIN.energy, (None, 0, 0))(0.0, q, v)
        assert float(jnp.max(jnp.abs(energy - energy[0]))) < 100 * tol
    assert errors[1] < 1e-2 * errors[0]  # tightening the tolerance pays


@pytest.mark.slow
@pytest.mark.parametrize(
    "inner", [diffrax.Dopri5(), diffrax.Kvaerno5()], ids=["Dopri5", "Kvaerno5"]
)
def test_projected_adaptive_other_solvers(tight_reference, inner):
    sol = sm.simulate(CHAIN, (Q0, V0), T1, solver=sm.Projected(inner), rtol=1e-9, atol=1e-9)
    assert _error((sol.ys[0][-1], sol.ys[1][-1]), tight_reference) < 50 * 1e-9


def test_lie_rk4_gradient_matches_finite_differences():
    """Reverse mode through LieRK4 (fixed steps, diffrax's checkpointed adjoint) against
    central differences of the same discrete map, along tangent directions of the
    initial state. One compilation: the differences reuse `value_and_grad`'s values."""
    dq = sm.project(Q0, jnp.array([[0.0, 0.3, -0.2], [0.5, 0.0, 0.1]]))
    dv = sm.project(Q0, jnp.array([[0.2, 0.0, 0.0], [0.0, -0.1, 0.4]]))

    @eqx.filter_jit
    @jax.value_and_grad
    def loss(y0):
        sol = diffrax.diffeqsolve(
            sm.MechanicsTerm(CHAIN),
            sm.LieRK4(),
            0.0,
            0.5,
            0.01,
            y0,
            stepsize_controller=CONSTANT,
            max_steps=64,
        )
        q, v = sol.ys
        return jnp.sum(q[-1, 1] * jnp.array([0.3, -1.0, 2.0])) + jnp.sum(v[-1] ** 2)

    _, (gq, gv) = loss((Q0, V0))
    eps = 1e-6
    for g, plus, minus in (
        (jnp.sum(gq * dq), (sm.normalize(Q0 + eps * dq), V0), (sm.normalize(Q0 - eps * dq), V0)),
        (jnp.sum(gv * dv), (Q0, V0 + eps * dv), (Q0, V0 - eps * dv)),
    ):
        fd = (loss(plus)[0] - loss(minus)[0]) / (2 * eps)
        assert abs(float(g) - float(fd)) < 1e-6 * abs(float(fd)), (g, fd)


def test_fixed_step_solver_refuses_adaptive_controller():
    """Named as scene files spell it: `Projected(RK4)`, not the wrapper alone."""
    with pytest.raises(ValueError, match=r"^Projected\(RK4\) has no error estimate"):
        sm.simulate(
            CHAIN,
            (Q0, V0),
            T1,
            solver=sm.Projected(sm.RK4()),
            stepsize_controller=diffrax.PIDController(rtol=1e-6, atol=1e-6),
            dt0=0.01,
        )
    with pytest.raises(ValueError, match="rtol/atol would be ignored"):
        sm.simulate(CHAIN, (Q0, V0), T1, solver=sm.RK4(), rtol=1e-6, dt0=0.01)
    with pytest.raises(ValueError, match=r"^Projected\(Projected\(RK4\)\) with fixed steps needs"):
        sm.simulate(CHAIN, (Q0, V0), T1, solver=sm.Projected(sm.Projected(sm.RK4())))


def test_lie_rk4_rejects_other_states_and_terms():
    """`LieRK4()` acts by SE(3), which needs the system (a `MechanicsTerm`); the SO(3) x
    R^3 action takes any term, but only states `(q, v)`."""
    term = diffrax.ODETerm(lambda t, y, args: -y)
    with pytest.raises(ValueError, match=r"MechanicsTerm"):
        diffrax.diffeqsolve(term, sm.LieRK4(), 0.0, 1.0, 0.1, (Q0, V0))
    with pytest.raises(ValueError, match=r"states y = \(q, v\)"):
        diffrax.diffeqsolve(term, sm.LieRK(sm.RK4(), action="SO3xR3"), 0.0, 1.0, 0.1, jnp.ones(3))
