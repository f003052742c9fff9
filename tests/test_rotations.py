"""The factor SO(3) (`sm.Rotations`): rigid bodies in the four forms, against closed forms
and scipy references written here (Euler's equations, a quaternion ODE), conservation
laws, the Lie-group solver's orthogonality, convergence orders, gradients and bad input."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import central_differences, fitted_order, fixed_steps, last, steps_taken
from scipy.integrate import solve_ivp
from scipy.special import ellipj

import sphere_mech as sm

J = jnp.array([1.0, 2.0, 3.0])  # J1 < J2 < J3
RHO = jnp.array([0.1, -0.2, 1.0])  # the centre of mass in the body frame (m)
M_G = 10.0 * 9.8  # m g (N)
R0 = sm.rotation_matrix(jnp.array([[0.3, -0.2, 0.5]]))
W0 = jnp.array([[1.0, 0.0, 0.8]])  # body angular velocity: Omega_2(0) = 0
TS = jnp.linspace(0.0, 3.0, 7)
TIGHT = dict(rtol=1e-12, atol=1e-12, saveat=diffrax.SaveAt(ts=TS))
SPACE = sm.Rotations(1)
FIXED = diffrax.ConstantStepSize()


def quaternion_matrix(qt):
    """The rotation matrix of a quaternion `(w, x, y, z)` (normalized first)."""
    w, x, y, z = qt / np.linalg.norm(qt)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quaternion_rate(qt, w):
    """`qdot = q (0, w) / 2` for the body angular velocity `w`."""
    return 0.5 * np.array(
        [
            -qt[1] * w[0] - qt[2] * w[1] - qt[3] * w[2],
            qt[0] * w[0] + qt[2] * w[2] - qt[3] * w[1],
            qt[0] * w[1] - qt[1] * w[2] + qt[3] * w[0],
            qt[0] * w[2] + qt[1] * w[1] - qt[2] * w[0],
        ]
    )


def quaternion(angle):
    """The unit quaternion of the rotation vector `angle`."""
    theta = np.linalg.norm(angle)
    return np.concatenate([[np.cos(theta / 2)], np.sin(theta / 2) * angle / theta])


def body(R, Rdot):
    return sm.vee(jnp.swapaxes(R, -1, -2) @ Rdot)


def pendulum_L2(t, R, W, args):
    """The 3-D pendulum in body angular velocity (form 2): a body on a fixed pivot."""
    return 0.5 * jnp.sum(J * W**2) - M_G * (R[0] @ RHO)[2]


def pendulum_L1(t, R, Rdot, args):
    """The same Lagrangian in `Rdot` (form 1)."""
    return pendulum_L2(t, R, body(R, Rdot), args)


def free_L2(t, R, W, args):
    return 0.5 * jnp.sum(J * W**2)


@pytest.fixture(scope="module")
def pendulum_reference():
    """`R(t)` of the 3-D pendulum from a unit-quaternion ODE solved by scipy:
    `qdot = q (0, Omega) / 2`, `J Omegadot = J Omega x Omega + m g (R^T e3) x rho`."""

    def rhs(t, y):
        q, w = y[:4], y[4:]
        e3_body = quaternion_matrix(q).T @ np.array([0.0, 0.0, 1.0])
        Jn, rho = np.asarray(J), np.asarray(RHO)
        wdot = (np.cross(Jn * w, w) + M_G * np.cross(e3_body, rho)) / Jn
        return np.concatenate([quaternion_rate(q, w), wdot])

    q0 = quaternion(np.array([0.3, -0.2, 0.5]))
    sol = solve_ivp(
        rhs,
        (0, 3),
        np.concatenate([q0, np.asarray(W0[0])]),
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
        t_eval=np.asarray(TS),
    )
    return np.stack([quaternion_matrix(q) for q in sol.y[:4].T]), sol.y[4:].T


def test_torque_free_body_against_jacobi_elliptic_closed_form():
    """Landau's solution (J1 < J2 < J3, |L|^2 > 2 E J2): `Omega_1 = a cn`, `Omega_2 = b
    sn`, `Omega_3 = c dn`; energy and the spatial angular momentum `R J Omega` constant."""
    system = sm.AngularLagrangian(free_L2, space=SPACE)
    sol = sm.simulate(system, (R0, W0), 3.0, solver=sm.LieRK(diffrax.Dopri8()), **TIGHT)
    R, W = sol.ys
    J1, J2, J3 = (float(j) for j in J)
    E = 0.5 * float(jnp.sum(J * W0**2))
    L2 = float(jnp.sum((J * W0) ** 2))
    assert L2 > 2 * E * J2
    tau = np.asarray(TS) * np.sqrt((J3 - J2) * (L2 - 2 * E * J1) / (J1 * J2 * J3))
    m = (J2 - J1) * (2 * E * J3 - L2) / ((J3 - J2) * (L2 - 2 * E * J1))
    sn, cn, dn, _ = ellipj(tau, m)
    closed = np.stack(
        [
            np.sqrt((2 * E * J3 - L2) / (J1 * (J3 - J1))) * cn,
            np.sqrt((2 * E * J3 - L2) / (J2 * (J3 - J2))) * sn,
            np.sqrt((L2 - 2 * E * J1) / (J3 * (J3 - J1))) * dn,
        ],
        axis=-1,
    )
    assert np.max(np.abs(np.asarray(W[:, 0]) - closed)) < 1e-9
    energy = 0.5 * jnp.sum(J * W**2, axis=(-2, -1))
    spatial = jnp.einsum("tkij,tkj->tki", R, J * W)
    assert float(jnp.max(jnp.abs(energy - E))) < 1e-10
    assert float(jnp.max(jnp.abs(spatial - spatial[0]))) < 1e-9
    orthogonality = jnp.swapaxes(R, -1, -2) @ R - jnp.eye(3)
    assert float(jnp.max(jnp.abs(orthogonality))) < 1e-14  # LieRK: a rotation to rounding


@pytest.mark.parametrize("form", [1, 2, 3, 4])
def test_four_forms_of_the_3d_pendulum_against_a_quaternion_ode(form, pendulum_reference):
    R_ref, W_ref = pendulum_reference
    lagrangian = (
        sm.Lagrangian(pendulum_L1, space=SPACE)
        if form in (1, 3)
        else sm.AngularLagrangian(pendulum_L2, space=SPACE)
    )
    v0 = R0 @ sm.hat(W0) if form in (1, 3) else W0
    system, y0 = lagrangian, (R0, v0)
    if form in (3, 4):
        system = sm.legendre(lagrangian)
        y0 = (R0, lagrangian.momentum(0.0, R0, v0))
    sol = sm.simulate(system, y0, 3.0, solver=sm.Projected(diffrax.Dopri8()), **TIGHT)
    R = sol.ys[0][:, 0]
    assert np.max(np.abs(np.asarray(R) - R_ref)) < 1e-8
    velocity = jax.jit(jax.vmap(lambda R, v: system.velocity(0.0, R, v)))(*sol.ys)
    assert np.max(np.abs(np.asarray(body(sol.ys[0], velocity)[:, 0]) - W_ref)) < 1e-8
    energy = jax.jit(jax.vmap(lambda R, v: system.energy(0.0, R, v)))(*sol.ys)
    assert float(jnp.max(jnp.abs(energy - energy[0]))) < 1e-10 * float(jnp.abs(energy[0]))


TAU = jnp.array([0.3, -0.5, 0.2])
TORQUED = (
    sm.AngularLagrangian(free_L2, lambda t, R, v, args: TAU[None], space=SPACE),
    sm.Lagrangian(
        lambda t, R, Rd, a: free_L2(t, R, body(R, Rd), a),
        lambda t, R, v, args: TAU[None],
        space=SPACE,
    ),
)
"""The free body under a constant body torque `TAU`, in forms 2 and 1."""


def torqued_body_reference(ts):
    """`Omega(ts)` of `J Omegadot = J Omega x Omega + TAU` from `W0`, by scipy."""
    Jn = np.asarray(J)
    rhs = lambda t, w: (np.cross(Jn * w, w) + np.asarray(TAU)) / Jn
    ref = solve_ivp(rhs, (0, ts[-1]), np.asarray(W0[0]), rtol=1e-13, atol=1e-13, t_eval=ts)
    return ref.y.T


def test_body_torque_is_the_generalized_force_of_a_rotation():
    """A constant body torque `tau` on a free body: `J Omegadot = J Omega x Omega + tau`
    (scipy), in form 2 and (as `R hat(tau) / 2` against `Rdot`) in form 1."""
    ref = torqued_body_reference(np.asarray(TS))
    two, one = TORQUED
    for system, v0 in ((two, W0), (one, R0 @ sm.hat(W0))):
        sol = sm.simulate(system, (R0, v0), 3.0, solver=sm.Projected(diffrax.Dopri8()), **TIGHT)
        W = jax.jit(jax.vmap(lambda R, v, s=system: body(R, s.velocity(0.0, R, v))))(*sol.ys)[:, 0]
        assert np.max(np.abs(np.asarray(W) - ref)) < 1e-9
        # the power of the torque is tau . Omega
        power = system.power(0.0, R0, v0)
        assert abs(float(power) - float(TAU @ W0[0])) < 1e-14


@pytest.mark.parametrize(
    "solver, order",
    [(sm.Projected(sm.RK4()), 4), (sm.LieRK(diffrax.Bosh3()), 3), (sm.LieRK4(), 4)],
    ids=["Projected(RK4)", "LieRK(Bosh3)", "LieRK4"],
)
def test_convergence_orders_on_rotations(solver, order, pendulum_reference):
    R_ref = pendulum_reference[0][-1]
    system = sm.AngularLagrangian(pendulum_L2, space=SPACE)
    dts = [0.02, 0.01, 0.005]
    errors = []
    for dt in dts:
        sol = sm.simulate(system, (R0, W0), 3.0, solver=solver, dt0=dt, stepsize_controller=FIXED)
        R = sol.ys[0][-1, 0]
        errors.append(float(jnp.max(jnp.abs(R - R_ref))))
        if isinstance(solver, sm.LieRK):
            assert float(jnp.max(jnp.abs(R.T @ R - jnp.eye(3)))) < 1e-14
    assert abs(fitted_order(dts, errors) - order) < 0.35


def test_gradient_through_a_rigid_body_matches_central_differences():
    system = sm.AngularLagrangian(
        lambda t, R, W, J_: 0.5 * jnp.sum(J_ * W**2) - M_G * (R[0] @ RHO)[2], space=SPACE
    )

    def final_spin(J_):
        options = dict(solver=sm.LieRK4(), dt0=0.01, stepsize_controller=FIXED)
        return sm.simulate(system, (R0, W0), 0.5, args=J_, **options).ys[1][-1, 0]

    grad = jax.jacrev(final_spin)(J)
    assert jnp.allclose(grad, central_differences(final_spin, J, 1e-6), rtol=1e-6, atol=1e-8)


def test_float32_rigid_body():
    system = sm.AngularLagrangian(pendulum_L2, space=SPACE)
    y0 = (R0.astype(jnp.float32), W0.astype(jnp.float32))
    sol = sm.simulate(system, y0, 1.0, solver=sm.LieRK4(), dt0=0.01, stepsize_controller=FIXED)
    R = sol.ys[0][-1, 0]
    assert R.dtype == jnp.float32
    assert float(jnp.max(jnp.abs(R.T @ R - jnp.eye(3)))) < 1e-5


def test_inverse_legendre_on_rotations_from_any_guess():
    """Form 1's inverse Legendre map `Rdot(mu)` by one linear solve around a guess: exact
    from any guess (the factor's tangent basis is orthonormal, so a guess's coordinates
    are its own), and the tangent basis `R hat(e_a) / sqrt(2)` is orthonormal."""
    system = sm.Lagrangian(pendulum_L1, space=SPACE)
    Rdot = R0 @ sm.hat(W0)
    mu = system.momentum(0.0, R0, Rdot)
    guess = R0 @ sm.hat(jnp.array([[0.3, 0.1, -0.2]]))
    v, _ = system.velocity_from_momentum(0.0, R0, mu, guess=guess, quadratic=True)
    assert float(jnp.max(jnp.abs(v - Rdot))) < 1e-14
    T = SPACE.tangent_basis(R0)[0]
    gram = jnp.einsum("ija,ijb->ab", T, T)
    assert float(jnp.max(jnp.abs(gram - jnp.eye(3)))) < 1e-15


def test_nearest_rotation_is_the_polar_factor():
    A = np.asarray(R0[0]) + 0.05 * np.random.default_rng(0).standard_normal((3, 3))
    U, _, Vt = np.linalg.svd(A)
    assert np.max(np.abs(np.asarray(sm.nearest_rotation(jnp.asarray(A))) - U @ Vt)) < 1e-14
    # Its input is checked (a (3,) vector gave an IndexError, iterations=-1 returned R).
    for R in (np.zeros(3), np.zeros((3, 4)), np.zeros((2, 2))):
        with pytest.raises(ValueError, match=r"nearest_rotation: R must have shape \(\.\.\., 3,"):
            sm.nearest_rotation(R)
    for iterations in (-1, 2.5):
        with pytest.raises(ValueError, match="iterations must be an integer >= 0"):
            sm.nearest_rotation(A, iterations)
    assert np.array_equal(sm.nearest_rotation(A.tolist(), 0), A)


def test_no_rotations_and_an_attitude_without_a_base_are_refused():
    """An empty `Rotations()` state is named (NumPy's zero-size reduction error before),
    as an empty `Spheres()` one is; `chain_space` refuses an attitude without a base (it
    was dropped) and an attitude that is not a bool."""
    system = sm.AngularLagrangian(pendulum_L2, space=sm.Rotations())
    with pytest.raises(ValueError, match=r"q must hold at least one rotation \(k >= 1\), got"):
        system.angular_acceleration(0.0, jnp.zeros((0, 3, 3)), jnp.ones((0, 3)), None)
    with pytest.raises(ValueError, match="a rigid base moves in 3-D space, got base=None"):
        sm.chain_space(None, 3, attitude=True)
    with pytest.raises(ValueError, match="attitude must be True or False, got 'yes'"):
        sm.chain_space(3, 3, attitude="yes")
    assert sm.chain_space(3, 2, attitude=np.True_) == sm.chain_space(3, 2, attitude=True)


def test_bad_rotation_input_is_named():
    system = sm.AngularLagrangian(pendulum_L2, space=SPACE)
    with pytest.raises(ValueError, match=r"q must have shape \(1, 3, 3\)"):
        sm.simulate(system, (R0[0], W0), 1.0)
    with pytest.raises(ValueError, match=r"omega must have shape \(1, 3\)"):
        sm.simulate(system, (R0, R0 @ sm.hat(W0)), 1.0)
    with pytest.raises(Exception, match="q is not a rotation"):
        sm.simulate(system, (R0 * 1.01, W0), 1.0)
    with pytest.raises(Exception, match=r"q is not a rotation.*\(a reflection"):
        sm.simulate(system, (-R0, W0), 1.0)  # det -1
    linear = sm.Lagrangian(pendulum_L1, space=SPACE)
    with pytest.raises(Exception, match="qdot is not tangent to the rotations"):
        sm.simulate(linear, (R0, R0 + 0.1), 1.0)
    torque = sm.AngularLagrangian(pendulum_L2, lambda t, R, W, a: jnp.zeros((1, 3, 3)), space=SPACE)
    with pytest.raises(ValueError, match=r"one body torque per rotation"):
        sm.simulate(torque, (R0, W0), 1.0)
    with pytest.raises(ValueError, match="Rotations\\(k\\): k must be a positive int"):
        sm.Rotations(0)


def test_batch_of_rigid_bodies_equals_one_by_one():
    system = sm.AngularLagrangian(pendulum_L2, space=SPACE)
    R = sm.rotation_matrix(jnp.array([[[0.3, -0.2, 0.5]], [[1.0, 0.2, -0.4]], [[0.0, 0.0, 0.1]]]))
    W = jnp.array([[[1.0, 0.0, 0.8]], [[0.1, 0.2, 0.3]], [[0.0, -1.0, 0.0]]])
    options = dict(solver=sm.LieRK4(), dt0=0.01, stepsize_controller=FIXED)
    batch = sm.simulate_batch(system, (R, W), 0.5, **options)
    for b in range(3):
        one = sm.simulate(system, (R[b], W[b]), 0.5, **options)
        assert jnp.allclose(batch.ys[0][b], one.ys[0], rtol=0, atol=1e-13)
        assert jnp.allclose(batch.ys[1][b], one.ys[1], rtol=0, atol=1e-13)


@pytest.mark.parametrize("angular", [False, True], ids=["form 1", "form 2"])
def test_a_body_with_a_position_and_an_attitude(angular):
    """`{"base": Euclidean(3), "attitude": Rotations(1)}`, a thrust `f R e3` along the body
    axis and no torque, from rest: `R` stays, `x(t) = (f R e3 / m - g e3) t^2 / 2`."""
    m, f, g = 2.0, 30.0, 9.81
    e3 = jnp.array([0.0, 0.0, 1.0])
    space = {"base": sm.Euclidean(3), "attitude": SPACE}

    def L(t, q, v, args):
        W = v["attitude"] if angular else body(q["attitude"], v["attitude"])
        kinetic = 0.5 * m * v["base"] @ v["base"] + 0.5 * jnp.sum(J * W**2)
        return kinetic - m * g * q["base"][2]

    def forces(t, q, v, args):
        return {"base": f * q["attitude"][0] @ e3, "attitude": jnp.zeros((1, 3))}

    system = (sm.AngularLagrangian if angular else sm.Lagrangian)(L, forces, space=space)
    q0 = {"base": jnp.zeros(3), "attitude": R0}
    v0 = {"base": jnp.zeros(3), "attitude": jnp.zeros((1, 3) if angular else (1, 3, 3))}
    sol = sm.simulate(system, (q0, v0), 3.0, solver=sm.LieRK(diffrax.Dopri8()), **TIGHT)
    expected = (f * R0[0] @ e3 / m - g * e3) * TS[:, None] ** 2 / 2
    assert float(jnp.max(jnp.abs(sol.ys[0]["base"] - expected))) < 1e-10
    assert float(jnp.max(jnp.abs(sol.ys[0]["attitude"] - R0))) < 1e-13


# A free body (position, attitude) carrying a pendulum hung from a point `d` off its centre
# of mass, on {"base": Euclidean(3), "attitude": Rotations(1), "pendulum": Spheres(1)}.
CARRIER = dict(M=2.0, m=0.5, rod=0.7, g=9.81, d=np.array([0.1, 0.2, -0.3]))
CARRIER_SPACE = {"base": sm.Euclidean(3), "attitude": SPACE, "pendulum": sm.Spheres(1)}


def carrier_L(angular):
    """The carrier's Lagrangian in form 2 (`angular`) or 1."""
    M, m, rod, g, d = (CARRIER[k] for k in "M m rod g d".split())

    def lagrangian(t, q, v, args):
        R, p = q["attitude"][0], q["pendulum"][0]
        W = v["attitude"][0] if angular else body(q["attitude"], v["attitude"])[0]
        pdot = jnp.cross(v["pendulum"][0], p) if angular else v["pendulum"][0]
        bob = v["base"] + R @ jnp.cross(W, jnp.asarray(d)) + rod * pdot
        kinetic = 0.5 * M * v["base"] @ v["base"] + 0.5 * jnp.sum(J * W**2)
        kinetic = kinetic + 0.5 * m * bob @ bob
        height = M * q["base"][2] + m * (q["base"] + R @ jnp.asarray(d) + rod * p)[2]
        return kinetic - g * height

    return lagrangian


def carrier_state(angular):
    """The carrier's initial state `(q0, v0)` in form 2 (`angular`) or 1."""
    p0 = sm.normalize(jnp.array([[0.3, -0.4, -1.0]]))
    W0_ = jnp.array([[0.5, -0.3, 0.9]])
    x0, xdot0 = jnp.zeros(3), jnp.array([0.2, 0.0, 1.0])
    omega_p0 = jnp.array([[0.0, 1.2, 0.0]])
    omega_p0 = omega_p0 - (omega_p0 @ p0[0]) * p0  # tangent to the pendulum's sphere
    q0 = {"base": x0, "attitude": R0, "pendulum": p0}
    if angular:
        return q0, {"base": xdot0, "attitude": W0_, "pendulum": omega_p0}
    pdot0 = jnp.cross(omega_p0, p0)
    return q0, {"base": xdot0, "attitude": R0 @ sm.hat(W0_), "pendulum": pdot0}


CARRIER_SYSTEMS = {
    angular: (sm.AngularLagrangian if angular else sm.Lagrangian)(
        carrier_L(angular), space=CARRIER_SPACE
    )
    for angular in (False, True)
}


@pytest.fixture(scope="module")
def carrier_lierk():
    """The carrier in forms 1 and 2 (`angular`) by `LieRK(Dopri8())` at tolerance 1e-12,
    saved at `TS[:4]` (0 .. 1.5 s)."""
    return {
        angular: sm.simulate(
            system,
            carrier_state(angular),
            TS[3],
            solver=sm.LieRK(diffrax.Dopri8()),
            rtol=1e-12,
            atol=1e-12,
            saveat=diffrax.SaveAt(ts=TS[:4]),
        )
        for angular, system in CARRIER_SYSTEMS.items()
    }


@pytest.mark.slow  # 38 s; test_rigid_base checks a body carrying a chain against the same
# kind of Cartesian + quaternion reference
def test_rigid_body_carrying_a_pendulum_against_a_cartesian_quaternion_dae(carrier_lierk):
    """A free body (position, attitude) carrying a pendulum hung from a point `d` off its
    centre of mass, on `{"base": Euclidean(3), "attitude": Rotations(1), "pendulum":
    Spheres(1)}` in forms 1 and 2, against the same system in Cartesian coordinates (body
    position, unit quaternion, body rate, bob position) with the rod held by a Lagrange
    multiplier, solved by scipy."""
    M, m, rod, g, d = (CARRIER[k] for k in "M m rod g d".split())
    e3 = np.array([0.0, 0.0, 1.0])
    Jn = np.asarray(J)
    q0, v0 = carrier_state(True)
    x0, xdot0, p0 = q0["base"], v0["base"], q0["pendulum"]
    W0_, omega_p0 = v0["attitude"], v0["pendulum"]

    # The reference: y = (x, quaternion, Omega, bob position, bob velocity).
    def rhs(t, y):
        x, xd, qt, W, yb, yd = y[:3], y[3:6], y[6:10], y[10:13], y[13:16], y[16:19]
        R = quaternion_matrix(qt)
        c = yb - x - R @ d
        cdot = yd - xd - R @ np.cross(W, d)
        # accelerations as a + lam b (lam: the rod's tension per unit length)
        a_x, b_x = -g * e3, c / M
        a_y, b_y = -g * e3, -c / m
        a_W = np.cross(Jn * W, W) / Jn
        b_W = np.cross(d, R.T @ c) / Jn
        # c . cddot + |cdot|^2 = 0, cddot = yddot - xddot - R (Wdot x d + W x (W x d))
        a_c = a_y - a_x - R @ (np.cross(a_W, d) + np.cross(W, np.cross(W, d)))
        b_c = b_y - b_x - R @ np.cross(b_W, d)
        lam = -(c @ a_c + cdot @ cdot) / (c @ b_c)
        qdot = quaternion_rate(qt, W)
        return np.concatenate([xd, a_x + lam * b_x, qdot, a_W + lam * b_W, yd, a_y + lam * b_y])

    qt0 = quaternion(np.array([0.3, -0.2, 0.5]))
    R0n = quaternion_matrix(qt0)
    bob0 = np.asarray(x0) + R0n @ d + rod * np.asarray(p0[0])
    bobdot0 = (
        np.asarray(xdot0)
        + R0n @ np.cross(np.asarray(W0_[0]), d)
        + rod * np.cross(np.asarray(omega_p0[0]), np.asarray(p0[0]))
    )
    y0 = np.concatenate([x0, xdot0, qt0, np.asarray(W0_[0]), bob0, bobdot0])
    ts = np.asarray(TS[:4])  # 0 .. 1.5 s
    ref = solve_ivp(rhs, (0, ts[-1]), y0, method="DOP853", rtol=1e-13, atol=1e-13, t_eval=ts).y.T

    for sol in carrier_lierk.values():
        q = sol.ys[0]
        bob = (
            q["base"] + jnp.einsum("tij,j->ti", q["attitude"][:, 0], d) + rod * q["pendulum"][:, 0]
        )
        assert np.max(np.abs(np.asarray(q["base"]) - ref[:, :3])) < 1e-9
        assert np.max(np.abs(np.asarray(bob) - ref[:, 13:16])) < 1e-9
        R_ref = np.stack([quaternion_matrix(qt) for qt in ref[:, 6:10]])
        assert np.max(np.abs(np.asarray(q["attitude"][:, 0]) - R_ref)) < 1e-9


# The Lie group variational integrator (`Variational` on a rotation factor). The tests share
# one system per kind and one set of simulate options, so compilations are shared too.

PENDULUM = sm.AngularLagrangian(pendulum_L2, space=SPACE)


def orthogonality_error(R):
    return float(jnp.max(jnp.abs(jnp.swapaxes(R, -1, -2) @ R - jnp.eye(3))))


@pytest.mark.parametrize("order, dts", [(2, (0.01, 0.005, 0.0025)), (4, (0.02, 0.01, 0.005))])
def test_variational_orders_on_rotations(order, dts, pendulum_reference):
    """The 3-D pendulum over 1 s against the quaternion ODE: orders 2 and 4 measured, and
    `R^T R = I` to rounding (the step renormalizes with the factor's nearest rotation)."""
    R_ref = pendulum_reference[0][2]  # t = 1
    errors = []
    for dt in dts:
        R = last(fixed_steps(PENDULUM, sm.Variational(order), dt, (R0, W0)).ys)[0][0]
        errors.append(float(jnp.max(jnp.abs(R - R_ref))))
        assert orthogonality_error(R) < 1e-15
    assert abs(fitted_order(dts, errors) - order) < 0.3, errors
    assert errors[-1] < (2e-3 if order == 2 else 1e-5), errors


def test_variational_energy_bounded_on_rotations():
    """3000 steps (h = 0.01, |Omega| up to 19 rad/s) of the 3-D pendulum: the energy error
    oscillates, O(h^2) and bounded, with no drift (the largest error of the last tenth of
    the run is that of the first); `R^T R = I` to rounding all along."""
    t, (R, W) = steps_taken(
        fixed_steps(
            PENDULUM,
            sm.Variational(),
            0.01,
            (R0, W0),
            t1=30.0,
            saveat=diffrax.SaveAt(steps=True),
            max_steps=4096,
        )
    )
    assert len(t) == 3000
    E0 = PENDULUM.energy(0.0, R0, W0)
    error = np.asarray(jax.jit(jax.vmap(lambda R_, W_: PENDULUM.energy(0.0, R_, W_)))(R, W) - E0)
    first, *_, last = (np.max(np.abs(e)) for e in np.array_split(error, 10))
    assert last < 1.5 * first
    slope = np.polyfit(np.asarray(t), error, 1)[0]
    assert abs(slope * float(t[-1] - t[0])) < 0.1 * np.max(np.abs(error))
    assert np.max(np.abs(error)) < 0.05 * float(jnp.abs(E0))
    assert orthogonality_error(R) < 1e-15


@pytest.mark.parametrize("order", [2, 4])
def test_variational_time_reversible_on_rotations(order):
    """Forward over [0, 0.5] then back with -h returns `(R0, Omega0)` to rounding
    (measured at order 4: 3.3e-14 and 3.1e-13 as the suite compiles, 1.3e-13 and 1.3e-12
    with JAX's default optimizations)."""
    solver = sm.Variational(order)
    forward = last(fixed_steps(PENDULUM, solver, 0.02, (R0, W0), t1=0.5).ys)
    back = last(fixed_steps(PENDULUM, solver, -0.02, forward, t0=0.5, t1=0.0).ys)
    assert float(jnp.max(jnp.abs(forward[0] - R0))) > 0.1  # it did move
    assert float(jnp.max(jnp.abs(back[0] - R0))) < 1e-12
    assert float(jnp.max(jnp.abs(back[1] - W0))) < 1e-11


@pytest.mark.slow  # 31 s; forced variational steps stay in test_mixed (order 2 against
# a reference), the variational orders on `Rotations` here
def test_variational_body_torque_in_forms_1_and_2():
    """A constant body torque (forced Lagrange-d'Alembert step, `h/2 tau` at both ends) on
    the free body: order 2 against scipy's `J Omegadot = J Omega x Omega + tau`, the same
    steps in form 1 (`Rdot`) and form 2 (`Omega`)."""
    ref = torqued_body_reference(np.array([1.0]))[-1]
    two, one = TORQUED
    dts, errors = (0.04, 0.02, 0.01), []
    for dt in dts:
        R2, W2 = last(fixed_steps(two, sm.Variational(), dt, (R0, W0)).ys)
        R1, Rdot1 = last(fixed_steps(one, sm.Variational(), dt, (R0, R0 @ sm.hat(W0))).ys)
        assert float(jnp.max(jnp.abs(R1 - R2))) < 1e-12
        assert float(jnp.max(jnp.abs(body(R1, Rdot1) - W2))) < 1e-12
        errors.append(float(np.max(np.abs(np.asarray(W2[0]) - ref))))
    assert abs(fitted_order(dts, errors) - 2) < 0.3, errors


@pytest.mark.slow  # 33 s; test_rigid_base steps `Variational` on the same kind of product
def test_variational_on_a_product_with_rotations_agrees_with_lierk(carrier_lierk):
    """The carrier (`Euclidean(3) x Rotations(1) x Spheres(1)`, form 2) over 1.5 s: the
    order-4 variational step at h = 0.0025 against `LieRK(Dopri8())` at tolerance 1e-12."""
    q, v = last(
        fixed_steps(
            CARRIER_SYSTEMS[True], sm.Variational(4), 0.0025, carrier_state(True), t1=1.5
        ).ys
    )
    tight = carrier_lierk[True].ys
    for k in CARRIER_SPACE:
        assert float(jnp.max(jnp.abs(q[k] - tight[0][k][-1]))) < 1e-8, k
        assert float(jnp.max(jnp.abs(v[k] - tight[1][k][-1]))) < 1e-8, k
    assert orthogonality_error(q["attitude"]) < 1e-15


@pytest.mark.slow  # 34 s; the variational step's implicit differentiation stays in
# test_variational (on the spheres)
def test_variational_gradient_on_rotations_matches_central_differences():
    """`jax.jacrev` through the Newton solves of the Lie group variational step (implicit
    differentiation) against central differences, in the initial body angular velocity."""

    def final_spin(w):
        return last(fixed_steps(PENDULUM, sm.Variational(), 0.02, (R0, w[None]), t1=0.2).ys)[1][0]

    grad = jax.jacrev(final_spin)(W0[0])
    fd = central_differences(final_spin, W0[0], 1e-6)
    assert jnp.allclose(grad, fd, rtol=1e-6, atol=1e-8)
    assert float(jnp.max(jnp.abs(grad - jnp.eye(3)))) > 0.1  # not the identity


def test_variational_float32_on_rotations():
    """float32 states step in float32 (Newton to `eps ** 0.75`), `R^T R = I` to its
    rounding, and follow the float64 steps."""
    y0 = (R0.astype(jnp.float32), W0.astype(jnp.float32))
    R = last(fixed_steps(PENDULUM, sm.Variational(), jnp.float32(0.01), y0).ys)[0][0]
    R64 = last(fixed_steps(PENDULUM, sm.Variational(), 0.01, (R0, W0)).ys)[0][0]
    assert R.dtype == jnp.float32
    assert orthogonality_error(R) < 1e-6
    assert float(jnp.max(jnp.abs(R - R64))) < 1e-3


# 74 s; `fit` through a Lie group solver stays in test_fit_models, a fit on `Rotations` in
# notebook 08 (the cable quadrotor's payload and yaw coefficient)
@pytest.mark.slow
@pytest.mark.parametrize("segments", [1, 3], ids=["single", "multiple shooting"])
def test_fit_a_3d_pendulum_from_its_attitude(segments):
    """Recover `m g` and `J3` from the centre of mass's observed path (form 2, body
    `Omega`); with multiple shooting the segment states are rotations in the tangent
    chart of `Rotations`."""

    def model(p):
        Jp = jnp.array([1.0, 2.0, p["J3"]])
        L = lambda t, R, W, a: 0.5 * jnp.sum(Jp * W**2) - p["mg"] * (R[0] @ RHO)[2]
        return sm.AngularLagrangian(L, space=SPACE)

    truth = {"mg": jnp.asarray(M_G), "J3": jnp.asarray(3.0)}
    ts = jnp.linspace(0.0, 0.6, 13)
    observe = lambda system, t, R, W: R[0] @ RHO
    options = dict(solver=sm.LieRK4(), dt0=0.005, stepsize_controller=FIXED)
    sol = sm.simulate(model(truth), (R0, W0), 0.6, saveat=diffrax.SaveAt(ts=ts), **options)
    obs = jnp.einsum("tij,j->ti", sol.ys[0][:, 0], RHO)
    start = {"mg": jnp.asarray(80.0), "J3": jnp.asarray(2.5)}
    result = sm.fit(
        model,
        start,
        ts,
        obs,
        observe,
        y0=(R0, W0),
        segments=segments,
        positive=True,
        simulate_options=options,
    )
    assert bool(result.converged)
    for k in truth:
        assert abs(float(result.params[k] / truth[k]) - 1) < 1e-6, result.params
    assert all(bool(jnp.isfinite(result.stderr[k])) for k in truth)


def test_rotations_body_must_be_a_bool():
    """`Rotations(1, body="yes")` was accepted (and read as true)."""
    for bad in ("yes", 1, None):
        with pytest.raises(
            ValueError, match=rf"^Rotations: body must be True or False, got {bad!r}\.$"
        ):
            sm.Rotations(1, body=bad)
    assert sm.Rotations(1, body=np.True_) == sm.Rotations(1).angular()
