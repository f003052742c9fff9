"""Dense (unrolled LU with partial pivoting when small), dense SPD (unrolled Cholesky when
small) and tridiagonal (O(n)) solves, differentiated as linear solves."""

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jax.flatten_util import ravel_pytree

UNROLL_MAX = 64
"""Largest tridiagonal system solved unrolled (larger ones: the same recursion in a scan)."""
DENSE_UNROLL_MAX = 16
"""Largest dense system factorized unrolled (larger ones: LAPACK, compiling in O(1))."""


def symmetric_solve(matvec, solve, b: jax.Array) -> jax.Array:
    """`solve(b)` for symmetric `A = matvec`, differentiated as a linear solve (one more
    `solve` and a `matvec` per tangent), not through `solve`'s steps: half the cost of a
    chain's gradient on a 2-core CPU (`benchmarks/gradients.py`)."""
    return jax.lax.custom_linear_solve(matvec, b, lambda _, r: solve(r), symmetric=True)


def spd_solve(A: jax.Array, b: jax.Array) -> jax.Array:
    """Solve `A x = b` for SPD `A` by Cholesky (non-finite if `A` is not). Small systems
    are factorized unrolled with elementwise operations, so that under `vmap` XLA on CPU
    runs each over the whole batch instead of calling LAPACK per tiny matrix."""
    return symmetric_solve(lambda x: A @ x, _cholesky(A), b)


def _cholesky(A):
    """`A`'s factorization, done once, as the map `b -> A^-1 b`."""
    n = A.shape[-1]
    if n > DENSE_UNROLL_MAX:
        c = jax.scipy.linalg.cho_factor(A, lower=True)
        return lambda b: jax.scipy.linalg.cho_solve(c, b)
    idx = jnp.arange(n)
    cols, work = [], A  # right-looking Cholesky: one rank-1 update per column
    for k in range(n):
        col = jnp.where(idx >= k, work[:, k], 0.0) / jnp.sqrt(work[k, k])
        work = work - col[:, None] * col[None, :]
        cols.append(col)
    L = jnp.stack(cols, axis=1)

    def substitute(b):
        vector = b.ndim == 1
        r = b[:, None] if vector else b
        y = []  # forward substitution L y = b, column by column
        for k in range(n):
            y.append(r[k] / L[k, k])
            r = r - L[:, k, None] * y[k]
        r, x = jnp.stack(y), [None] * n  # back substitution L^T x = y
        for k in reversed(range(n)):
            x[k] = r[k] / L[k, k]
            r = r - L[k, :, None] * x[k]
        x = jnp.stack(x)
        return x[:, 0] if vector else x

    return substitute


def dense_solve(A: jax.Array, b: jax.Array, rcond: float = 0.0) -> jax.Array:
    """Solve `A x = b` for a general nonsingular `A` (`b` `(n,)`; non-finite if `A` is
    singular, or if its smallest pivot is below `rcond` times its largest: singular to
    rounding): LU with partial pivoting (`lu_factor`), differentiated as a linear solve
    (the transpose solve reuses the factors)."""
    factors = lu_factor(A)
    x = jax.lax.custom_linear_solve(
        lambda x: A @ x,
        b,
        lambda _, r: lu_solve(factors, r),
        lambda _, r: lu_solve(factors, r, transpose=True),
    )
    pivots = jnp.abs(jnp.diagonal(factors[1]))
    return jnp.where(jnp.min(pivots) <= rcond * jnp.max(pivots), jnp.nan, x)


