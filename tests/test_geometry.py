"""Geometry helpers of (S^2)^n."""

import jax
import jax.numpy as jnp
import jax.scipy.linalg
import numpy as np
import pytest

import sphere_mech as sm


@pytest.fixture(scope="module")
def points():
    q = sm.random_points(jax.random.PRNGKey(0), 6)
    poles = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1e-9, 0.0, -1.0]])
    return jnp.concatenate([q, sm.normalize(poles)])


def test_hat(getkey):
    x, y = jax.random.normal(getkey(), (2, 5, 3))
    np.testing.assert_allclose(sm.hat(x) @ y[..., None], jnp.cross(x, y)[..., None], atol=1e-15)
    np.testing.assert_allclose(sm.hat(x), -jnp.swapaxes(sm.hat(x), -1, -2))


def test_normalize_project_retract(getkey):
    x, v = jax.random.normal(getkey(), (2, 4, 3))
    q = sm.normalize(x)
    np.testing.assert_allclose(jnp.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    assert float(sm.constraint_error(q)) < 1e-15
    assert float(sm.constraint_error(x)) > 0.01
    np.testing.assert_allclose(jnp.sum(q * sm.project(q, v), -1), 0.0, atol=1e-15)
    q2, v2 = sm.retract(2.0 * x, v)
    np.testing.assert_allclose(q2, q, atol=1e-15)
    np.testing.assert_allclose(v2, sm.project(q, v), atol=1e-15)


def test_tangent_basis_orthonormal_right_handed(points):
    T = sm.tangent_basis(points)
    assert T.shape == (points.shape[0], 3, 2)
    gram = jnp.einsum("ica,icb->iab", T, T)
    np.testing.assert_allclose(gram, jnp.broadcast_to(jnp.eye(2), gram.shape), atol=1e-14)
    np.testing.assert_allclose(jnp.einsum("ic,ica->ia", points, T), 0.0, atol=1e-14)
    np.testing.assert_allclose(jnp.cross(T[..., 0], T[..., 1]), points, atol=1e-14)
    # points slightly off the sphere are normalized first
    np.testing.assert_allclose(sm.tangent_basis(1.001 * points), T, atol=1e-14)


def test_rotate_and_rotation_matrix(getkey):
    w = jax.random.normal(getkey(), (4, 3))
    w = w.at[0].set(1e-5 * w[0]).at[1].set(0.0)  # series branch and exact zero
    x = jax.random.normal(getkey(), (4, 3))
    R = sm.rotation_matrix(w)
    expected = jax.vmap(jax.scipy.linalg.expm)(sm.hat(w))
    np.testing.assert_allclose(R, expected, atol=1e-13)
    np.testing.assert_allclose(sm.rotate(w, x), (R @ x[..., None])[..., 0], atol=1e-13)
    np.testing.assert_allclose(jnp.linalg.det(R), 1.0, atol=1e-13)
    # smooth derivatives through the small-angle branch
    g0 = jax.grad(lambda s: jnp.sum(sm.rotate(s * w[2], x[2])))(0.0)
    np.testing.assert_allclose(g0, jnp.sum(jnp.cross(w[2], x[2])), rtol=1e-12)


def test_sphere_exp_follows_great_circles(points, getkey):
    v = sm.project(points, jax.random.normal(getkey(), points.shape))
    speed = jnp.linalg.norm(v, axis=-1, keepdims=True)
    expected = jnp.cos(speed) * points + jnp.sin(speed) * v / speed
    got = sm.sphere_exp(points, v)
    np.testing.assert_allclose(got, expected, atol=1e-13)
    assert float(sm.constraint_error(got)) < 1e-14
    np.testing.assert_allclose(sm.sphere_exp(points, 0.0 * v), points, atol=1e-15)


def test_random_points_and_states(getkey):
    q = sm.random_points(getkey(), 1000)
    assert q.shape == (1000, 3)
    assert float(sm.constraint_error(q)) < 1e-14
    np.testing.assert_allclose(jnp.mean(q, axis=0), 0.0, atol=0.1)  # roughly uniform
    q, v = sm.random_state(getkey(), 5, speed=3.0, dtype=jnp.float32)
    assert q.dtype == v.dtype == jnp.float32
    assert float(jnp.max(jnp.abs(jnp.sum(q * v, -1)))) < 1e-5
    assert float(jnp.mean(jnp.linalg.norm(v, axis=-1))) > 1.0


def test_shapes_and_counts_are_checked():
    """A vector or matrix of the wrong size raises (it used to give a 3x3 matrix or a
    vector from the first entries); so does a count that is not a positive integer, and a
    speed that is not a finite number >= 0."""
    with pytest.raises(ValueError, match=r"hat: x must have shape \(\.\.\., 3\), got \(4,\)"):
        sm.hat(jnp.ones(4))
    with pytest.raises(ValueError, match=r"rotation_matrix: w must have shape \(\.\.\., 3\)"):
        sm.rotation_matrix(jnp.ones((5, 2)))
    with pytest.raises(ValueError, match=r"vee: M must have shape \(\.\.\., 3, 3\), got \(2, 2\)"):
        sm.vee(jnp.ones((2, 2)))
    for n in (0, -1, 2.0):
        with pytest.raises(ValueError, match="random_state: n must be a positive integer"):
            sm.random_state(jax.random.PRNGKey(0), n)
        with pytest.raises(ValueError, match="random_points: n must be a positive integer"):
            sm.random_points(jax.random.PRNGKey(0), n)
    assert sm.random_state(jax.random.PRNGKey(0), np.int64(2))[0].shape == (2, 3)
    for speed in (np.nan, np.inf, -1.0, "1"):  # NaN velocities before
        with pytest.raises(ValueError, match="random_state: speed must be a finite number >= 0"):
            sm.random_state(jax.random.PRNGKey(0), 2, speed=speed)
    assert jnp.all(sm.random_state(jax.random.PRNGKey(0), 2, speed=0.0)[1] == 0)
    for dtype in (jnp.int32, bool):  # JAX's error named `normal`, not the argument
        with pytest.raises(ValueError, match="^random_state: dtype must be a floating dtype"):
            sm.random_state(jax.random.PRNGKey(0), 2, dtype=dtype)
        with pytest.raises(ValueError, match="^random_points: dtype must be a floating dtype"):
            sm.random_points(jax.random.PRNGKey(0), 2, dtype=dtype)
    assert sm.vee(sm.hat(jnp.ones((4, 3)))).shape == (4, 3)


def test_wrong_shapes_are_named_and_lists_are_read():
    """A `(..., 2)` or `(..., 4)` vector gave a garbage tangent basis (`(1, 3, 2)` from a
    `(1, 2)`), a zero constraint error, a projection, or a raw JAX error; the conversions
    broadcast `q (2, 3)` against `omega (3,)`; `hat`, `vee`, `rotation_matrix` raised
    `TypeError` on lists. Every helper now names the argument and the expected shape."""
    q2 = jnp.array([[0.6, 0.8]])
    q, v = sm.random_state(jax.random.PRNGKey(0), 2)
    vectors = {
        "normalize": lambda x: sm.normalize(x),
        "constraint_error": lambda x: sm.constraint_error(x),
        "tangent_basis": lambda x: sm.tangent_basis(x),
        "project": lambda x: sm.project(x, x),
        "retract": lambda x: sm.retract(x, x),
        "sphere_exp": lambda x: sm.sphere_exp(x, x),
    }
    for fn, call in vectors.items():
        for bad in (q2, jnp.ones((1, 4))):
            with pytest.raises(ValueError, match=rf"^{fn}: q must have shape \(\.\.\., 3\), got"):
                call(bad)
    with pytest.raises(ValueError, match=r"^rotate: w must have shape \(\.\.\., 3\), got \(4, 2\)"):
        sm.rotate(jnp.ones((4, 2)), jnp.ones((4, 2)))
    with pytest.raises(
        ValueError, match=r"^project: v must have shape \(\.\.\., 3\), got \(3, 2\)"
    ):
        sm.project(q, jnp.ones((3, 2)))
    conversions = {
        "omega_from_qdot": (sm.omega_from_qdot, "qdot"),
        "qdot_from_omega": (sm.qdot_from_omega, "omega"),
        "pi_from_mu": (sm.pi_from_mu, "mu"),
        "mu_from_pi": (sm.mu_from_pi, "pi"),
    }
    for fn, (convert, name) in conversions.items():
        same = rf"^{fn}: {name} must have the same shape as q, \(2, 3\), got \(3,\)\.$"
        with pytest.raises(ValueError, match=same):
            convert(q, v[0])
        with pytest.raises(ValueError, match=rf"^{fn}: q must have shape \(\.\.\., 3\), got"):
            convert(q2, q2)
        np.testing.assert_array_equal(convert(q.tolist(), v.tolist()), convert(q, v))
    # lists are read as arrays, as `_check_trailing` says
    w = [0.1, 0.2, 0.3]
    np.testing.assert_array_equal(sm.hat(w), sm.hat(jnp.array(w)))
    np.testing.assert_array_equal(sm.rotation_matrix(w), sm.rotation_matrix(jnp.array(w)))
    M = [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0], [6.0, 7.0, 8.0]]
    np.testing.assert_array_equal(sm.vee(M), sm.vee(jnp.array(M)))
    np.testing.assert_array_equal(
        sm.rotate(w, [1.0, 0.0, 0.0]), sm.rotate(jnp.array(w), jnp.eye(3)[0])
    )
    np.testing.assert_array_equal(sm.tangent_basis(q.tolist()), sm.tangent_basis(q))
    np.testing.assert_array_equal(sm.sphere_exp(q.tolist(), v.tolist()), sm.sphere_exp(q, v))
    assert float(sm.constraint_error([[2.0, 0.0, 0.0]])) == 1.0
    # the checks are static: traced arguments pass through jit and vmap unchanged
    np.testing.assert_allclose(jax.jit(sm.tangent_basis)(q), sm.tangent_basis(q), atol=1e-15)
    np.testing.assert_allclose(jax.vmap(sm.omega_from_qdot)(q, v), jnp.cross(q, v), atol=1e-15)


