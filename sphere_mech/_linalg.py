"""Linear algebra in tangent coordinates.

Every form's linear system `(P H + Q) x = P r` is solved in an orthonormal tangent basis
`T` (`(n, 3, 2)`, 2n columns): `(T^T H T) a = T^T r`, `x = T a`. This is the 2n x 2n
symmetric form recommended in DESIGN.md, better conditioned than the 3n x 3n system and
independent of which tangent basis is used.
"""

import jax
import jax.numpy as jnp

from ._geometry import tangent_basis


def to_tangent(T: jax.Array, v: jax.Array) -> jax.Array:
    """Coordinates of `v` (`(n, 3)`) in the basis `T`, flattened to `(2n,)`."""
    return jnp.einsum("ica,ic->ia", T, v).reshape(-1)


def from_tangent(T: jax.Array, a: jax.Array) -> jax.Array:
    """The `(n, 3)` tangent vector with coordinates `a` (`(2n,)`) in the basis `T`."""
    return jnp.einsum("ica,ia->ic", T, a.reshape(T.shape[0], 2))


def basis_directions(T: jax.Array) -> jax.Array:
    """The 2n basis vectors as `(2n, n, 3)` arrays (each nonzero on one sphere only)."""
    n = T.shape[0]
    eye = jnp.eye(n, dtype=T.dtype)
    # directions[(j, b), i, c] = delta_ij T[j, c, b]
    return jnp.einsum("ij,jcb->jbic", eye, T).reshape(2 * n, n, 3)


def reduced_matrix(hvp, T: jax.Array) -> jax.Array:
    """`T^T H T` (2n x 2n) for a linear map `hvp: (n, 3) -> (n, 3)` applying `H`."""
    HT = jax.vmap(hvp)(basis_directions(T))  # (2n, n, 3): H applied to each direction
    return jax.vmap(lambda col: to_tangent(T, col), out_axes=1)(HT)


def tangent_solve(hvp, q: jax.Array, rhs: jax.Array, T: jax.Array | None = None):
    """Solve `P H x = P rhs` for a tangent `x`, with `H` given as a linear map `hvp`."""
    if T is None:
        T = tangent_basis(q)
    A = reduced_matrix(hvp, T)
    return from_tangent(T, jnp.linalg.solve(A, to_tangent(T, rhs)))


def scalar_inertia_matrix(M: jax.Array, T: jax.Array) -> jax.Array:
    """`T^T (M kron I_3) T` for a scalar inertia matrix `M` (n x n): block (i, j) is
    `M_ij T_i^T T_j`. No Hessian, no autodiff: the Corollary-1 fast path."""
    n = M.shape[0]
    G = jnp.einsum("ica,jcb->iajb", T, T) * M[:, None, :, None]
    return G.reshape(2 * n, 2 * n)


def spd_solve(A: jax.Array, b: jax.Array) -> jax.Array:
    """Solve `A x = b` for symmetric positive-definite `A` by Cholesky. A matrix that is
    not positive definite gives non-finite output (checked by the callers)."""
    c = jax.scipy.linalg.cho_factor(A, lower=True)
    return jax.scipy.linalg.cho_solve(c, b)