def lu_factor(A: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """`P A = L U` with partial pivoting: `(L, U, perm)`, `L` unit lower triangular, `U`
    upper triangular, `A[perm] = L U`. Small systems (up to `DENSE_UNROLL_MAX`) by Gaussian
    elimination unrolled with elementwise operations, so that under `vmap` XLA on CPU runs
    each over the whole batch instead of calling LAPACK once per tiny matrix (and no LAPACK
    call sits inside a batched loop); larger ones by LAPACK (compiling in O(1)).

    The unrolled elimination works on the rows not yet pivoted only (their multipliers and
    the active block), one row leaving at each column: about `n^3 / 3` elementwise updates
    against `n^3` when every column's swap and update went over the whole matrix. A solve
    under `vmap` over 256 systems (2-core AMD EPYC, 2026-12-04): 1.7 us a system at
    `n = 8` (LAPACK 2.2, the whole-matrix elimination 8.3), 4.0 at 12 (LAPACK 4.2, before
    13.7), 13.0 at 16 (LAPACK 7.2, before 61.6)."""
    n = A.shape[-1]
    if n > DENSE_UNROLL_MAX:
        lu, _, perm = jax.lax.linalg.lu(A)
        return jnp.tril(lu, -1) + jnp.eye(n, dtype=A.dtype), jnp.triu(lu), perm
    rows, order = [], []  # the pivot rows of W = L - I + U, in order, and their indices
    tail, index = A, jnp.arange(n)  # the rows not yet pivoted: [multipliers | active block]
    for k in range(n):
        pivot = jnp.arange(n - k) == jnp.argmax(jnp.abs(tail[:, k]))
        rows.append(jnp.sum(jnp.where(pivot[:, None], tail, 0), axis=0))
        order.append(jnp.sum(jnp.where(pivot, index, 0)))
        # the first row takes the pivot row's place among those left
        tail = jnp.where(pivot[1:, None], tail[:1], tail[1:])
        index = jnp.where(pivot[1:], index[0], index[1:])
        col = tail[:, k] / rows[k][k]
        update = tail[:, k + 1 :] - col[:, None] * rows[k][None, k + 1 :]
        tail = jnp.concatenate([tail[:, :k], col[:, None], update], axis=1)
    W = jnp.stack(rows)
    return jnp.tril(W, -1) + jnp.eye(n, dtype=A.dtype), jnp.triu(W), jnp.stack(order)


def lu_solve(factors, b: jax.Array, transpose: bool = False) -> jax.Array:
    """`A^-1 b` (or `A^-T b` if `transpose`) from `lu_factor(A)`, `b` `(n,)` or `(n, k)`."""
    L, U, perm = factors
    if transpose:  # U^T y = b, L^T z = y, x = P^T z
        z = _back(L.T, _forward(U.T, b, unit=False), unit=True)
        return jnp.zeros_like(z).at[perm].set(z)
    return _back(U, _forward(L, b[perm], unit=True))  # L y = P b, U x = y


class DenseLU(lx.AbstractLinearSolver):
    """lineax's `LU` solve (square, nonsingular operators) factorized by `lu_factor`: for
    the small Jacobians of Newton's method under `vmap` (the variational integrator, the
    momentum inversion), elementwise over the whole batch instead of LAPACK per matrix
    inside the batched loop. Implements lineax's solver protocol (lineax 0.1)."""

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        del options
        if operator.in_size() != operator.out_size():
            raise ValueError("DenseLU needs a square operator.")
        unravel = lambda structure: ravel_pytree(
            jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), structure)
        )[1]
        layout = _Layout(unravel(operator.in_structure()), unravel(operator.out_structure()))
        return lu_factor(operator.as_matrix()), layout

    def compute(self, state, vector, options):
        del options
        factors, layout = state
        x = lu_solve(factors, ravel_pytree(vector)[0], transpose=layout.transposed)
        unravel = layout.out_unravel if layout.transposed else layout.in_unravel
        return unravel(x), lx.RESULTS.successful, {}

    def transpose(self, state, options):
        factors, layout = state
        return (factors, dataclasses.replace(layout, transposed=not layout.transposed)), {}

    def conj(self, state, options):
        (L, U, perm), layout = state
        return ((L.conj(), U.conj(), perm), layout), {}

    def assume_full_rank(self):
        return True