def test_nearest_rotation_converges_from_any_scale():
    """Plain Newton left 8.9e-3 after its 8 steps from singular values (1, 1, 0.01) and gave
    1.012 I from 0.01 I or 100 I; the scaled iteration reaches the SVD's polar factor."""
    R0 = np.asarray(sm.rotation_matrix(jnp.array([0.3, -1.2, 0.7])))
    A = np.stack(
        [
            R0 @ np.diag([1.0, 1.0, 0.01]),
            R0 @ np.diag([1e4, 1.0, 1e-6]),
            0.01 * np.eye(3),
            100.0 * np.eye(3),
            R0 + 0.5 * np.random.default_rng(0).standard_normal((3, 3)) @ R0,
        ]
    )
    A[4] *= np.sign(np.linalg.det(A[4]))
    U, _, Vt = np.linalg.svd(A)
    got = sm.nearest_rotation(jnp.asarray(A))
    assert float(jnp.max(jnp.abs(got - U @ Vt))) < 1e-14
    assert (
        float(jnp.max(jnp.abs(sm.nearest_rotation(jnp.asarray(A[:1]), 5) - U[:1] @ Vt[:1]))) < 1e-14
    )
    np.testing.assert_array_equal(sm.nearest_rotation(-jnp.eye(3)), -jnp.eye(3))
    # differentiable: the Jacobian at a far matrix is the polar factor's (central differences)
    B, h = A[0], 1e-6
    E = np.eye(9).reshape(9, 3, 3)
    polar = lambda M: np.linalg.svd(M)[0] @ np.linalg.svd(M)[2]
    fd = np.stack([(polar(B + h * e) - polar(B - h * e)) / (2 * h) for e in E], -1)
    jac = jax.jacfwd(sm.nearest_rotation)(jnp.asarray(B)).reshape(3, 3, 9)
    np.testing.assert_allclose(jac, fd, atol=1e-8)
