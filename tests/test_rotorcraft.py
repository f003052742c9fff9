"""Rotors and the geometric tracking controller on SE(3) (Lee, Leok and McClamroch 2010):
the mixing and its saturation, the controller against the same controller written by hand
here (closed-form derivatives of the command attitude, no autodiff), and the published
recovery from a nearly inverted start to hover."""

import json
from pathlib import Path

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import exact_observations
from test_cli import run_cli
from test_rigid_base import random_rigid_state

import sphere_mech as sm

# Lee, Leok and McClamroch (2010), section V: the vehicle, its rotors and the gains.
MASS, INERTIA = 4.34, np.array([0.0820, 0.0845, 0.1377])
ARM, C_TF = 0.315, 8.004e-4
GAINS = dict(kx=16 * MASS, kv=5.6 * MASS, kR=8.81, kOmega=2.54)
G = 9.81
CIRCLE = dict(center=[0.1, -0.2, 1.0], radius=0.8, angular_frequency=1.3, phase=0.4)
HEADING = np.array([0.6, 0.8, 0.0])
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def quadrotor(command, *, min_thrust=0.0, max_thrust=None, payload=0.01):
    """The published vehicle carrying a light damped pendulum (a short cable)."""
    control = sm.GeometricControl(MASS + payload, INERTIA, command=command, g=G, **GAINS)
    return sm.Scene(
        sm.RigidBase(MASS, INERTIA),
        sm.Chain(payload, 0.3),
        sm.Gravity(G),
        sm.JointDamping(1e-3),
        sm.Rotors(control, ARM, C_TF, min_thrust=min_thrust, max_thrust=max_thrust),
    ), control


def test_mixing_and_saturation():
    rotors = sm.Rotors([0.0] * 4, ARM, C_TF, min_thrust=0.5, max_thrust=12.0)
    A = sm.mixing_matrix(jnp.asarray(ARM), jnp.asarray(C_TF))
    inside = jnp.array([2.0, 3.0, 4.0, 5.0])
    assert np.allclose(rotors.thrusts(A @ inside), inside, rtol=1e-14)
    # The moments of rotors at (d, 0), (0, d), (-d, 0), (0, -d) pushing along +e3.
    arms = ARM * np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], dtype=float)
    moment = sum(np.cross(r, [0.0, 0.0, f]) for r, f in zip(arms, inside, strict=True))
    assert np.allclose((A @ inside)[1:3], moment[:2], rtol=1e-14)
    clipped = rotors.thrusts(A @ jnp.array([-1.0, 3.0, 20.0, 5.0]))
    assert np.array_equal(clipped, [0.5, 3.0, 12.0, 5.0])
    with pytest.raises(ValueError, match="max_thrust must be > min_thrust"):
        sm.Rotors([0.0] * 4, ARM, C_TF, min_thrust=2.0, max_thrust=1.0)
    with pytest.raises(ValueError, match="Rotors needs a RigidBase"):
        sm.Scene(sm.Chain(1.0, 1.0), sm.Rotors([0.0] * 4, ARM, C_TF))


def _unit_derivatives(u, ud, udd):
    """`u / |u|` and its first two time derivatives."""
    n = np.linalg.norm(u)
    uud = u @ ud
    first = ud / n - u * uud / n**3
    second = udd / n - 2 * ud * uud / n**3 - u * (ud @ ud + u @ udd) / n**3 + 3 * u * uud**2 / n**5
    return u / n, first, second


