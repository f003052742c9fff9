"""Geometry of (S^2)^n: hat map, projections, tangent bases, exponential maps.

Points are `(n, 3)` arrays of unit vectors; tangent vectors are `(n, 3)` arrays with
`q_i . v_i = 0`. Every function here also accepts a single `(3,)` vector.
"""

import jax
import jax.numpy as jnp
import jax.random as jr

from ._custom_types import Points, Scalar, Tangents


def hat(x: jax.Array) -> jax.Array:
    """The hat map: `hat(x) @ y == cross(x, y)`.

    **Arguments:**
    - `x`: vectors, shape `(..., 3)`.

    **Returns:** the skew-symmetric matrices, shape `(..., 3, 3)`.
    """
    x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
    z = jnp.zeros_like(x1)
    rows = [
        jnp.stack([z, -x3, x2], axis=-1),
        jnp.stack([x3, z, -x1], axis=-1),
        jnp.stack([-x2, x1, z], axis=-1),
    ]
    return jnp.stack(rows, axis=-2)


def dot(a: jax.Array, b: jax.Array) -> jax.Array:
    """Row-wise dot product, keeping the last axis: `(..., 3), (..., 3) -> (..., 1)`."""
    return jnp.sum(a * b, axis=-1, keepdims=True)


def normalize(q: jax.Array) -> jax.Array:
    """Scale each row of `q` to unit length.

    **Arguments:**
    - `q`: nonzero vectors, shape `(..., 3)`.

    **Returns:** `q_i / |q_i|`, the same shape.
    """
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def project(q: Points, v: jax.Array) -> Tangents:
    """Remove from each `v_i` its component along `q_i`: `(I - q_i q_i^T) v_i`.

    **Arguments:**
    - `q`: unit vectors, `(n, 3)` (or `(3,)`).
    - `v`: vectors of the same shape.

    **Returns:** the tangent parts of `v`, the same shape.
    """
    return v - dot(q, v) * q


def retract(q: jax.Array, v: jax.Array) -> tuple[Points, Tangents]:
    """Put a state back on the tangent bundle: normalize `q`, make `v` tangent to it.

    **Arguments:**
    - `q`: nonzero vectors, `(n, 3)`, near the spheres.
    - `v`: vectors of the same shape (a velocity, angular velocity or momentum).

    **Returns:** `(q / |q|, v projected on the tangent planes at the normalized q)`.
    """
    q = normalize(q)
    return q, project(q, v)


def tangent_basis(q: Points) -> jax.Array:
    """An orthonormal basis of each tangent plane.

    Uses the branch-free construction of Duff et al. (2017); columns `b1, b2` satisfy
    `b1 x b2 = q_i`. `q` is normalized first, so points slightly off the sphere are fine.

    **Arguments:**
    - `q`: points, `(n, 3)` (or `(3,)`).

    **Returns:** the bases, `(n, 3, 2)` (or `(3, 2)`): column `k` of `[i]` is `b_k` at `q_i`.
    """
    q = normalize(q)
    x, y, z = q[..., 0], q[..., 1], q[..., 2]
    s = jnp.where(z >= 0, 1.0, -1.0).astype(q.dtype)
    a = -1.0 / (s + z)
    b = x * y * a
    b1 = jnp.stack([1.0 + s * x * x * a, s * b, -s * x], axis=-1)
    b2 = jnp.stack([b, s + y * y * a, -y], axis=-1)
    return jnp.stack([b1, b2], axis=-1)


def _sinc_and_cosc(theta2: jax.Array) -> tuple[jax.Array, jax.Array]:
    """`sin(t)/t` and `(1 - cos t)/t^2` as functions of `t^2`, smooth (and with smooth
    derivatives) at zero."""
    small = theta2 < 1e-4
    safe2 = jnp.where(small, 1.0, theta2)
    t = jnp.sqrt(safe2)
    sinc = jnp.where(small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, jnp.sin(t) / t)
    cosc = jnp.where(small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, (1.0 - jnp.cos(t)) / safe2)
    return sinc, cosc


def rotate(w: jax.Array, x: jax.Array) -> jax.Array:
    """Apply the rotation `exp(hat(w_i))` to each `x_i` (Rodrigues' formula).

    **Arguments:**
    - `w`: rotation vectors (axis times angle in rad), `(..., 3)`.
    - `x`: vectors to rotate, same shape.

    **Returns:** the rotated vectors, same shape; smooth (and differentiable) at `w = 0`.
    """
    sinc, cosc = _sinc_and_cosc(jnp.sum(w * w, axis=-1, keepdims=True))
    wx = jnp.cross(w, x)
    return x + sinc * wx + cosc * jnp.cross(w, wx)


def left_jacobian(w: jax.Array, b: jax.Array) -> jax.Array:
    """`J(w) b`, row-wise over `(..., 3)`, with `J(w) = sum_k hat(w)^k / (k + 1)! =
    I + (1 - cos t)/t^2 hat(w) + (t - sin t)/t^3 hat(w)^2` (`t = |w|`) the left
    Jacobian of `SO(3)`: the exponential of `(w, b)` in `se(3)` is the rotation
    `exp(hat(w))` followed by the translation `J(w) b`. Smooth at `w = 0`."""
    theta2 = jnp.sum(w * w, axis=-1, keepdims=True)
    sinc, cosc = _sinc_and_cosc(theta2)
    small = theta2 < 1e-4
    safe2 = jnp.where(small, 1.0, theta2)
    # (t - sin t)/t^3 = (1 - sinc)/t^2, by its series where that cancels.
    sinc3 = jnp.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (1.0 - sinc) / safe2)
    wb = jnp.cross(w, b)
    return b + cosc * wb + sinc3 * jnp.cross(w, wb)