class _Layout(eqx.Module):
    """Static facts of a `DenseLU` state (it may be carried through loops): how flat
    vectors unravel into the operator's input and output structures, and whether the
    solve is transposed (its solution then has the output's structure)."""

    in_unravel: Callable = eqx.field(static=True)
    out_unravel: Callable = eqx.field(static=True)
    transposed: bool = eqx.field(static=True, default=False)


def _forward(L, b, unit):
    """`L^-1 b`, `L` lower triangular (unit diagonal if `unit`): unrolled when small."""
    n = L.shape[0]
    if n > DENSE_UNROLL_MAX:
        return jax.scipy.linalg.solve_triangular(L, b, lower=True, unit_diagonal=unit)
    x = []
    for k in range(n):
        r = b[k] - sum((L[k, j] * x[j] for j in range(k)), jnp.zeros_like(b[k]))
        x.append(r if unit else r / L[k, k])
    return jnp.stack(x)


def _back(U, b, unit=False):
    """`U^-1 b`, `U` upper triangular (unit diagonal if `unit`): unrolled when small."""
    n = U.shape[0]
    if n > DENSE_UNROLL_MAX:
        return jax.scipy.linalg.solve_triangular(U, b, lower=False, unit_diagonal=unit)
    x = [None] * n
    for k in reversed(range(n)):
        r = b[k] - sum((U[k, j] * x[j] for j in range(k + 1, n)), jnp.zeros_like(b[k]))
        x[k] = r if unit else r / U[k, k]
    return jnp.stack(x)


def tridiagonal_matvec(d: jax.Array, e: jax.Array, x: jax.Array) -> jax.Array:
    """`A x`, `A` symmetric tridiagonal (diagonal `d`, off-diagonal `e`), `x` `(n,)`/`(n, k)`."""
    d, e = (d.reshape(d.shape + (1,) * (x.ndim - 1)), e.reshape(e.shape + (1,) * (x.ndim - 1)))
    zero = jnp.zeros_like(x[:1])
    return d * x + jnp.concatenate([zero, e * x[:-1]]) + jnp.concatenate([e * x[1:], zero])


def tridiagonal_spd_solve(d: jax.Array, e: jax.Array, b: jax.Array) -> jax.Array:
    """Solve `A x = b` for SPD tridiagonal `A` (as in `tridiagonal_matvec`) in O(n): the
    Thomas algorithm (`L D L^T`), unrolled up to `UNROLL_MAX`, else in `lax.scan`."""
    return symmetric_solve(lambda x: tridiagonal_matvec(d, e, x), lambda r: _thomas(d, e, r), b)


def _thomas(d, e, b):
    n = d.shape[0]
    if n > UNROLL_MAX:
        return _tridiagonal_scan(d, e, b)
    piv, y = [d[0]], [b[0]]
    for k in range(1, n):
        ratio = e[k - 1] / piv[k - 1]
        piv.append(d[k] - ratio * e[k - 1])
        y.append(b[k] - ratio * y[k - 1])
    x = [None] * n
    x[n - 1] = y[n - 1] / piv[n - 1]
    for k in reversed(range(n - 1)):
        x[k] = (y[k] - e[k] * x[k + 1]) / piv[k]
    return jnp.stack(x)


def _tridiagonal_scan(d, e, b):
    def forward(carry, inputs):
        (piv_prev, y_prev), (d_k, e_prev, b_k) = carry, inputs
        ratio = e_prev / piv_prev
        carry = (d_k - ratio * e_prev, b_k - ratio * y_prev)
        return carry, carry

    _, (piv, y) = jax.lax.scan(forward, (d[0], b[0]), (d[1:], e, b[1:]))
    piv, y = jnp.concatenate([d[:1], piv]), jnp.concatenate([b[:1], y])

    def backward(x_next, inputs):
        y_k, e_k, piv_k = inputs
        x = (y_k - e_k * x_next) / piv_k
        return x, x

    last = y[-1] / piv[-1]
    _, x = jax.lax.scan(backward, last, (y[:-1], e, piv[:-1]), reverse=True)
    return jnp.concatenate([x, last[None]])
