"""Hard cases stay numerically stable.

Every case runs without NaN, keeps `max_i | |q_i| - 1 |` under 1e-12 at every step (read
from the solver's raw states, not from `simulate`'s retracted output), and agrees with an
independent reference (a tight-tolerance `Projected(Dopri8)` run, an exact solution, or a
planar pendulum in one angle) or a conservation law, to the tolerance stated at each
assertion. Where a case cannot be made stable the test pins down the error the user gets.
"""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sphere_mech as sm

G = 9.81
RTOL = 1e-10  # tolerance of the runs under test (Projected(Tsit5) unless stated)
REF_TOL = 1e-13  # tolerance of the references (same program, 1000 times tighter)
UNIT = 1e-12  # the bound on max | |q_i| - 1 |


def _step_constraint(t, y, args):
    return sm.constraint_error(y[0])


def run(system, y0, t1, *, solver=None, rtol=RTOL, n_save=101, max_steps=100_000):
    """Integrate; return the states at `n_save` times (retracted, as `simulate` returns
    them), the largest constraint error over every step of the raw solver state, and the
    solution (stats, result). Tolerances and `t1` are passed as arrays, so runs of one
    system at different tolerances share one compiled program."""
    ts = jnp.linspace(0.0, t1, n_save)
    saveat = diffrax.SaveAt(
        subs=[diffrax.SubSaveAt(steps=True, fn=_step_constraint), diffrax.SubSaveAt(ts=ts)]
    )
    tol = jnp.asarray(rtol)
    sol = sm.simulate(
        system,
        y0,
        jnp.asarray(t1),
        solver=solver,
        rtol=tol,
        atol=tol,
        saveat=saveat,
        max_steps=max_steps,
    )
    step_errors, (q, v) = sol.ys
    step_errors = np.asarray(step_errors)
    constraint = float(np.max(step_errors[np.isfinite(step_errors)]))
    q, v = np.asarray(q), np.asarray(v)
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(v)), "NaN or inf in the trajectory"
    return sm.retract(jnp.asarray(q), jnp.asarray(v)), constraint, sol


def reference(system, y0, t1, solver=None):
    """Final state of a run at rtol = atol = 1e-13 (its own constraint check included)."""
    (q, v), constraint, _ = run(system, y0, t1, rtol=REF_TOL, solver=solver)
    assert constraint < UNIT
    return q[-1], v[-1]


def energies(system, q, v):
    return np.asarray(jax.jit(jax.vmap(lambda a, b: system.energy(0.0, a, b, None)))(q, v))


def max_energy_drift(system, q, v):
    e = energies(system, q, v)
    return float(np.max(np.abs(e - e[0])))


def vertical_angular_momentum(chain, q, v):
    """`sum_i m_i (x_i x xdot_i) . e3`, conserved by gravity-only chains."""

    def lz(q_, v_):
        x, xdot = jax.jvp(chain.positions, (q_,), (v_,))
        return jnp.sum(chain.masses() * jnp.cross(x, xdot)[:, 2])

    return np.asarray(jax.jit(jax.vmap(lz))(q, v))


def chain_state(vectors, velocities):
    return sm.retract(sm.normalize(jnp.asarray(vectors, float)), jnp.asarray(velocities, float))


# ----------------------------------------------------------------------------------------
# Spherical pendulum through the poles, and fast precession around a pole

PENDULUM = sm.chain_pendulum(jnp.ones(1), jnp.ones(1))


def planar_pendulum(theta0, thetadot0, t1):
    """Reference in one angle from the downward vertical (no chart singularity in the
    plane): `theta'' = -g sin(theta)`; returns the final unit vector in the x-z plane."""
    term = diffrax.ODETerm(lambda t, y, a: jnp.stack([y[1], -G * jnp.sin(y[0])]))
    sol = diffrax.diffeqsolve(
        term,
        diffrax.Dopri8(),
        0.0,
        t1,
        1e-3,
        jnp.array([theta0, thetadot0]),
        max_steps=100_000,
        stepsize_controller=diffrax.PIDController(rtol=1e-13, atol=1e-13),
    )
    theta = sol.ys[0, 0]
    return jnp.array([jnp.sin(theta), 0.0, -jnp.cos(theta)])


