"""The classic fourth-order Runge-Kutta method as a diffrax solver."""

from collections.abc import Callable
from typing import ClassVar

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
    in `sphere_mech.Projected` to stay on the spheres (unwrapped, `|q_i| - 1` drifts)."""

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
        tm = t0 + 0.5 * (t1 - t0)
        k1 = terms.vf_prod(t0, y0, args, h)
        k2 = terms.vf_prod(tm, axpy(y0, (0.5, k1)), args, h)
        k3 = terms.vf_prod(tm, axpy(y0, (0.5, k2)), args, h)
        k4 = terms.vf_prod(t1, axpy(y0, (1.0, k3)), args, h)
        y1 = axpy(y0, (1 / 6, k1), (1 / 3, k2), (1 / 3, k3), (1 / 6, k4))
        # Hermite dense output from the end slopes (k4 approximates f(t1, y1)).
        k = jtu.tree_map(lambda a, b: jnp.stack([a, b]), k1, k4)
        return y1, None, dict(y0=y0, y1=y1, k=k), None, RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)
