"""Geometry of (S^2)^n: points are `(n, 3)` unit vectors, tangent vectors `(n, 3)` with
`q_i . v_i = 0`; every function also accepts a single `(3,)` vector."""

import jax
import jax.numpy as jnp
import jax.random as jr
import numpy as np

from ._custom_types import Points, Scalar, Tangents
from ._misc import check_integer, check_positive, float_dtype


def _check_trailing(x, shape: tuple, name: str, fn: str) -> jax.Array:
    """`x` (an array or nested lists) as an array whose last axes are `shape`
    (`ValueError` at trace time otherwise, naming `fn` and `name`)."""
    if np.ndim(x) < len(shape) or np.shape(x)[-len(shape) :] != shape:  # lists too
        want = ", ".join(["..."] + [str(d) for d in shape])
        raise ValueError(f"{fn}: {name} must have shape ({want}), got {np.shape(x)}.")
    return jnp.asarray(x)


def hat(x: jax.Array) -> jax.Array:
    """The hat map: `hat(x) @ y == cross(x, y)`.

    **Arguments:**
    - `x`: vectors, shape `(..., 3)`.

    **Returns:** the skew-symmetric matrices, shape `(..., 3, 3)`."""
    x = _check_trailing(x, (3,), "x", "hat")
    x1, x2, x3 = x[..., 0], x[..., 1], x[..., 2]
    z = jnp.zeros_like(x1)
    rows = [[z, -x3, x2], [x3, z, -x1], [-x2, x1, z]]
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def dot(a: jax.Array, b: jax.Array) -> jax.Array:
    """Row-wise dot product, keeping the last axis: `(..., 3), (..., 3) -> (..., 1)`."""
    return jnp.sum(a * b, axis=-1, keepdims=True)


def normalize(q: jax.Array) -> jax.Array:
    """Scale each row of `q` to unit length.

    **Arguments:**
    - `q`: nonzero vectors, shape `(..., 3)`.

    **Returns:** `q_i / |q_i|`, the same shape: NaN for a zero row, which has no direction
    (its value unchecked: the solvers' retractions call this in every step; `simulate`
    refuses a NaN state, naming it)."""
    q = _check_trailing(q, (3,), "q", "normalize")
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def project(q: Points, v: jax.Array) -> Tangents:
    """Remove from each `v_i` its component along `q_i`: `(I - q_i q_i^T) v_i`.

    **Arguments:**
    - `q`, `v`: unit vectors, `(n, 3)` (or `(3,)`), and vectors of the same shape.

    **Returns:** the tangent parts of `v`, the same shape."""
    q, v = _check_trailing(q, (3,), "q", "project"), _check_trailing(v, (3,), "v", "project")
    return v - dot(q, v) * q


def retract(q: jax.Array, v: jax.Array) -> tuple[Points, Tangents]:
    """Put a state back on the tangent bundle: normalize `q`, make `v` tangent to it.

    **Arguments:**
    - `q`, `v`: nonzero vectors near the spheres, `(n, 3)`, and vectors of the same shape
      (a velocity, angular velocity or momentum).

    **Returns:** `(q / |q|, v projected on the tangent planes at the normalized q)`."""
    q, v = _check_trailing(q, (3,), "q", "retract"), _check_trailing(v, (3,), "v", "retract")
    q = normalize(q)
    return q, project(q, v)


def tangent_basis(q: Points) -> jax.Array:
    """An orthonormal basis of each tangent plane, by the branch-free construction of Duff
    et al. (2017): `b1 x b2 = q_i`. `q` is normalized first.

    **Arguments:**
    - `q`: points, `(n, 3)` (or `(3,)`).

    **Returns:** the bases, `(n, 3, 2)` (or `(3, 2)`): column `k` of `[i]` is `b_k` at `q_i`."""
    q = normalize(_check_trailing(q, (3,), "q", "tangent_basis"))
    x, y, z = q[..., 0], q[..., 1], q[..., 2]
    s = jnp.where(z >= 0, 1.0, -1.0).astype(q.dtype)
    a = -1.0 / (s + z)
    b = x * y * a
    b1 = jnp.stack([1.0 + s * x * x * a, s * b, -s * x], axis=-1)
    b2 = jnp.stack([b, s + y * y * a, -y], axis=-1)
    return jnp.stack([b1, b2], axis=-1)


