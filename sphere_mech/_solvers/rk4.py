"""The classic fourth-order Runge-Kutta method as a diffrax solver."""

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from diffrax import (
    RESULTS,
    AbstractSolver,
    AbstractTerm,
    ButcherTableau,
    ThirdOrderHermitePolynomialInterpolation,
)

from .._misc import fill_zeros, tree_add


def axpy(y, *terms):
    """`y + sum_i c_i k_i` over PyTrees, for `terms = ((c_1, k_1), (c_2, k_2), ...)`."""
    coeffs, leaves = zip(*terms, strict=True)
    return jtu.tree_map(
        lambda a, *ks: a + sum(c * k for c, k in zip(coeffs, ks, strict=True)), y, *leaves
    )


class RK4(AbstractSolver):
    """The classic Runge-Kutta method of order 4 (diffrax has none; MuJoCo's RK4 is the
    same method): four evaluations per step, fixed steps only (no error estimate), cubic
    Hermite dense output. Use it with `diffrax.ConstantStepSize()` and a `dt0`, wrapped
    in `sphere_mech.Projected` to stay on the spheres (unwrapped, `|q_i| - 1` drifts).

    **Arguments:**
    - `stagewise_reverse`: reverse-mode derivatives of a step one stage at a time (a
      `jax.custom_vjp` whose backward pass is a `lax.scan` over the four stages) instead
      of JAX's transpose of the whole step. The same steps and the same gradient (to
      rounding), at about half the cost of a step's backward pass on CPU, where XLA
      otherwise fuses the stages' cotangents into one program and recomputes them in
      every consumer; no forward mode (`jax.jvp`). The default adjoint of `simulate`
      and `simulate_batch` sets it for its reverse mode (`sphere_mech._adjoint`)."""

    stagewise_reverse: bool = eqx.field(static=True, default=False)

    tableau: ClassVar[ButcherTableau] = ButcherTableau(
        c=np.array([0.5, 0.5, 1.0, 1.0]),
        b_sol=np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6, 0.0]),
        b_error=np.array([0.0, 0.0, 0.0, 1 / 6, -1 / 6]),
        a_lower=(
            np.array([0.5]),
            np.array([0.0, 0.5]),
            np.array([0.0, 0.0, 1.0]),
            np.array([1 / 6, 1 / 3, 1 / 3, 1 / 6]),
        ),
    )
    """The classic tableau plus an FSAL stage `f(y1)` and embedded order-3 weights
    `(1/6, 1/3, 1/3, 0, 1/6)`, for `LieRK(RK4())` (`RK4` evaluates only four stages)."""

    term_structure: ClassVar = AbstractTerm
    interpolation_cls: ClassVar[Callable[..., ThirdOrderHermitePolynomialInterpolation]] = (
        ThirdOrderHermitePolynomialInterpolation.from_k
    )

    def order(self, terms):
        return 4

    def init(self, terms, t0, t1, y0, args):
        return None

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        h = terms.contr(t0, t1)
        if self.stagewise_reverse:
            # Closure-converted: values that the vector field closes over (a parameter
            # captured by `L`) are inputs of the step's `custom_vjp`, which differentiates them.
            vf_prod = eqx.filter_closure_convert(terms.vf_prod, t0, y0, args, h)
            y1, k1, k4 = _stagewise_step((vf_prod, h, t0, t1, y0, args))
        else:
            y1, k1, k4 = _step(terms.vf_prod, h, t0, t1, y0, args)[0]
        # Hermite dense output from the end slopes (k4 approximates f(t1, y1)).
        k = jtu.tree_map(lambda a, b: jnp.stack([a, b]), k1, k4)
        return y1, None, dict(y0=y0, y1=y1, k=k), None, RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def stage_coefficients(tableau, stages: int) -> np.ndarray:
    """`(stages, s)`: row `i` holds the coefficients `a_ij` of stage `i`'s state `y0 + sum_j
    a_ij k_j` for the first `stages` stages of a diffrax `ButcherTableau` (row 0, the first
    stage's, is zero), padded with zeros to its `s` stages."""
    a = np.zeros((stages, tableau.num_stages))
    for i, row in enumerate(tableau.a_lower[: stages - 1]):
        a[i + 1, : len(row)] = row
    return a


