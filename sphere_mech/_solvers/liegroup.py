"""Runge-Kutta-Munthe-Kaas methods over any explicit diffrax tableau, on T(S^2)^n."""

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
import jax.tree_util as jtu
from diffrax import (
    RESULTS,
    AbstractAdaptiveSolver,
    AbstractERK,
    AbstractLocalInterpolation,
    AbstractTerm,
    AbstractWrappedSolver,
    ThirdOrderHermitePolynomialInterpolation,
)

from .._lie import AbstractLieAction
from .._misc import tree_sub
from .._term import MechanicsTerm, space_of, system_of
from .rk4 import RK4, stage_coefficients
from .wrapped import described

ACTIONS = ("SE3", "SO3xR3")
ERROR_ESTIMATES = ("state", "algebra")


def _combine(coeffs, ks):
    """`sum_j c_j k_j` over Lie-algebra elements stacked along a leading axis."""
    return jtu.tree_map(lambda K: jnp.tensordot(coeffs, K, axes=1), ks)


class LieInterpolation(AbstractLocalInterpolation):
    r"""`LieRK`'s dense output on one step: $y(t) = \exp(\sigma(t)) \cdot y_0$, finished
    as the end point is; `sigma` interpolates the algebra increment ($\sigma(t_0) = 0$,
    $\sigma(t_1) = \sum_i b_i k_i$)."""

    t0: Any
    t1: Any
    y0: Any
    sigma: AbstractLocalInterpolation
    group: AbstractLieAction

    def evaluate(self, t0, t1=None, left=True):
        del left
        if t1 is not None:
            return tree_sub(self.evaluate(t1), self.evaluate(t0))
        return self.group.finish(self.group.act(self.sigma.evaluate(t0), self.y0))


class _LieInterpolationCls(eqx.Module):
    """`LieRK.interpolation_cls`: a `LieInterpolation` from a step's `dense_info` (a Module,
    compared by value: diffrax's `DenseInterpolation` keeps it as a static field)."""

    algebra: Callable[..., AbstractLocalInterpolation] = eqx.field(static=True)

    def __call__(self, *, t0, t1, y0, u, k, group):
        zero = jtu.tree_map(jnp.zeros_like, u)
        sigma = self.algebra(t0=t0, t1=t1, y0=zero, y1=u, k=k)
        return LieInterpolation(t0=t0, t1=t1, y0=y0, sigma=sigma, group=group)