@pytest.mark.parametrize(
    "theta0, thetadot0",
    [
        (1.0, 0.0),  # swings through the bottom pole -e3 exactly (x = y = 0 at the bottom)
        (0.0, 1.1 * 2.0 * np.sqrt(G)),
    ],  # starts at the bottom, goes over the top pole +e3
)
def test_pendulum_through_poles(theta0, thetadot0):
    t1 = 3.0
    q0 = jnp.array([[np.sin(theta0), 0.0, -np.cos(theta0)]])
    v0 = thetadot0 * jnp.array([[np.cos(theta0), 0.0, np.sin(theta0)]])
    (q, v), constraint, _ = run(PENDULUM, (q0, v0), t1)
    assert constraint < UNIT
    exact = planar_pendulum(theta0, thetadot0, t1)
    # The motion stays in the x-z plane (to rounding) and matches the planar pendulum.
    assert float(jnp.max(jnp.abs(q[:, 0, 1]))) == 0.0
    assert float(jnp.max(jnp.abs(q[-1, 0] - exact))) < 1e-7
    assert max_energy_drift(PENDULUM, q, v) < 1e-8
    if thetadot0 > 0:  # it really went over the top
        assert float(jnp.max(q[:, 0, 2])) > 0.999


@pytest.mark.parametrize("pole", [-1.0, 1.0])
def test_fast_precession_near_pole(pole):
    """1e-3 rad from a pole, precessing at 1000 rad/s: the azimuth rate that makes
    angle coordinates stiff. Energy and the vertical angular momentum are conserved."""
    alpha, rate, t1 = 1e-3, 1e3, 0.5
    q0 = jnp.array([[np.sin(alpha), 0.0, pole * np.cos(alpha)]])
    v0 = jnp.array([[0.0, rate * np.sin(alpha), 0.0]])
    (q, v), constraint, _ = run(PENDULUM, (q0, v0), t1, n_save=1001)
    assert constraint < UNIT
    e = energies(PENDULUM, q, v)
    lz = vertical_angular_momentum(PENDULUM, q, v)
    assert float(np.max(np.abs(e - e[0]))) < 1e-8 * (1.0 + abs(e[0]))
    assert float(np.max(np.abs(lz - lz[0]))) < 1e-10
    np.testing.assert_allclose(lz[0], rate * np.sin(alpha) ** 2, rtol=1e-12)


# ----------------------------------------------------------------------------------------
# Folded and inverted chains, extreme parameter ratios (all three-link chains, so they
# share one compiled program)

CHAIN3 = sm.chain_pendulum(jnp.ones(3), jnp.ones(3))


def _compare(chain, y0, t1, tol, energy_tol):
    (q, v), constraint, _ = run(chain, y0, t1)
    q_ref, _ = reference(chain, y0, t1)
    assert constraint < UNIT
    error = float(
        jnp.max(jnp.linalg.norm(chain.positions(q[-1]) - chain.positions(q_ref), axis=-1))
    )
    assert error < tol, error
    assert max_energy_drift(chain, q, v) < energy_tol
    return q


def test_chain_folded_back_on_itself():
    # Consecutive links antiparallel: the second mass sits on the pivot.
    y0 = chain_state([[1, 0, 0], [-1, 0, 0], [1, 0, 0]], [[0, 1, 0.5], [0, -1, 0], [0, 0, 2]])
    _compare(CHAIN3, y0, 2.0, tol=1e-7, energy_tol=1e-7)


def test_chain_straight_up():
    # Inverted, unstable equilibrium, perturbed by 1e-6: the perturbation grows ~e^(5 t)
    # and the chain falls; the run still tracks the reference.
    y0 = chain_state([[1e-6, 0, 1], [0, 1e-6, 1], [0, 0, 1]], np.zeros((3, 3)))
    q = _compare(CHAIN3, y0, 2.5, tol=1e-5, energy_tol=1e-6)
    assert float(q[-1, 0, 2]) < 0.5  # it did fall


@pytest.mark.parametrize(
    "masses, lengths", [((1.0, 1e-6, 1.0), (1.0, 1.0, 1.0)), ((1.0, 1.0, 1.0), (1.0, 1e-3, 1.0))]
)
def test_extreme_ratios(masses, lengths):
    chain = sm.chain_pendulum(jnp.asarray(masses), jnp.asarray(lengths))
    y0 = chain_state([[1, 0, -1], [0, 1, -1], [-1, 0.3, 0]], [[0, 1, 0], [1, 0, 0.5], [0, 0, 1]])
    _compare(chain, y0, 2.0, tol=1e-6, energy_tol=1e-7)


# ----------------------------------------------------------------------------------------
# High spin rate: an exact solution