def hand_written_control(t, q, qdot, mass):
    """The controller of Lee, Leok and McClamroch (2010) with the derivatives of `R_c`
    written out (the FDCL way), for `CIRCLE` and `HEADING`, frame `e3` up."""
    x, v = np.asarray(q["base"]), np.asarray(qdot["base"])
    R = np.asarray(q["attitude"][0])
    Omega = np.asarray(sm.vee(R.T @ qdot["attitude"][0]))
    J, e3 = np.diag(INERTIA), np.array([0.0, 0.0, 1.0])
    c, r, w = np.array(CIRCLE["center"]), CIRCLE["radius"], CIRCLE["angular_frequency"]
    phi = w * t + CIRCLE["phase"]
    cs, sn = np.array([np.cos(phi), np.sin(phi), 0.0]), np.array([-np.sin(phi), np.cos(phi), 0.0])
    x_d, v_d, a_d, j_d, s_d = c + r * cs, r * w * sn, -r * w**2 * cs, -r * w**3 * sn, r * w**4 * cs
    kx, kv, kR, kO = GAINS["kx"], GAINS["kv"], GAINS["kR"], GAINS["kOmega"]
    F = -kx * (x - x_d) - kv * (v - v_d) + mass * (G * e3 + a_d)
    b3_body, b3_rate = R @ e3, R @ np.cross(Omega, e3)
    f = F @ b3_body
    a = -G * e3 + f * b3_body / mass
    Fd = -kx * (v - v_d) - kv * (a - a_d) + mass * j_d
    fd = Fd @ b3_body + F @ b3_rate
    ad = (fd * b3_body + f * b3_rate) / mass
    Fdd = -kx * (a - a_d) - kv * (ad - j_d) + mass * s_d
    b3, b3d, b3dd = _unit_derivatives(F, Fd, Fdd)
    b2, b2d, b2dd = _unit_derivatives(
        np.cross(b3, HEADING), np.cross(b3d, HEADING), np.cross(b3dd, HEADING)
    )
    b1, b1d = np.cross(b2, b3), np.cross(b2d, b3) + np.cross(b2, b3d)
    b1dd = np.cross(b2dd, b3) + 2 * np.cross(b2d, b3d) + np.cross(b2, b3dd)
    Rc, Rcd, Rcdd = (
        np.stack(cols, axis=-1) for cols in ((b1, b2, b3), (b1d, b2d, b3d), (b1dd, b2dd, b3dd))
    )
    vee = lambda S: 0.5 * np.array([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]])
    Omega_c, Omegadot_c = vee(Rc.T @ Rcd), vee(Rc.T @ Rcdd)
    hat = lambda u: np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
    e_R = 0.5 * vee(Rc.T @ R - R.T @ Rc)
    e_O = Omega - R.T @ Rc @ Omega_c
    M = -kR * e_R - kO * e_O + np.cross(Omega, J @ Omega)
    M -= J @ (hat(Omega) @ R.T @ Rc @ Omega_c - R.T @ Rc @ Omegadot_c)
    return np.concatenate([[f], M])


def test_geometric_control_equals_the_hand_written_controller():
    """At random states and times, on a circle: thrust and moments to 1e-10 (relative)."""
    command = sm.Circle(**CIRCLE, heading=HEADING)
    control = sm.GeometricControl(MASS, INERTIA, command=command, g=G, **GAINS)
    ours = eqx.filter_jit(lambda c, t, q, v: c(t, q, v, None))
    for seed in range(4):
        q, v = random_rigid_state(seed, n=1)
        t = 0.7 * seed + 0.1
        expected = hand_written_control(t, q, v, MASS)
        got = np.asarray(ours(control, t, q, v))
        assert np.max(np.abs(got - expected)) < 1e-10 * np.max(np.abs(expected))


def test_geometric_control_recovers_from_nearly_inverted_to_hover():
    """The published case (their R(0), nearly upside down; thrust not saturated, as in
    their analysis): from rest at the hover point, the vehicle turns over, and after
    10 s it hovers: position within 1e-3 m, `e3 . R e3` within 1e-6 of 1."""
    R0 = sm.nearest_rotation(jnp.array([[1.0, 0, 0], [0, -0.9995, -0.0314], [0, 0.0314, -0.9995]]))
    scene, _ = quadrotor(sm.Hover(), min_thrust=None)
    q0 = {"attitude": R0[None], "base": jnp.zeros(3), "spheres": jnp.array([[0.0, 0.0, -1.0]])}
    v0 = jax.tree.map(jnp.zeros_like, {**q0, "attitude": jnp.zeros((1, 3, 3))})
    ts = jnp.array([0.0, 1.0, 10.0])
    sol = sm.simulate(scene, (q0, v0), 10.0, saveat=diffrax.SaveAt(ts=ts))
    height = sol.ys[0]["attitude"][:, 0, 2, 2]
    assert height[0] < -0.99 and height[1] < 0.0  # it starts inverted, is still turning at 1 s
    assert np.max(np.abs(sol.ys[0]["base"][-1])) < 1e-3
    assert 1.0 - height[-1] < 1e-6