def dexpinv_so3(w: jax.Array, k: jax.Array) -> jax.Array:
    """The inverse of the derivative of the exponential of `so(3)`, in closed form:
    `dexp_w^{-1}(k) = k - (w x k)/2 + c(t) w x (w x k)`, `c(t) = (1 - (t/2) cot(t/2))/t^2`,
    `t = |w|` (the series `sum_j B_j/j! ad_w^j k` summed, with the Bernoulli numbers
    `B_j`; valid for `t < 2 pi`). Row-wise over `(..., 3)`; smooth at `w = 0`."""
    theta2 = jnp.sum(w * w, axis=-1, keepdims=True)
    small = theta2 < 1e-2
    safe2 = jnp.where(small, 1.0, theta2)
    half = 0.5 * jnp.sqrt(safe2)
    series = 1 / 12 + theta2 / 720 + theta2**2 / 30240 + theta2**3 / 1209600
    c = jnp.where(small, series, (1.0 - half / jnp.tan(half)) / safe2)
    wk = jnp.cross(w, k)
    return k - 0.5 * wk + c * jnp.cross(w, wk)


def rotation_matrix(w: jax.Array) -> jax.Array:
    """`exp(hat(w))` as a rotation matrix (Rodrigues' formula).

    **Arguments:**
    - `w`: rotation vectors (axis times angle in rad), `(..., 3)`.

    **Returns:** the rotation matrices, `(..., 3, 3)`.
    """
    sinc, cosc = _sinc_and_cosc(jnp.sum(w * w, axis=-1))
    W = hat(w)
    eye = jnp.eye(3, dtype=w.dtype)
    return eye + sinc[..., None, None] * W + cosc[..., None, None] * (W @ W)


def sphere_exp(q: Points, v: Tangents) -> Points:
    """The exponential map of the round sphere: follow the great circle from `q_i`
    with initial velocity `v_i` for unit time. Equals `rotate(cross(q, v), q)`.

    **Arguments:**
    - `q`: points, `(n, 3)` unit vectors.
    - `v`: tangent vectors at `q` (`q_i . v_i = 0`), same shape.

    **Returns:** the end points, `(n, 3)` unit vectors.
    """
    return rotate(jnp.cross(q, v), q)


def constraint_error(q: jax.Array) -> Scalar:
    """The distance of a configuration from (S^2)^n.

    **Arguments:**
    - `q`: vectors, `(n, 3)` (or with leading axes, e.g. a trajectory `(T, n, 3)`).

    **Returns:** the scalar `max_i | |q_i| - 1 |` over every point.
    """
    return jnp.max(jnp.abs(jnp.linalg.norm(q, axis=-1) - 1.0))


def random_points(key: jax.Array, n: int, *, dtype=None) -> Points:
    """Independent, uniformly distributed points on the unit sphere.

    **Arguments:**
    - `key`: a JAX PRNG key.
    - `n`: the number of points.
    - `dtype`: the floating dtype (default JAX's, float64 with x64 enabled).

    **Returns:** an `(n, 3)` array of unit vectors.
    """
    return normalize(jr.normal(key, (n, 3), dtype=dtype))


def random_state(
    key: jax.Array, n: int, *, speed: float = 1.0, dtype=None
) -> tuple[Points, Tangents]:
    """A random state `(q, v)` on the tangent bundle of (S^2)^n.

    `q` is uniform on each sphere; `v` is a Gaussian tangent vector. `v` can equally be
    read as an angular velocity (`q_i . omega_i = 0`) or a momentum.

    **Arguments:**
    - `key`: a JAX PRNG key.
    - `n`: the number of spheres.
    - `speed`: standard deviation of `v` per tangent direction.
    - `dtype`: the floating dtype (default JAX's).

    **Returns:** `(q, v)`, two `(n, 3)` arrays with `|q_i| = 1` and `q_i . v_i = 0`.
    """
    kq, kv = jr.split(key)
    q = random_points(kq, n, dtype=dtype)
    v = project(q, speed * jr.normal(kv, (n, 3), dtype=dtype))
    return q, v


def vee(M: jax.Array) -> jax.Array:
    """The inverse of `hat` on the skew part: `vee(M) = w` with `hat(w) = (M - M^T)/2`.

    **Arguments:**
    - `M`: matrices, `(..., 3, 3)`.

    **Returns:** vectors, `(..., 3)`.
    """
    return 0.5 * jnp.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]],
        axis=-1,
    )


def nearest_rotation(R: jax.Array, iterations: int = 8) -> jax.Array:
    """The rotation nearest to each `R_j` in the Frobenius norm (the orthogonal factor of
    its polar decomposition), by Newton's iteration `X <- (X + X^-T) / 2`: quadratic
    convergence, differentiable (unlike an SVD at a rotation's repeated singular values).

    **Arguments:**
    - `R`: matrices with positive determinant, `(..., 3, 3)`.
    - `iterations`: Newton steps (8 reach rounding from `|R^T R - I|` up to about 1).

    **Returns:** rotation matrices, `(..., 3, 3)`.
    """
    X = R
    for _ in range(iterations):
        X = 0.5 * (X + jnp.swapaxes(jnp.linalg.inv(X), -1, -2))
    return X


def rotation_error(R: jax.Array) -> Scalar:
    """The distance of matrices from SO(3): `max |R^T R - I|` over every entry of every
    matrix (`(..., 3, 3)`, any leading axes)."""
    return jnp.max(jnp.abs(jnp.swapaxes(R, -1, -2) @ R - jnp.eye(3, dtype=R.dtype)))