def test_spin_rate_1e3():
    """A straight chain spinning rigidly at 1000 rad/s about the vertical, without
    gravity, is an exact solution: q_i(t) = R_z(1000 t) e_x."""
    chain = sm.chain_pendulum(jnp.ones(2), jnp.ones(2), g=0.0)
    rate, t1 = 1e3, 0.05  # 50 rad, about 8 turns
    q0 = jnp.array([[1.0, 0, 0], [1.0, 0, 0]])
    v0 = jnp.array([[0, rate, 0], [0, rate, 0]])
    (q, v), constraint, _ = run(chain, (q0, v0), t1)
    assert constraint < UNIT
    exact = jnp.array([np.cos(rate * t1), np.sin(rate * t1), 0.0])
    assert float(jnp.max(jnp.abs(q[-1] - exact))) < 1e-7
    assert max_energy_drift(chain, q, v) < 1e-8 * float(energies(chain, q[:1], v[:1])[0])


# ----------------------------------------------------------------------------------------
# Stiff bending springs with an implicit solver


def test_stiff_bending_springs_implicit():
    """Bending springs `U = k sum_i (1 - q_i . q_{i+1})` 1e6 times stiffer than gravity
    (`k = 1e6 m g l`), on the constant-inertia fast path, integrated by
    `Projected(Kvaerno5)` at rtol = atol = 1e-5: it follows the slow swing of the nearly
    rigid chain in ~250 steps, where `Projected(Tsit5)` at the same tolerance needs
    ~13 000 (its step is bounded by stability, ~3.5 / 3000 rad/s). The limit: at
    tolerances below the amplitude of the bending vibration (~1e-6 rad here) the implicit
    solver resolves the vibration too and loses its advantage."""
    n = 4
    base = sm.chain_pendulum(jnp.ones(n), jnp.ones(n))
    k = 1e6 * G

    def potential(t, q, args):
        return base.potential(t, q) + k * jnp.sum(1.0 - jnp.sum(q[:-1] * q[1:], axis=-1))

    stiff = sm.ConstantInertiaLagrangian(base.inertia(), potential)
    direction = sm.normalize(jnp.array([[np.sin(0.6), 0.0, -np.cos(0.6)]]))
    # A rigid swing: every link the same direction and the same angular velocity.
    y0 = (jnp.tile(direction, (n, 1)), jnp.tile(jnp.array([[0.0, 1.0, 0.0]]), (n, 1)))
    t1 = 1.0
    (q, v), constraint, sol = run(stiff, y0, t1, solver=sm.Projected(diffrax.Kvaerno5()), rtol=1e-5)
    assert constraint < UNIT
    _, _, explicit = run(stiff, y0, t1, rtol=1e-5)
    assert int(sol.stats["num_steps"]) < int(explicit.stats["num_steps"]) / 10
    # Reference: Projected(Dopri8) at 1e-13 (Tsit5 would need ~1e6 steps here).
    q_ref, _ = reference(stiff, y0, t1, solver=sm.Projected(diffrax.Dopri8()))
    error = float(jnp.max(jnp.linalg.norm(base.positions(q[-1]) - base.positions(q_ref), axis=-1)))
    assert error < 1e-4, error
    # Energy: the implicit method damps the (tiny) bending vibration, nothing else.
    assert max_energy_drift(stiff, q, v) < 1e-3 * n * G
    # Bending stays tiny: neighbouring links within 1e-4 rad of each other.
    assert float(jnp.max(1.0 - jnp.sum(q[:, :-1] * q[:, 1:], axis=-1))) < 1e-8


# ----------------------------------------------------------------------------------------
# A long chain


def test_64_link_chain():
    n, t1 = 64, 0.5
    chain = sm.chain_pendulum(jnp.full(n, 1.0 / n), jnp.full(n, 1.0 / n))
    i = np.arange(n)
    angle = 0.5 * np.sin(np.pi * (i + 1) / (n + 1))
    q0 = np.stack([np.sin(angle), np.zeros(n), -np.cos(angle)], -1)
    v0 = np.stack([np.zeros(n), 0.5 * np.cos(np.pi * i / n), np.zeros(n)], -1)
    (q, v), constraint, _ = run(chain, chain_state(q0, v0), t1, rtol=1e-8, n_save=21)
    assert constraint < UNIT
    e = energies(chain, q, v)
    lz = vertical_angular_momentum(chain, q, v)
    assert float(np.max(np.abs(e - e[0]))) < 1e-6 * float(np.max(np.abs(e)))
    assert float(np.max(np.abs(lz - lz[0]))) < 1e-8


# ----------------------------------------------------------------------------------------
# Initial states off the sphere; degenerate Lagrangians


ENDS = diffrax.SaveAt(t0=True, t1=True)  # one compiled program for the next tests