def _rodrigues_coefficients(theta2: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`sin(t)/t`, `(1 - cos t)/t^2` and `(t - sin t)/t^3` as functions of `t^2`, smooth at
    zero."""
    small = theta2 < 1e-4
    safe2 = jnp.where(small, 1.0, theta2)
    t = jnp.sqrt(safe2)
    sinc = jnp.where(small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, jnp.sin(t) / t)
    cosc = jnp.where(small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, (1.0 - jnp.cos(t)) / safe2)
    sinc3 = jnp.where(small, 1 / 6 - theta2 / 120 + theta2**2 / 5040, (1.0 - sinc) / safe2)
    return sinc, cosc, sinc3


def rotate(w: jax.Array, x: jax.Array) -> jax.Array:
    """Apply the rotation `exp(hat(w_i))` to each `x_i` (Rodrigues' formula).

    **Arguments:**
    - `w`, `x`: rotation vectors (axis times angle in rad), `(..., 3)`, and vectors to
      rotate, same shape.

    **Returns:** the rotated vectors, same shape; smooth (and differentiable) at `w = 0`."""
    w, x = _check_trailing(w, (3,), "w", "rotate"), _check_trailing(x, (3,), "x", "rotate")
    return x + rotation_increment(w, x)


def rotation_increment(w: jax.Array, x: jax.Array) -> jax.Array:
    """`exp(hat(w_i)) x_i - x_i` row-wise, without the rounding of that difference (about
    `eps |x|`, which a division by a small step would amplify): Rodrigues' terms alone."""
    sinc, cosc, _ = _rodrigues_coefficients(jnp.sum(w * w, axis=-1, keepdims=True))
    wx = jnp.cross(w, x)
    return sinc * wx + cosc * jnp.cross(w, wx)


def left_jacobian(w: jax.Array, b: jax.Array) -> jax.Array:
    """`J(w) b` row-wise, `J(w) = I + (1 - cos t)/t^2 hat(w) + (t - sin t)/t^3 hat(w)^2`
    (`t = |w|`) the left Jacobian of `SO(3)`: `exp(w, b)` in `se(3)` is `exp(hat(w))`
    then the translation `J(w) b`. Smooth at `w = 0`."""
    _, cosc, sinc3 = _rodrigues_coefficients(jnp.sum(w * w, axis=-1, keepdims=True))
    wb = jnp.cross(w, b)
    return b + cosc * wb + sinc3 * jnp.cross(w, wb)


def dexpinv_so3(w: jax.Array, k: jax.Array) -> jax.Array:
    """`dexp_w^{-1}(k) = k - (w x k)/2 + c(t) w x (w x k)` of `so(3)` row-wise,
    `c(t) = (1 - (t/2) cot(t/2))/t^2`, `t = |w| < 2 pi` (the Bernoulli series summed);
    smooth at `w = 0`."""
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

    **Returns:** the rotation matrices, `(..., 3, 3)`."""
    w = _check_trailing(w, (3,), "w", "rotation_matrix")
    return jnp.eye(3, dtype=w.dtype) + rotation_matrix_increment(w)


def rotation_matrix_increment(w: jax.Array) -> jax.Array:
    """`exp(hat(w)) - I` without the rounding of that difference: Rodrigues' terms alone."""
    sinc, cosc, _ = _rodrigues_coefficients(jnp.sum(w * w, axis=-1))
    W = hat(w)
    return sinc[..., None, None] * W + cosc[..., None, None] * (W @ W)


def sphere_exp(q: Points, v: Tangents) -> Points:
    """The exponential map of the round sphere: the great circle from `q_i` with initial
    velocity `v_i`, at unit time; `rotate(cross(q, v), q)`.

    **Arguments:**
    - `q`, `v`: `(n, 3)` unit vectors and tangent vectors at them.

    **Returns:** the end points, `(n, 3)` unit vectors."""
    q, v = _check_trailing(q, (3,), "q", "sphere_exp"), _check_trailing(v, (3,), "v", "sphere_exp")
    return rotate(jnp.cross(q, v), q)


def constraint_error(q: jax.Array) -> Scalar:
    """The distance of a configuration from (S^2)^n.

    **Arguments:**
    - `q`: vectors, `(n, 3)` (or with leading axes, e.g. a trajectory `(T, n, 3)`).

    **Returns:** the scalar `max_i | |q_i| - 1 |` over every point."""
    q = _check_trailing(q, (3,), "q", "constraint_error")
    return jnp.max(jnp.abs(jnp.linalg.norm(q, axis=-1) - 1.0))


def random_points(key: jax.Array, n: int, *, dtype=None) -> Points:
    """Independent, uniformly distributed points on the unit sphere.

    **Arguments:**
    - `key`, `n`: a JAX PRNG key and the number of points.
    - `dtype`: the floating dtype (default JAX's, float64 with x64 enabled).

    **Returns:** an `(n, 3)` array of unit vectors."""
    check_integer(n, "random_points: n")
    return normalize(jr.normal(key, (n, 3), dtype=float_dtype(dtype, "random_points: dtype")))


def random_state(
    key: jax.Array, n: int, *, speed: float = 1.0, dtype=None
) -> tuple[Points, Tangents]:
    """A random state on the tangent bundle of (S^2)^n: `q` uniform on each sphere, `v` a
    Gaussian tangent vector (equally an angular velocity or a momentum).

    **Arguments:**
    - `key`, `n`: a JAX PRNG key and the number of spheres.
    - `speed`, `dtype`: the standard deviation of `v` per tangent direction and the
      floating dtype (default JAX's).

    **Returns:** `(q, v)`, two `(n, 3)` arrays with `|q_i| = 1` and `q_i . v_i = 0`."""
    check_integer(n, "random_state: n")
    check_positive(speed, "random_state: speed", zero=True)
    dtype = float_dtype(dtype, "random_state: dtype")
    kq, kv = jr.split(key)
    q = random_points(kq, n, dtype=dtype)
    return q, project(q, speed * jr.normal(kv, (n, 3), dtype=dtype))


def vee(M: jax.Array) -> jax.Array:
    """The inverse of `hat` on the skew part: `vee(M) = w` with `hat(w) = (M - M^T)/2`.

    **Arguments:**
    - `M`: matrices, `(..., 3, 3)`.

    **Returns:** vectors, `(..., 3)`.
    """
    M = _check_trailing(M, (3, 3), "M", "vee")
    return 0.5 * jnp.stack(
        [M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]],
        axis=-1,
    )


def nearest_rotation(R: jax.Array, iterations: int = 8) -> jax.Array:
    """The rotation nearest to each `R_j` in the Frobenius norm (the orthogonal factor of
    its polar decomposition), by Newton's iteration with Frobenius-norm scaling (Higham,
    1986) `X <- (g X + X^-T / g) / 2`, `g = (|X^-1|_F / |X|_F)^(1/2)`: quadratic
    convergence from any scale, differentiable (unlike an SVD at a rotation's repeated
    singular values; `g = 1` at a rotation, so derivatives are those of the polar factor).
    `X^-T` is the cofactor matrix over the determinant, elementwise (no LAPACK call per
    matrix under `vmap`).

    **Arguments:**
    - `R`: matrices with positive determinant, `(..., 3, 3)`.
    - `iterations`: Newton steps, an integer `>= 0` (8 reach rounding: measured in float64,
      within 1e-14 of the SVD's polar factor for random matrices of condition number up
      to 1e12 and norm 1e-3 to 1e3, after 5 steps from singular values `(1, 1, 0.01)`,
      after 1 from `0.01 I` or `100 I`; 0 returns `R`).

    **Returns:** rotation matrices, `(..., 3, 3)`. Not checked (at run time, traced):
    a matrix of negative determinant gives its orthogonal factor, a reflection
    (`det = -1`; `-I` is returned as it is), and a singular one (zero) NaN.
    """
    X = _check_trailing(R, (3, 3), "R", "nearest_rotation")
    check_integer(iterations, "nearest_rotation: iterations", 0)
    squares = lambda M: jnp.sum(M * M, axis=(-2, -1), keepdims=True)
    for _ in range(iterations):
        x0, x1, x2 = X[..., 0, :], X[..., 1, :], X[..., 2, :]
        cofactors = jnp.stack([jnp.cross(x1, x2), jnp.cross(x2, x0), jnp.cross(x0, x1)], -2)
        det = jnp.sum(x0 * cofactors[..., 0, :], -1)[..., None, None]
        inverse_t = cofactors / det
        g = (squares(inverse_t) / squares(X)) ** 0.25
        X = 0.5 * (g * X + inverse_t / g)
    return X


def rotation_error(R: jax.Array) -> Scalar:
    """The distance of matrices from SO(3): `max |R^T R - I|` over every entry of every
    matrix (`(..., 3, 3)`, any leading axes)."""
    return jnp.max(jnp.abs(jnp.swapaxes(R, -1, -2) @ R - jnp.eye(3, dtype=R.dtype)))