def test_geometric_control_without_gravity_hovers_where_the_thrust_is_zero():
    """With `g = 0` the thrust vector vanishes at the target, where its direction is free:
    at rest there the wrench is zero (not NaN) and the vehicle stays; from 0.23 m off it
    turns to push towards the target and after 10 s is within 1e-4 m of it."""
    control = sm.GeometricControl(MASS, INERTIA, command=sm.Hover(), g=0.0, **GAINS)
    rotors = sm.Rotors(control, ARM, C_TF, min_thrust=None)
    scene = sm.Scene(sm.RigidBase(MASS, INERTIA), sm.Chain(0.01, 0.3), rotors)
    ts = jnp.array([0.0, 10.0])
    for x0, tolerance in (([0.0, 0.0, 0.0], 0.0), ([0.1, -0.05, 0.2], 1e-4)):
        q0 = {"attitude": jnp.eye(3)[None], "base": jnp.array(x0), "spheres": -jnp.eye(3)[2:]}
        v0 = jax.tree.map(jnp.zeros_like, {**q0, "attitude": jnp.zeros((1, 3, 3))})
        wrench = np.asarray(control(0.0, q0, v0, None))
        assert np.all(np.isfinite(wrench)) and (tolerance > 0) == np.any(wrench != 0)
        sol = sm.simulate(scene, (q0, v0), 10.0, saveat=diffrax.SaveAt(ts=ts))
        assert np.max(np.abs(sol.ys[0]["base"][-1])) <= tolerance


def test_geometric_control_tracks_a_circle_given_as_a_function():
    """A user's function of time (the circle written by hand) commands the same thrust and
    moments as `Circle`; flown from rest 1.3 m off the circle with a 53 degree heading
    error (rotors unsaturated), the vehicle tracks it to 1e-3 m from 5 s on, its body
    `e1` in the plane of `e3` and the commanded heading."""
    circle = sm.Circle(**CIRCLE, heading=HEADING)

    def by_hand(t):
        phi = CIRCLE["angular_frequency"] * t + CIRCLE["phase"]
        offset = jnp.stack([jnp.cos(phi), jnp.sin(phi), 0.0 * phi])
        return jnp.asarray(CIRCLE["center"]) + CIRCLE["radius"] * offset, jnp.asarray(HEADING)

    scene, control = quadrotor(by_hand, min_thrust=None)
    q, v = random_rigid_state(2, n=1)
    as_circle = eqx.tree_at(lambda c: c.command, control, circle)
    assert np.allclose(control(0.3, q, v, None), as_circle(0.3, q, v, None), rtol=1e-13)
    q0 = {
        "attitude": jnp.eye(3)[None],
        "base": jnp.zeros(3),
        "spheres": jnp.array([[0.0, 0.0, -1.0]]),
    }
    v0 = jax.tree.map(jnp.zeros_like, q0)
    ts = jnp.linspace(5.0, 10.0, 11)
    sol = sm.simulate(scene, (q0, v0), 10.0, saveat=diffrax.SaveAt(ts=ts))
    x_d = jax.vmap(lambda t: circle(t)[0])(ts)
    assert np.max(np.linalg.norm(sol.ys[0]["base"] - x_d, axis=-1)) < 1e-3
    R = sol.ys[0]["attitude"][-1, 0]
    assert abs(np.linalg.det(np.stack([R[:, 0], R[:, 2], HEADING]))) < 1e-3


def test_quadrotor_cable_example(tmp_path):
    """`examples/quadrotor_cable.toml` under `sphere-mech run`: the geometric controller
    flies the step with saturated rotors, `trajectory.npz` holds the attitude."""
    out = tmp_path / "out"
    assert run_cli(EXAMPLES / "quadrotor_cable.toml", out, "--no-progress", "--no-animation") == 0
    summary = json.loads((out / "summary.json").read_text())
    np.testing.assert_allclose(summary["base"], [1.0, 0.0, 0.5], atol=0.01)  # measured 3.0e-3
    assert summary["max_relative_work_energy_balance"] < 1e-6  # measured 2.6e-9
    data = np.load(out / "trajectory.npz")
    R = data["q.attitude"][:, 0]
    assert R.shape == (1001, 3, 3) and data["v.attitude"].shape == (1001, 1, 3, 3)
    assert np.max(np.abs(np.einsum("tji,tjk->tik", R, R) - np.eye(3))) < 1e-12
    assert np.max(np.abs(R[-1] - np.eye(3))) < 1e-2  # level again, heading kept


