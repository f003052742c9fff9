"""Scenes with a `RigidBase` (a quadrotor-like body carrying a chain from a body point):
the O(n) fast path of R^3 x SO(3) x (S^2)^n against the general path (Hessians of the
scene's own `L`), against a Cartesian + quaternion reference written here (Newton-Euler
with link tensions, scipy), the dense variational step, and bad input."""

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import G, jaxpr_equations
from scipy.integrate import solve_ivp
from test_base_scenes import DENSE_PRIMITIVES, general_twin, max_abs_diff
from test_scenes import RIGID_SCENE, TORQUE, _file

import sphere_mech as sm
from sphere_mech._solvers.discrete_mechanics import substep

INERTIA = np.array([[0.30, 0.02, 0.01], [0.02, 0.40, -0.03], [0.01, -0.03, 0.50]])
ATTACH = np.array([0.10, -0.05, -0.20])
MASSES, LENGTHS = np.array([0.3, 0.2, 0.4]), np.array([0.5, 0.3, 0.4])
BODY_MASS = 1.5


def rigid_scene(*extra, attach=ATTACH):
    return sm.Scene(
        sm.RigidBase(BODY_MASS, INERTIA, attach=attach),
        sm.Chain(MASSES, LENGTHS),
        sm.Gravity(G),
        *extra,
    )


def random_rigid_state(seed, n=3):
    k = jax.random.split(jax.random.PRNGKey(seed), 6)
    s = sm.normalize(jax.random.normal(k[0], (n, 3)))
    R = sm.rotation_matrix(jax.random.normal(k[1], (3,)))
    Omega = jax.random.normal(k[2], (3,))
    q = {"base": jax.random.normal(k[3], (3,)), "spheres": s, "attitude": R[None]}
    v = {
        "base": jax.random.normal(k[4], (3,)),
        "spheres": sm.project(s, jax.random.normal(k[5], (n, 3))),
        "attitude": (R @ sm.hat(Omega))[None],
    }
    return q, v


@pytest.mark.parametrize("attach", [ATTACH, np.zeros(3)], ids=["offset", "centre"])
def test_rigid_base_fast_path_equals_general_path(attach):
    """A rigid body (full inertia tensor) carrying a 3-link chain from a body point (or its
    centre of mass), with forces on the body, its attitude and the chain: the O(n) fast
    path gives the general path's rates (to 1e-12) and inverse Legendre map, with no
    dense solve."""
    scene = rigid_scene(
        sm.JointDamping(0.1),
        sm.TipForce([0.0, 1.0, 0.5]),
        sm.BaseForce(sm.Harmonic([0.0, 1.0, 20.0], 2.0)),
        sm.BodyTorque(sm.Harmonic([0.1, -0.2, 0.05], 3.0)),
        attach=attach,
    )
    assert scene.space == sm.chain_space(3, 3, attitude=True)
    assert scene.space.factors == {
        "attitude": sm.Rotations(1),
        "base": sm.Euclidean(3),
        "spheres": sm.Spheres(3),
    }
    q, v = random_rigid_state(1)
    twin = general_twin(scene)
    for t in (0.1, 0.3):
        assert max_abs_diff(scene.rates(t, (q, v), None), twin.rates(t, (q, v), None)) < 1e-12
    p = scene.momentum(0.3, q, v)
    assert max_abs_diff(scene.velocity_from_momentum(0.3, q, p)[0], v) < 1e-13
    assert abs(float(scene.energy(0.3, q, v) - twin.energy(0.3, q, v))) < 1e-12
    eqns = jaxpr_equations(jax.make_jaxpr(lambda y: scene.rates(0.3, y, None))((q, v)).jaxpr)
    assert not DENSE_PRIMITIVES & {e.primitive.name for e in eqns}