def test_initial_state_slightly_off_sphere_is_normalized():
    """Within `unit_tolerance` (1e-6 in float64) `simulate` accepts the state and uses
    `q_i / |q_i|` and `v_i - (q_i . v_i) q_i` (with the normalized `q_i`) instead."""
    q = jnp.array([[0.6, 0.0, -0.8], [0.0, 0.6, -0.8]]) * (1.0 + 1e-9)
    v = jnp.array([[0.0, 1.0, 1e-9], [1.0, 0.0, 0.0]])
    chain = sm.chain_pendulum(jnp.ones(2), jnp.ones(2))
    sol = sm.simulate(chain, (q, v), 0.1, saveat=ENDS)
    q0, v0 = sol.ys[0][0], sol.ys[1][0]
    expected = sm.retract(q, v)
    np.testing.assert_allclose(q0, expected[0], rtol=0, atol=1e-16)
    np.testing.assert_allclose(v0, expected[1], rtol=0, atol=1e-16)
    assert float(sm.constraint_error(q0)) < 1e-15
    assert float(jnp.max(jnp.abs(jnp.sum(q0 * v0, axis=-1)))) < 1e-15


def test_initial_state_far_off_sphere_is_an_error():
    chain = sm.chain_pendulum(jnp.ones(2), jnp.ones(2))
    q = jnp.array([[0.6, 0.0, -0.8], [0.0, 0.6, -0.8]]) * (1.0 + 1e-2)
    with pytest.raises(Exception, match="q is not on the spheres"):
        sm.simulate(chain, (q, jnp.zeros((2, 3))), 0.1)
    q = sm.normalize(q)
    with pytest.raises(Exception, match="qdot is not tangent"):
        sm.simulate(chain, (q, 1e-2 * q), 0.1)


def test_zero_mass_is_a_clear_error():
    q, v = chain_state([[1, 0, -1], [0, 1, -1]], [[0, 1, 0], [1, 0, 0]])
    with pytest.raises(ValueError, match=r"masses must be > 0 \(kg\), got \[1.0, 0.0\]"):
        sm.chain_pendulum(jnp.array([1.0, 0.0]), jnp.ones(2))
    chain = sm.chain_pendulum(jnp.array([1.0, 1.0]), jnp.ones(2))

    def L(t, q, qdot, args):  # the chain with a massless tip, as a general Lagrangian
        return chain.lagrangian(t, q, qdot.at[1].set(0.0), args)

    general = sm.Lagrangian(L)
    with pytest.raises(Exception, match="reduced mass matrix"):
        general.acceleration(0.0, q, v)
    with pytest.raises(Exception, match="equations of motion are not finite"):
        sm.simulate(general, (q, v), 0.1, saveat=ENDS)


# ----------------------------------------------------------------------------------------
# float32


def test_float32_double_pendulum():
    """float32 for 10 s at the float32 default tolerances (rtol 1e-5, atol 1e-6): the
    projection keeps |q_i| = 1 to float32 rounding (~1e-7) at every step; the energy and
    the final positions stay within the stated bounds of a float64 reference."""
    chain32 = sm.chain_pendulum(jnp.ones(2, jnp.float32), jnp.ones(2, jnp.float32))
    chain64 = sm.chain_pendulum(jnp.ones(2), jnp.ones(2))
    q0, v0 = chain_state([[1, 0, -1], [0, 1, -2]], [[0, 1.0, 0], [0.5, 0, 0.25]])
    y32 = (q0.astype(jnp.float32), v0.astype(jnp.float32))
    ts = jnp.linspace(0.0, 10.0, 201, dtype=jnp.float32)
    saveat = diffrax.SaveAt(
        subs=[diffrax.SubSaveAt(steps=True, fn=_step_constraint), diffrax.SubSaveAt(ts=ts)]
    )
    sol = sm.simulate(chain32, y32, jnp.float32(10.0), saveat=saveat)
    step_errors, (q, v) = sol.ys
    assert q.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(q))) and np.all(np.isfinite(np.asarray(v)))
    step_errors = np.asarray(step_errors)
    assert float(np.max(step_errors[np.isfinite(step_errors)])) < 5e-7
    q, v = sm.retract(q, v)
    e = energies(chain64, q.astype(jnp.float64), v.astype(jnp.float64))
    assert float(np.max(np.abs(e - e[0]))) < 1e-3
    q_ref, _ = reference(chain64, (q0, v0), 10.0)
    error = jnp.max(
        jnp.linalg.norm(
            chain64.positions(q[-1].astype(jnp.float64)) - chain64.positions(q_ref), axis=-1
        )
    )
    assert float(error) < 1e-2