FLIGHT_TS = np.linspace(0.0, 2.0, 21)


def cable_quadrotor(params):
    """The example's quadrotor (3-link cable) flying a step while turning 90 degrees in
    yaw; its flight controller allocates with the nominal yaw coefficient 0.0135 m, the
    rotors' true one is a parameter (with the payload)."""
    control = sm.GeometricControl(
        0.6,
        [0.00557, 0.00557, 0.0105],
        kx=4.0,
        kv=2.8,
        kR=0.5,
        kOmega=0.1,
        command=sm.Hover(heading=[0.0, 1.0, 0.0], step=[0.5, 0.0, 0.3]),
    )
    return sm.Scene(
        sm.RigidBase(0.5, [0.00557, 0.00557, 0.0105], attach=[0.0, 0.0, -0.05]),
        sm.Chain(0.01, 0.3, links=3, payload=params["payload"]),
        sm.Gravity(G),
        sm.JointDamping(5e-4),
        sm.Rotors(
            control,
            0.17,
            params["torque_coefficient"],
            max_thrust=4.0,
            model_torque_coefficient=0.0135,
        ),
    )


def observe_flight(scene, t, q, v):
    """The vehicle's and the payload's positions and the body's heading `R e1`."""
    return jnp.concatenate([q["base"], scene.positions(q)[-1], q["attitude"][0][:, 0]])


@pytest.mark.slow  # 118 s alone: the fit compiles the controller's nested derivatives
def test_fit_recovers_payload_and_rotor_coefficient_with_standard_errors():
    """`fit` recovers the payload mass and the rotors' yaw coefficient (started 50 % and
    32 % off) from noisy positions and headings (sigma = 1e-3, from a Dopri8 run at
    1e-12; the model integrates with RK4 at dt = 0.01); each estimate lies within 3
    standard errors of the truth (measured: 0.4 and 0.3), which are below 1 %."""
    truth = {"payload": 0.1, "torque_coefficient": 0.02}
    hanging = jnp.tile(jnp.array([0.0, 0.0, -1.0]), (3, 1))
    y0 = (
        {"attitude": jnp.eye(3)[None], "base": jnp.zeros(3), "spheres": hanging},
        {"attitude": jnp.zeros((1, 3, 3)), "base": jnp.zeros(3), "spheres": jnp.zeros((3, 3))},
    )
    clean = exact_observations(cable_quadrotor(truth), y0, FLIGHT_TS, observe_flight)
    noisy = clean + 1e-3 * jax.random.normal(jax.random.PRNGKey(0), clean.shape)
    result = sm.fit(
        cable_quadrotor,
        {"payload": 0.15, "torque_coefficient": 0.0135},
        FLIGHT_TS,
        noisy,
        observe_flight,
        y0=y0,
        positive=True,
        simulate_options=dict(solver=sm.Projected(sm.RK4()), dt0=0.01),
    )
    assert bool(result.converged)
    assert 0.8e-3 < float(jnp.sqrt(result.residual_variance)) < 1.2e-3
    for name, value in truth.items():
        estimate, stderr = float(result.params[name]), float(result.stderr[name])
        assert abs(estimate - value) < 3 * stderr, name
        assert stderr < 1e-2 * value, name