def _quaternion_matrix(w, x, y, z):
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _quaternion_of(R):
    w = 0.5 * np.sqrt(1.0 + np.trace(R))  # the rotations here are far from pi
    return np.array([w, R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / [
        1,
        *[4 * w] * 3,
    ]


def cartesian_reference(q, v, ts):
    """The same body and chain in Cartesian coordinates: the body's centre `x`, unit
    quaternion and body `Omega`; the masses' positions `X_i`; link tensions `lam_i` from
    the acceleration-level constraints `|X_i - X_{i-1}|^2 = l_i^2` (`X_0` the joint `x + R d`),
    solved at every evaluation. Newton-Euler, gravity, scipy DOP853 at 1e-12."""
    n, J, Jinv, d = len(MASSES), INERTIA, np.linalg.inv(INERTIA), ATTACH
    gravity = np.array([0.0, 0.0, -G])

    def accelerations(x_dot, Omega, R, X, Xdot, lam):
        p = x_dot[0] + R @ d  # x_dot = (x, xdot)
        links = np.diff(np.vstack([p, X]), axis=0)  # e_i = X_i - X_{i-1}
        pull = lam[:, None] * links  # link i pulls X_{i-1} towards X_i, X_i back
        F_body = BODY_MASS * gravity + pull[0]
        xdd = F_body / BODY_MASS
        Omegadot = Jinv @ (np.cross(J @ Omega, Omega) + np.cross(d, R.T @ pull[0]))
        F = MASSES[:, None] * gravity - pull + np.vstack([pull[1:], np.zeros((1, 3))])
        Xdd = F / MASSES[:, None]
        pdd = xdd + R @ (np.cross(Omegadot, d) + np.cross(Omega, np.cross(Omega, d)))
        return xdd, Omegadot, Xdd, pdd, links

    def rhs(t, y):
        x, xd, quat, Omega = y[:3], y[3:6], y[6:10], y[10:13]
        X, Xd = y[13 : 13 + 3 * n].reshape(n, 3), y[13 + 3 * n :].reshape(n, 3)
        R = _quaternion_matrix(*quat / np.linalg.norm(quat))
        pd = xd + R @ np.cross(Omega, d)
        rel_v = np.diff(np.vstack([pd, Xd]), axis=0)

        def constraint(lam):  # e_i . (Xdd_i - Xdd_{i-1}) + |edot_i|^2, affine in lam
            _, _, Xdd, pdd, links = accelerations((x, xd), Omega, R, X, Xd, lam)
            return np.sum(links * np.diff(np.vstack([pdd, Xdd]), axis=0), -1) + np.sum(rel_v**2, -1)

        c0 = constraint(np.zeros(n))
        A = np.stack([constraint(np.eye(n)[i]) - c0 for i in range(n)], axis=1)
        lam = np.linalg.solve(A, -c0)
        xdd, Omegadot, Xdd, _, _ = accelerations((x, xd), Omega, R, X, Xd, lam)
        w, *u = quat
        quat_dot = 0.5 * np.array(
            [-np.dot(u, Omega), *(w * Omega + np.cross(u, Omega))]
        )  # q' = q (0, Omega)/2
        return np.concatenate([xd, xdd, quat_dot, Omegadot, Xd.ravel(), Xdd.ravel()])

    R0 = np.asarray(q["attitude"][0])
    Omega0 = np.asarray(sm.vee(R0.T @ v["attitude"][0]))
    x0, xd0 = np.asarray(q["base"]), np.asarray(v["base"])
    p0, pd0 = x0 + R0 @ d, xd0 + R0 @ np.cross(Omega0, d)
    X0 = p0 + np.cumsum(LENGTHS[:, None] * np.asarray(q["spheres"]), axis=0)
    Xd0 = pd0 + np.cumsum(LENGTHS[:, None] * np.asarray(v["spheres"]), axis=0)
    y0 = np.concatenate([x0, xd0, _quaternion_of(R0), Omega0, X0.ravel(), Xd0.ravel()])
    sol = solve_ivp(rhs, (ts[0], ts[-1]), y0, "DOP853", t_eval=ts, rtol=1e-12, atol=1e-12)
    y = sol.y.T
    R = np.stack([_quaternion_matrix(*u / np.linalg.norm(u)) for u in y[:, 6:10]])
    return y[:, :3], R, y[:, 13 : 13 + 3 * n].reshape(len(ts), n, 3)


def test_rigid_base_against_cartesian_quaternion_reference():
    """A tumbling body swinging a 3-link chain from an offset point, 1 s under gravity:
    the centre of mass, attitude and masses follow the Cartesian + quaternion reference to
    1e-8 (values between steps too, at `SaveAt(ts)`), energy to 1e-9."""
    scene = rigid_scene()
    q, v = random_rigid_state(3)
    ts = np.linspace(0.0, 1.0, 11)
    sol = sm.simulate(scene, (q, v), 1.0, rtol=1e-12, atol=1e-12, saveat=diffrax.SaveAt(ts=ts))
    x_ref, R_ref, X_ref = cartesian_reference(q, v, ts)
    qs = sol.ys[0]
    assert np.max(np.abs(qs["base"] - x_ref)) < 1e-8
    assert np.max(np.abs(qs["attitude"][:, 0] - R_ref)) < 1e-8
    assert np.max(np.abs(jax.vmap(scene.positions)(qs) - X_ref)) < 1e-8
    energy = jax.vmap(lambda q_, v_: scene.energy(0.0, q_, v_))(*sol.ys)
    assert np.max(np.abs(energy - energy[0])) < 1e-9 * (1 + abs(float(energy[0])))
    moved = np.max(np.abs(R_ref[-1] - R_ref[0]))
    assert moved > 0.1  # it tumbled


def angular_momentum_rate(scene, body, q, v):
    """`dL/dt` of a scene on the `RigidBase` `body` (about the origin), along its rates."""

    def angular_momentum(q, v):
        x, xdot = jax.jvp(scene.points, (q,), (v,))
        R, Omega = q["attitude"][0], sm.vee(q["attitude"][0].T @ v["attitude"][0])
        return scene.point_masses() @ jnp.cross(x, xdot) + R @ body.inertia @ Omega

    return jax.jvp(angular_momentum, (q, v), scene.rates(0.0, (q, v), None))[1]


def largest_force(forces) -> float:
    return max(float(jnp.max(jnp.abs(f))) for f in jax.tree.leaves(forces))


def test_the_first_joint_is_on_the_body():
    """The first link's joint is on the body, which takes the reaction of `JointDamping`
    and `BaseTorque` there (they acted against the world before: with no gravity the
    total angular momentum changed by the torque, and a link turning with the body was
    damped). The part of the body's rotation along the link is free (its spin)."""
    k = jax.random.split(jax.random.PRNGKey(11), 6)
    R, Omega = sm.rotation_matrix(jax.random.normal(k[0], (3,))), jax.random.normal(k[1], (3,))
    s = sm.normalize(jax.random.normal(k[2], (1, 3)))
    body, link = sm.RigidBase(BODY_MASS, INERTIA, attach=ATTACH), sm.Chain(0.3, 0.5)

    def state(sdot):
        q = {"base": jax.random.normal(k[3], (3,)), "spheres": s, "attitude": R[None]}
        v = {"base": jax.random.normal(k[4], (3,)), "spheres": sdot}
        return q, v | {"attitude": (R @ sm.hat(Omega))[None]}

    damped = sm.Scene(body, link, sm.JointDamping(0.5))
    turning = damped.forces(0.0, *state(jnp.cross(R @ Omega, s)), None)  # turns with it
    assert largest_force(turning) < 1e-14
    q, v = state(sm.project(s, jax.random.normal(k[5], (1, 3))))
    across = sm.project(s, jnp.cross(s, v["spheres"]) - R @ Omega)
    np.testing.assert_allclose(damped.power(0.0, q, v, None), -0.5 * jnp.sum(across**2), 1e-13)

    scene = sm.Scene(body, link, sm.JointDamping(0.5), sm.BaseTorque([0.3, -0.1, 0.2]))

    assert float(jnp.max(jnp.abs(angular_momentum_rate(scene, body, q, v)))) < 1e-13


def test_joint_damping_is_internal_along_the_chain():
    """`JointDamping` in every joint of a chain on a `RigidBase` (no gravity) conserves the
    total angular momentum: the links' free spins take the axial torques (before, the
    axial parts of the joints between links were dropped: |dL/dt| was 1.24 here), and a
    chain turning rigidly with the body is not damped."""
    body, chain = sm.RigidBase(BODY_MASS, INERTIA, attach=ATTACH), sm.Chain(MASSES, LENGTHS)
    scene = sm.Scene(body, chain, sm.JointDamping(jnp.array([0.3, 0.5, 0.2])))
    q, v = random_rigid_state(3)

    assert float(jnp.max(jnp.abs(angular_momentum_rate(scene, body, q, v)))) < 1e-13
    assert float(scene.power(0.0, q, v, None)) < -1e-3  # it damps
    R, Omega = q["attitude"][0], sm.vee(q["attitude"][0].T @ v["attitude"][0])
    rigid = v | {"spheres": jnp.cross(R @ Omega, q["spheres"])}
    assert largest_force(scene.forces(0.0, q, rigid, None)) < 1e-14


def test_chain_offset_on_a_rigid_base_is_refused(tmp_path):
    """`Chain(base=...)` on a `RigidBase` was a world-axes shift of every position, not a
    body point (the chain pulled at `attach`, drawn elsewhere): refused in Python and in a
    scene file with the same words, pointing to `attach`."""
    words = r"hangs from the body point attach: give the offset as RigidBase\(attach=...\)"
    with pytest.raises(ValueError, match=words + r".*got \[0.3, 0.0, 0.0\]$"):
        sm.Scene(sm.RigidBase(1.0, INERTIA), sm.Chain(0.2, 0.5, base=[0.3, 0.0, 0.0], links=1))
    path = _file(
        tmp_path, template=RIGID_SCENE, replace={"links = 3": "links = 3\nbase = [0.3, 0, 0]"}
    )
    with pytest.raises(sm.SceneFileError, match=words):
        sm.load_scene(path)


def test_variational_step_on_rigid_base_fast_path():
    """`Variational` on a rigid body carrying a chain from a body point: the O(n) chord
    iteration (the body's 3x3 block in the multiplier solve) takes the same step as the
    general Newton path (to 1e-10), with `R^T R = I` to rounding."""
    scene = rigid_scene(sm.JointDamping(0.05), sm.BodyTorque([0.1, 0.0, -0.2]))
    y = random_rigid_state(5)
    t = jnp.asarray(0.1)
    steps = [
        substep(scene, t, 0.02, *y, scene.rates(t, y, None), None, 1e-12, 32, fast)
        for fast in (True, False)
    ]
    assert all(result == diffrax.RESULTS.successful for _, _, result in steps)
    assert max_abs_diff(steps[0][0], steps[1][0]) < 1e-10
    assert max_abs_diff(steps[0][0], y) > 1e-3  # it moved
    R = steps[0][0][0]["attitude"][0]
    assert np.max(np.abs(R.T @ R - np.eye(3))) < 1e-15


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: sm.RigidBase(1.0, [1.0, 1.0, 3.0]), "principal moments must satisfy J1 \\+ J2"),
        (
            lambda: sm.RigidBase(1.0, [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
            "inertia must be symmetric positive-definite",
        ),
        (
            lambda: sm.RigidBase(1.0, [1.0, -1.0, 1.0]),
            "inertia must be symmetric positive-definite",
        ),
        (lambda: sm.RigidBase(1.0, [1.0, 1.0]), "inertia must be three principal moments"),
        (lambda: sm.RigidBase(-1.0, [1.0, 1.0, 1.0]), "mass must be > 0"),
        (
            lambda: sm.RigidBase(1.0, [1.0, 1.0, 1.0], attach=[0.0, 1.0]),
            "attach must be a \\(3,\\)",
        ),
        (
            lambda: sm.Scene(sm.RigidBase(1.0, [1.0] * 3), sm.Particles(1.0, 1.0, count=2)),
            "a RigidBase carries one Chain",
        ),
        (
            lambda: sm.Scene(
                sm.RigidBase(1.0, [1.0] * 3), sm.Base(1.0), sm.Chain(1.0, 1.0, links=2)
            ),
            "at most one base",
        ),
        (
            lambda: sm.Scene(sm.Chain(1.0, 1.0, links=2), sm.BodyTorque([0.0, 0.0, 1.0])),
            "BodyTorque needs a RigidBase",
        ),
        (
            lambda: sm.Scene(
                sm.RigidBase(1.0, [1.0] * 3), sm.Chain(1.0, 1.0, links=1), sm.BaseForce([1.0] * 2)
            ),
            r"force must have 3 components, one per axis of the RigidBase, got shape \(2,\)",
        ),
    ],
)
def test_rigid_base_rejects_bad_input(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_rigid_base_scene_file(tmp_path):
    """A file builds the Python scene, and its initial attitude and body angular
    velocity are the state's `R` and `Rdot = R hat(Omega)`."""
    spec = sm.load_scene(
        _file(tmp_path, template=RIGID_SCENE, extra=TORQUE.format("[0.0, 0.0, 1e-3]"))
    )
    python = sm.Scene(
        sm.RigidBase(0.5, [0.00557, 0.00557, 0.0105], attach=[0.0, 0.0, -0.05]),
        sm.Chain(0.02, 0.2, links=3),
        sm.Gravity(),
        sm.BodyTorque([0.0, 0.0, 1e-3]),
    )
    assert max_abs_diff(spec.scene, python) == 0.0
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    q, v = spec.y0
    assert np.array_equal(q["attitude"][0], R)
    assert np.allclose(v["attitude"][0], R @ sm.hat(jnp.array([0.1, 0.2, 0.3])), atol=1e-15)
    assert np.array_equal(q["base"], np.zeros(3))


def test_rigid_base_initial_attitude_must_be_a_rotation(tmp_path):
    bad = "attitude = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]"  # det -1
    path = _file(
        tmp_path,
        template=RIGID_SCENE,
        replace={"attitude = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]": bad},
    )
    message = (
        r"initial.attitude: the attitude is not a rotation: .* Got \[\[1.0, 0.0, 0.0\], "
        r"\[0.0, 1.0, 0.0\], \[0.0, 0.0, -1.0\]\]\.$"
    )
    with pytest.raises(sm.SceneFileError, match=message):
        sm.load_scene(path)


def test_rigid_base_pictures_draw_its_joint_and_arms():
    """`drawn_points` adds the joint and the arms' ends; the skeleton hangs the chain from
    the joint and draws the arms through the centre of mass (`plot.png`, animations)."""
    from sphere_mech._drawing import skeleton

    scene = rigid_scene()
    q, v = random_rigid_state(4)
    x = np.asarray(scene.drawn_points(q))
    skel = skeleton(scene, x.shape[0])
    R, centre = np.asarray(q["attitude"][0]), np.asarray(q["base"])
    assert x.shape == (1 + 3 + 1 + 5, 3)
    np.testing.assert_allclose(x[4], centre + R @ ATTACH, atol=1e-15)  # the joint
    np.testing.assert_array_equal(skel.links[0], [4, 1, 2, 3])  # joint, then the masses
    pts = skel.points(x)
    for line, axis in zip(skel.frame, (R[:, 0], R[:, 1], R[:, 2]), strict=True):
        assert line[len(line) // 2 if len(line) == 3 else 0] == 0  # through the centre
        np.testing.assert_allclose(
            pts[line[-1]] - centre, 0.2 * axis * (1 if len(line) == 2 else -1), atol=1e-15
        )
