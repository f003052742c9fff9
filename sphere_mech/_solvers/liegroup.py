"""A Lie-group Runge-Kutta method (Munthe-Kaas, order 4) for states on T(S^2)^n."""

from collections.abc import Callable
from typing import ClassVar

import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
from diffrax import (
    RESULTS,
    AbstractAdaptiveSolver,
    AbstractTerm,
    ThirdOrderHermitePolynomialInterpolation,
)

from .._geometry import project, rotate


def _check_state_structure(y0):
    ok = isinstance(y0, tuple) and len(y0) == 2
    ok = ok and all(jnp.ndim(x) >= 1 and jnp.shape(x)[-1] == 3 for x in y0)
    if not ok or jnp.shape(y0[0]) != jnp.shape(y0[1]):
        raise ValueError(
            "LieRK4 integrates states y = (q, v) of two arrays of shape (n, 3) (points on "
            f"(S^2)^n and a tangent vector), got {jtu.tree_map(jnp.shape, y0)}."
        )


def _algebra(y, dy):
    """The Lie-algebra element `(w, a)` of `so(3)^n x R^(3n)` that moves the state
    `y = (q, v)` with velocity `dy = (dq, dv)`: `w_i = q_i x dq_i` (so that
    `w_i x q_i = dq_i` for tangent `dq_i`) and `a = dv`."""
    q, _ = y
    dq, dv = dy
    return jnp.cross(q, dq), dv


def _act(u, y0):
    """The group action `exp(u) . (q, v) = (exp(hat(w)) q, v + a)`."""
    w, a = u
    q0, v0 = y0
    return rotate(w, q0), v0 + a


def _dexpinv(u, k):
    """`dexp_u^{-1}(k)`, truncated after the `ad_u^2` term (the next term of the series
    is `ad_u^4`, of order h^5 here, so the order 4 is kept). Only the `so(3)` part has
    brackets (`[w, w'] = w x w'`); the `R^(3n)` part is abelian."""
    uw, _ = u
    kw, ka = k
    cross1 = jnp.cross(uw, kw)
    return kw - 0.5 * cross1 + jnp.cross(uw, cross1) / 12.0, ka


def _combine(*terms):
    """`sum_i c_i u_i` over Lie-algebra elements, for `terms = ((c_1, u_1), ...)`."""
    coeffs = [c for c, _ in terms]
    return jtu.tree_map(lambda *xs: sum(c * x for c, x in zip(coeffs, xs, strict=True)),
                        *[u for _, u in terms])


class LieRK4(AbstractAdaptiveSolver):
    """A Lie-group Runge-Kutta method of order 4 on T(S^2)^n: the Runge-Kutta-Munthe-Kaas
    method (RKMK4) built on the classic RK4 tableau, with an embedded order-3 error
    estimate for adaptive step sizes.

    The state `y = (q, v)` (any of the four forms: `v` is `qdot`, `omega`, `mu` or `pi`)
    is moved by the group `SO(3)^n x R^(3n)`: each `q_i` by a rotation
    `exp(h hat(w_i))`, with `w_i = q_i x qdot_i` computed from the system's rates (the
    diffrax term's vector field), so `|q_i| = 1` holds to rounding without any
    projection; `v` is advanced by the Runge-Kutta combination of its rates and, at the
    end of each step, its normal part at the new `q` is removed (`v_i . q_i = 0`). That
    projection changes `v` by no more than the local error, O(h^5), so the order is kept.
    The stage values of `v` are not projected: the rates are defined for any `v`, and
    the tangent bundle is invariant under their flow, which is what RKMK's order theory
    needs.

    Per step: 4 evaluations of the vector field (the 5th, at the new state, is reused as
    the first of the next step: first same as last), a few cross products and one
    Rodrigues rotation per stage. The error estimate compares the step with the embedded
    order-3 method `b^ = (1/6, 1/3, 1/3, 0, 1/6)` (the last stage is `f(y1)`), so
    `PIDController` works; with `ConstantStepSize` it is a plain fixed-step method.
    Dense output: cubic Hermite from `f(y0)` and `f(y1)`.

    Reference: H. Munthe-Kaas, High order Runge-Kutta methods on manifolds, Appl. Numer.
    Math. 29 (1999) 115-127.
    """

    term_structure: ClassVar = AbstractTerm
    interpolation_cls: ClassVar[Callable[..., ThirdOrderHermitePolynomialInterpolation]] = (
        ThirdOrderHermitePolynomialInterpolation.from_k
    )

    def order(self, terms):
        return 4

    def error_order(self, terms):
        # The estimate is the difference with an order-3 method: O(h^4) per step.
        return 4

    def init(self, terms, t0, t1, y0, args):
        _check_state_structure(y0)
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        _check_state_structure(y0)
        h = terms.contr(t0, t1)
        tm = t0 + 0.5 * (t1 - t0)
        f0 = solver_state
        if not (isinstance(made_jump, bool) and not made_jump):
            f0 = lax.cond(jnp.any(made_jump), lambda: terms.vf(t0, y0, args), lambda: f0)

        def stage(t, u):
            y = _act(u, y0)
            return _dexpinv(u, _algebra(y, terms.vf_prod(t, y, args, h)))

        k1 = _algebra(y0, terms.prod(f0, h))
        k2 = stage(tm, _combine((0.5, k1)))
        k3 = stage(tm, _combine((0.5, k2)))
        u4 = k3
        k4 = stage(t1, u4)
        u = _combine((1 / 6, k1), (1 / 3, k2), (1 / 3, k3), (1 / 6, k4))
        q1, v1 = _act(u, y0)
        y1 = (q1, project(q1, v1))
        f1 = terms.vf(t1, y1, args)
        k5 = _dexpinv(u, _algebra(y1, terms.prod(f1, h)))
        # Embedded order-3 solution: replace the weight 1/6 of k4 by that of k5.
        u_hat = _combine((1.0, u), (1 / 6, k5), (-1 / 6, k4))
        q_hat, v_hat = _act(u_hat, y0)
        y_error = (q1 - q_hat, v1 - v_hat)
        k = jtu.tree_map(lambda a, b: jnp.stack([a, b]), terms.prod(f0, h), terms.prod(f1, h))
        dense_info = dict(y0=y0, y1=y1, k=k)
        return y1, y_error, dense_info, f1, RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)