def test_geometric_control_flies_a_float32_state_under_x64():
    """The command and the gains are float64 under x64; a float32 state flies in float32
    (it raised jax.jvp's primal/tangent dtype mismatch) and lands within 1e-4 m of the
    float64 flight after 0.5 s of a step command (the same fixed steps: a shorter
    compile than the adaptive default's)."""
    scene, control = quadrotor(sm.Hover(step=[1.0, 0.0, 0.5]))
    ends = {}
    for dtype in (jnp.float32, jnp.float64):
        q0 = {
            "attitude": jnp.eye(3, dtype=dtype)[None],
            "base": jnp.zeros(3, dtype),
            "spheres": jnp.array([[0.0, 0.0, -1.0]], dtype),
        }
        v0 = jax.tree.map(jnp.zeros_like, q0)
        sol = sm.simulate(scene, (q0, v0), 0.5, solver=sm.Projected(sm.RK4()), dt0=0.01)
        assert {a.dtype for a in jax.tree.leaves(sol.ys)} == {jnp.dtype(dtype)}
        ends[dtype] = sol.ys[0]["base"][-1]
    np.testing.assert_allclose(ends[jnp.float32], ends[jnp.float64], atol=1e-4)
    assert np.max(np.abs(ends[jnp.float64])) > 0.05  # it moved towards the step
    R32 = jnp.eye(3, dtype=jnp.float32)
    z32 = jnp.zeros(3, jnp.float32)
    assert control.wrench(0.3, z32, z32, R32, z32).dtype == jnp.float32


def test_flight_commands_and_drives_are_not_taken_for_one_another():
    """`Rotors` takes a drive, not a flight command (it failed late with a TypeError);
    `GeometricControl` takes a flight command, not a drive, and its check evaluates the
    command's shapes (a function of the wrong shape failed at the first step)."""
    body, cable = sm.RigidBase(MASS, INERTIA), sm.Chain(0.01, 0.3)
    with pytest.raises(ValueError, match="not a flight command: fly Hover") as info:
        sm.Rotors(sm.Hover(), ARM, C_TF)
    assert info.value.field == "command"
    with pytest.raises(ValueError, match="torque must be a vector or a drive, not a flight"):
        sm.BodyTorque(sm.Hover())  # failed at the first step: Hover.__call__() takes 2 ...
    with pytest.raises(ValueError, match=r"\(x_d, b1_d\), two \(3,\) vectors, not a drive"):
        sm.GeometricControl(MASS, INERTIA, command=sm.PDTorque(1.0, 1.0, [0, 0, 1]), **GAINS)
    for command, shapes in (
        (lambda t: jnp.zeros(3), r"\[\(3,\)\]"),
        (lambda t: (jnp.zeros(3), jnp.zeros(2)), r"\[\(3,\), \(2,\)\]"),
    ):
        control = sm.GeometricControl(MASS, INERTIA, command=command, **GAINS)
        with pytest.raises(ValueError, match="it returns shapes " + shapes) as info:
            sm.Scene(body, cable, sm.Rotors(control, ARM, C_TF))
        assert info.value.field == "command.command"


def test_geometric_control_wrench_checks_its_arguments():
    """`wrench` names a misshapen argument (a batched R gave a raw error); lists and
    integers are read as floats."""
    control = sm.GeometricControl(MASS, INERTIA, command=sm.Hover(), g=G, **GAINS)
    z, R = [0.0, 0.0, 0.0], np.eye(3)
    with pytest.raises(ValueError, match=r"wrench: R must have shape \(3, 3\), got \(1, 3, 3\)"):
        control.wrench(0.0, z, z, R[None], z)
    with pytest.raises(ValueError, match=r"wrench: x must have shape \(3,\), got \(2,\)"):
        control.wrench(0.0, z[:2], z, R, z)
    with pytest.raises(ValueError, match=r"wrench: t must have shape \(\), got \(2,\)"):
        control.wrench(jnp.zeros(2), z, z, R, z)
    hover = control.wrench(0, [0, 0, 0], z, R.astype(int).tolist(), z)
    np.testing.assert_allclose(hover, [MASS * G, 0.0, 0.0, 0.0], atol=1e-12)
    # thrust_vector and command_attitude alike (raw broadcasting errors before; a list x an
    # AttributeError)
    with pytest.raises(ValueError, match=r"thrust_vector: x must have shape \(3,\), got \(2,\)"):
        control.thrust_vector(0.0, z[:2], z)
    with pytest.raises(ValueError, match=r"command_attitude: R must have shape \(3, 3\)"):
        control.command_attitude(0.0, z, z, R[:2])
    F, b1 = control.thrust_vector(0, [0, 0, 0], [0, 0, 0])
    np.testing.assert_allclose(F, [0.0, 0.0, MASS * G], atol=1e-12)
    np.testing.assert_allclose(control.command_attitude(0, z, z, R), np.eye(3), atol=1e-12)