_A = stage_coefficients(RK4.tableau, 4)[:, :4]
_B = RK4.tableau.b_sol[:4]
"""The classic tableau, read from `RK4.tableau` (its four stages, not the FSAL one): stage
`i` is evaluated at `y0 + sum_j _A[i, j] k_j`, and `y1 = y0 + sum_j _B[j] k_j`."""


def _step(vf_prod, h, t0, t1, y0, args):
    """One step of `vf_prod(t, y, args, h)` (a term's, `h` its control over the step):
    `(y1, k1, k4)` and the four stages' states."""
    tm = t0 + 0.5 * (t1 - t0)
    k1 = vf_prod(t0, y0, args, h)
    y2 = axpy(y0, (0.5, k1))
    k2 = vf_prod(tm, y2, args, h)
    y3 = axpy(y0, (0.5, k2))
    k3 = vf_prod(tm, y3, args, h)
    y4 = axpy(y0, (1.0, k3))
    k4 = vf_prod(t1, y4, args, h)
    y1 = axpy(y0, (1 / 6, k1), (1 / 3, k2), (1 / 3, k3), (1 / 6, k4))
    return (y1, k1, k4), (y0, y2, y3, y4)


def _stage(i, vf_prod, h, t0, t1, args, y):
    """Stage `i` (traced, 0 to 3) of `_step` at its state `y`."""
    tm = t0 + 0.5 * (t1 - t0)
    return vf_prod(jnp.stack([t0, tm, tm, t1])[i], y, args, h)


@eqx.filter_custom_vjp
def _stagewise_step(inputs):
    return _step(*inputs)[0]


@_stagewise_step.def_fwd
def _stagewise_fwd(perturbed, inputs):
    out, stages = _step(*inputs)
    return out, jtu.tree_map(lambda *ys: jnp.stack(ys), *stages)


@_stagewise_step.def_bwd
def _stagewise_bwd(stages, grad_out, perturbed, inputs):
    """The cotangents of `inputs` from those of `(y1, k1, k4)`: the stages in reverse order,
    each one `jax.vjp` of the vector field (its forward pass recomputed) inside a `lax.scan`,
    so that XLA compiles one stage's backward pass, not the step's four fused together."""
    vf_prod, h, t0, t1, y0, args = inputs
    zero_state = jtu.tree_map(jnp.zeros_like, y0)
    g_y1, g_k1, g_k4 = (zero_state if g is None else fill_zeros(g, y0) for g in grad_out)
    # The stages' cotangents, before the stages after them add theirs (Python floats: no
    # promotion of float32).
    weights = [float(b) for b in _B]
    ends = lambda g1, g4: (g1, 0.0, 0.0, g4)
    g_k = jtu.tree_map(
        lambda g, g1, g4: jnp.stack(
            [g * b + c for b, c in zip(weights, ends(g1, g4), strict=True)]
        ),
        g_y1,
        g_k1,
        g_k4,
    )
    shared, static = eqx.partition((vf_prod, h, t0, t1, args), eqx.is_inexact_array)
    stage = lambda i, shared, y: _stage(i, *eqx.combine(shared, static), y)

    def body(carry, i):
        g_k, g_y0, g_shared = carry
        y_i = jtu.tree_map(lambda ys: ys[i], stages)
        _, pullback = jax.vjp(lambda s, y: stage(i, s, y), shared, y_i)
        g_s, g_yi = pullback(jtu.tree_map(lambda g: g[i], g_k))
        row = jnp.asarray(_A)[i]
        g_k = jtu.tree_map(
            lambda g, gy: g + jnp.reshape(row.astype(g.dtype), (4,) + (1,) * gy.ndim) * gy,
            g_k,
            g_yi,
        )
        return (g_k, tree_add(g_y0, g_yi), tree_add(g_shared, g_s)), None

    zeros = jtu.tree_map(jnp.zeros_like, shared)
    (_, g_y0, g_shared), _ = jax.lax.scan(body, (g_k, g_y1, zeros), jnp.arange(3, -1, -1))
    g_vf_prod, g_h, g_t0, g_t1, g_args = g_shared
    return g_vf_prod, g_h, g_t0, g_t1, g_y0, g_args