class LieRK(AbstractAdaptiveSolver):
    r"""A Runge-Kutta-Munthe-Kaas (RKMK) method on $T(S^2)^n$ over the Butcher tableau
    of any explicit diffrax Runge-Kutta solver: `LieRK(diffrax.Dopri5())`,
    `LieRK(sphere_mech.RK4())`, ...

    A step writes $y = \exp(u) \cdot y_0$ for a Lie group acting on the tangent bundle
    and integrates $u$ in the algebra: $u_i = \sum_j a_{ij} k_j$,
    $k_i = h\, \mathrm{dexp}_{u_i}^{-1}\big(\xi(\exp(u_i) \cdot y_0)\big)$ ($\xi(y)$ the
    algebra element whose infinitesimal action at $y$ is the vector field),
    $y_1 = \exp(\sum_i b_i k_i) \cdot y_0$. $\mathrm{dexp}^{-1}$ is in closed form, so
    the method has the tableau's order (tests/test_liegroup.py: 3 for Bosh3, 4 for RK4,
    5 for Dopri5 and Tsit5, 8 for Dopri8). The embedded pair gives the error estimate,
    for any diffrax step-size controller (or `diffrax.ConstantStepSize()`). $f(y_1)$ is
    reused as the next first stage: a first-same-as-last tableau (Bosh3, Dopri5, Tsit5,
    Dopri8, RK4's embedded stage) costs `num_stages - 1` evaluations a step.

    Dense output is the tableau's continuous extension carried through the algebra,
    $y(t_0 + \theta h) = \exp(\sigma(\theta)) \cdot y_0$, $\sigma(\theta) = \sum_i
    b_i(\theta) k_i$ (the wrapped solver's `interpolation_cls` on the stages, which are
    ordinary RK stages of $\sigma' = \mathrm{dexp}^{-1}_\sigma(h\,\xi)$: the order is
    kept); a tableau that is not first-same-as-last (`Heun`, `Midpoint`, ...) gets the
    cubic Hermite of $\sigma$ from $k_1$ and $\mathrm{dexp}^{-1}_{\sigma(1)}(h\,\xi(y_1))$.
    Dense points lie on the spheres and in the tangent planes to rounding; the wrapped
    interpolation must be linear in `(y0, y1, k)`, as diffrax's are.

    **Arguments:**
    - `solver`: an explicit Runge-Kutta solver (any `diffrax.AbstractERK` or
      `sphere_mech.RK4()`); only its tableau and order are read.
    - `action`: the group acting on $T(S^2)^n$, one copy per sphere (Euclidean factors
      of a mixed space are translated, $(x, v) \mapsto (x + a, v + b)$, by either):
        - `"SE3"` (default): $SE(3)$ acting by
          $(A, b) \cdot (q, \omega) = (A q, A \omega + b \times A q)$ on the angular form
          (Celledoni, Cokaj, Leone, Murari, Owren 2022; linear variables are converted,
          $\omega_i = q_i \times v_i$): $|q_i| = 1$ and $q_i \cdot v_i = 0$ to rounding
          with no projection. Needs a `MechanicsTerm` (as `simulate` uses); as cheap as
          `"SO3xR3"` for the same error (benchmarks/nfold_pendulum.py).
        - `"SO3xR3"`: $SO(3)^n \times \mathbb{R}^{3n}$, rotating each $q_i$ by
          $\exp(\widehat{w_i})$, $w_i = q_i \times \dot q_i$, and translating $v$ (its
          normal part removed after each step); any diffrax term with state `(q, v)`.
    - `error`: `"state"` (default), the difference of the two solutions; or `"algebra"`,
      $\sum_i (b_i - \hat b_i) k_i$ as a state-shaped pair (the paper's estimate).

    **Returns:** a diffrax `AbstractAdaptiveSolver` (`jit`, `vmap` and `grad` compose with
    it). A non-finite step is rejected, or with fixed steps reported `RESULTS.nonfinite`.

    Reference: H. Munthe-Kaas, High order Runge-Kutta methods on manifolds, Appl.
    Numer. Math. 29 (1999) 115-127.
    """

    solver: AbstractERK | RK4
    action: str = eqx.field(static=True, default="SE3")
    error: str = eqx.field(static=True, default="state")

    @property
    def term_structure(self):
        """`MechanicsTerm` for `"SE3"` (it needs the system), else any diffrax term."""
        return MechanicsTerm if self.action == "SE3" else AbstractTerm

    @property
    def interpolation_cls(self):
        """The wrapped solver's interpolation of the algebra increment, or cubic Hermite."""
        if self.solver.tableau.fsal:
            return _LieInterpolationCls(self.solver.interpolation_cls)
        return _LieInterpolationCls(ThirdOrderHermitePolynomialInterpolation.from_k)

    def __check_init__(self):
        # a wrapper passes `isinstance` (diffrax's `AbstractWrappedSolver`) but has no tableau
        if isinstance(self.solver, AbstractWrappedSolver) or not isinstance(
            self.solver, AbstractERK | RK4
        ):
            raise ValueError(
                "LieRK needs an explicit Runge-Kutta solver with a Butcher tableau "
                "(diffrax.Dopri5(), diffrax.Tsit5(), diffrax.Bosh3(), diffrax.Dopri8(), "
                f"sphere_mech.RK4(), ...), got {described(self.solver)}."
            )
        if self.action not in ACTIONS:
            raise ValueError(f"LieRK: action must be one of {ACTIONS}, got {self.action!r}.")
        if self.error not in ERROR_ESTIMATES:
            raise ValueError(f"LieRK: error must be one of {ERROR_ESTIMATES}, got {self.error!r}.")

    def order(self, terms):
        return self.solver.order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def _group(self, terms, y) -> AbstractLieAction:
        """The group action this solver moves states `y` with."""
        space = space_of(terms, y, "LieRK")
        angular = self.action == "SE3" and system_of(terms).angular  # SO3xR3: any term
        return space.lie_action(self.action, angular)

    def _stage_rows(self, dtype):
        """`(i, a_i, c_i)` of the stages computed inside a step (0-based `i` from 1; not an
        FSAL tableau's last), `a_i` padded to length `s`."""
        tableau = self.solver.tableau
        a = stage_coefficients(tableau, tableau.num_stages - tableau.fsal)[1:]
        index = jnp.arange(1, len(a) + 1)
        return index, jnp.asarray(a, dtype), jnp.asarray(tableau.c[: len(a)], dtype)

    def init(self, terms, t0, t1, y0, args):
        self._group(terms, y0)  # a static error now if the action cannot work with `terms`
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        tableau, group = self.solver.tableau, self._group(terms, y0)
        h = terms.contr(t0, t1)
        f0 = solver_state
        if not (isinstance(made_jump, bool) and not made_jump):
            f0 = lax.cond(jnp.any(made_jump), lambda: terms.vf(t0, y0, args), lambda: f0)
        dtype = jnp.result_type(*jtu.tree_leaves(y0))
        rows, s = self._stage_rows(dtype), tableau.num_stages
        # The stages' algebra elements k_1..k_s stacked per leaf (an FSAL k_s comes last).
        k1 = group.algebra(y0, terms.prod(f0, h))
        ks = jtu.tree_map(lambda k: jnp.zeros((s,) + k.shape, k.dtype).at[0].set(k), k1)

        def stage(ks, row):
            i, a, c = row
            u = _combine(a, ks)
            y = group.act(u, y0)
            k = group.dexpinv(u, group.algebra(y, terms.vf_prod(t0 + c * (t1 - t0), y, args, h)))
            return jtu.tree_map(lambda K, x: K.at[i].set(x), ks, k), None

        ks, _ = lax.scan(stage, ks, rows)
        u = _combine(jnp.asarray(tableau.b_sol, dtype), ks)
        y1_unfinished = group.act(u, y0)
        y1 = group.finish(y1_unfinished)
        f1 = terms.vf(t1, y1, args)
        # The rate at y1: an FSAL tableau's last stage (u_s = u), else the Hermite's end slope.
        k_end = group.dexpinv(u, group.algebra(y1, terms.prod(f1, h)))
        if tableau.fsal:
            ks = k_dense = jtu.tree_map(lambda K, x: K.at[s - 1].set(x), ks, k_end)
        else:
            k_dense = jtu.tree_map(lambda a, b: jnp.stack([a[0], b]), ks, k_end)
        y_error = _combine(jnp.asarray(tableau.b_error, dtype), ks)  # error="algebra"
        if self.error == "state":
            y_error = tree_sub(y1_unfinished, group.act(tree_sub(u, y_error), y0))
        dense_info = dict(y0=y0, u=u, k=k_dense, group=group)
        return y1, y_error, dense_info, f1, RESULTS.successful

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)


def LieRK4() -> LieRK:
    """`LieRK(RK4())`: the Runge-Kutta-Munthe-Kaas method of order 4 with an embedded
    order-3 estimate and `LieRK`'s default action (`"SE3"`, on a `MechanicsTerm` as
    `simulate` builds), adaptive or with fixed steps; 4 evaluations per step
    (`LieRK(RK4(), action="SO3xR3")` for any diffrax term whose state is `(q, v)`).
    **Returns:** the `LieRK` solver."""
    return LieRK(RK4())
