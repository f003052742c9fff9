"""The variational (RATTLE-type) integrator on spheres, rotations and Euclidean factors as
a diffrax solver, and its symmetric composition of order 4."""

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from diffrax import (
    RESULTS,
    AbstractLocalInterpolation,
    AbstractSolver,
    ThirdOrderHermitePolynomialInterpolation,
)
from jax import lax

from .._misc import check_integer, check_positive, tree_dtype
from .._momentum import newton_tolerance
from .._system import vector_field
from .._term import MechanicsTerm, physical_time, system_of
from .discrete_mechanics import check_lagrangian, substep


class _StepInterpolation(AbstractLocalInterpolation):
    """diffrax's cubic Hermite dense output of a step, `inf` inside a failed step: fixed
    steps keep it, and the save times in it are unreached (before: a curve from y0 to y0)."""

    t0: jax.Array
    t1: jax.Array
    hermite: ThirdOrderHermitePolynomialInterpolation
    failed: jax.Array

    def __init__(self, *, t0, t1, y0, y1, k, failed):
        self.t0, self.t1, self.failed = t0, t1, failed
        self.hermite = ThirdOrderHermitePolynomialInterpolation.from_k(
            t0=t0, t1=t1, y0=y0, y1=y1, k=k
        )

    def evaluate(self, t0, t1=None, left=True):
        y = self.hermite.evaluate(t0, t1, left)
        unreached = self.failed & (True if t1 is not None else t0 > self.t0)
        return jtu.tree_map(lambda x: jnp.where(unreached, jnp.inf, x), y)


def composition_coefficients(order: int, composition: str) -> tuple[float, ...]:
    """Step fractions `gamma_k` (summing to 1) of the symmetric composition of the order-2
    step: `(1,)` for order 2; for order 4 Suzuki's 5-stage fractal or Yoshida's triple
    jump (Hairer, Lubich & Wanner, Geometric Numerical Integration, section II.4)."""
    if order not in (2, 4):
        raise ValueError(f"Variational: order must be 2 or 4, got {order!r}.")
    if composition == "suzuki":
        outer = 1.0 / (4.0 - 4.0 ** (1.0 / 3.0))
        return (1.0,) if order == 2 else (outer, outer, 1.0 - 4.0 * outer, outer, outer)
    if composition == "yoshida":
        outer = 1.0 / (2.0 - 2.0 ** (1.0 / 3.0))
        return (1.0,) if order == 2 else (outer, 1.0 - 2.0 * outer, outer)
    raise ValueError(
        f"Variational: composition must be 'suzuki' or 'yoshida', got {composition!r}."
    )


class Variational(AbstractSolver):
    """The variational integrator for Lagrangian systems on (S^2)^n, SO(3)^k and their
    products with Euclidean factors: the discrete Euler-Lagrange (RATTLE-type) equations
    of the trapezoidal discrete Lagrangian, with `|q_i| = 1` imposed by Lagrange
    multipliers. Symplectic, time-reversible (stepping back with `-h` returns the initial
    state to rounding), `|q_i| = 1` and `R^T R = I` to rounding, and for conservative
    systems an energy error bounded over millions of steps. Order 2; `order=4` composes
    the same step symmetrically (still symplectic and reversible).

    On a rotation factor (`Rotations`) it is the Lie group variational integrator of
    Lee, Leok and McClamroch: `R1 = R0 F`, `F = expm(h hat(xi))`, the discrete
    Lagrangian a function of `(R0, F)` (the chord's body velocity on both ends is
    `vee(F - F^T) / (2h)`), Newton's method on the rotation vector of `F`, and `R1`
    renormalized to the nearest rotation; body torques enter as on the spheres.

    For any `Lagrangian`, `AngularLagrangian`, `ConstantInertiaLagrangian` or `Scene`
    (Hamiltonian systems are refused with a `ValueError`): each (sub)step solves `2n`
    equations derived from `L` by autodiff (optimistix, implicit differentiation, so
    `jax.grad` works), from a predictor built from the accelerations: Newton's method
    (about two iterations, O(n^3)), or for constant-inertia systems (chains, scenes)
    Newton steps with the constant inertia, solved in O(n), Anderson-accelerated; both
    to the same tolerance. `L` is evaluated at the chord velocity projected on each
    tangent plane, so forms 1 and 2 give the same steps. Time-dependent `L` is supported
    (still symplectic). With forces it is the forced Lagrange-d'Alembert integrator
    (`h/2 f` at both ends): reversible in form, of the same order, not symplectic. On a
    mixed space a Euclidean factor steps by `x1 = x0 + h a` (tests/test_mixed.py), a
    rotation factor as above (tests/test_rotations.py).

    Fixed steps only (no error estimate): `sphere_mech.simulate(system, y0, t1,
    solver=Variational(), dt0=h)`, or `diffrax.diffeqsolve(sphere_mech.MechanicsTerm(
    system), Variational(), t0, t1, h, y0, args=args)`. A Newton iteration that does
    not converge is reported through the solution's `result` (raised by `simulate`
    unless `throw=False`); the state then stays at the last good step, and save times
    inside the failed step are `inf`, as those after it. diffrax labels that kept state
    with the failed step's end time (its `SaveAt(t1=True)` or `steps=True` entry): the
    time where the run stopped is one step earlier. The state is kept rather than made
    `inf` so that an event's condition does not change sign on the failed step, which
    diffrax would report as the event instead of the failure.

    **Arguments:**
    - `order`: 2 (the basic step) or 4 (a symmetric composition of it).
    - `composition` (order 4): `"suzuki"` (default; 5 substeps) or `"yoshida"` (3
      substeps, one backward and 1.7 times the step: Newton needs smaller steps).
    - `root_find_max_steps`: iterations allowed per substep (a positive integer, default
      32).
    - `root_find_tol`: Newton tolerance on the last correction and the residual, both
      relative: a number `> 0` and `< 1` (default `None`: `eps ** 0.75` of the state's
      dtype).
    - `fast_path`: whether constant-inertia systems use the O(n) iteration (default
      `True`). Its rate is about the angle a link turns per step times the spread of the
      inertia's eigenvalues: on too coarse steps it may run out of iterations where
      Newton's method (`False`, O(n^3)) still converges.
    - `root_finder` (the dense path): `"newton"` (default) factors the Jacobian at every
      iterate; `"chord"` factors it once per substep, at the predictor, and reuses it.
      Both solve the same equations to the same tolerance. The chord iteration contracts
      at a rate about the predictor's error, so on fine steps it takes as many
      iterations, each without a Jacobian: on the 3-D pendulum at h = 0.01 its steps
      were 1.5 to 2.3 times faster, batched on the CPU. On coarse steps it fails more
      often: 12 of 500 random 3-D pendulum states at h = 0.05 against Newton's 4 (a
      failure is reported, never silent).
    """

    gammas: tuple[float, ...] = eqx.field(static=True)
    claimed_order: int = eqx.field(static=True)
    root_find_max_steps: int = eqx.field(static=True)
    root_find_tol: float | None = eqx.field(static=True)
    fast_path: bool = eqx.field(static=True)
    root_finder: str = eqx.field(static=True)

    term_structure: ClassVar = MechanicsTerm
    interpolation_cls: ClassVar[Callable[..., AbstractLocalInterpolation]] = _StepInterpolation

    def __init__(
        self,
        order: int = 2,
        *,
        composition: str = "suzuki",
        root_find_max_steps: int = 32,
        root_find_tol: float | None = None,
        fast_path: bool = True,
        root_finder: str = "newton",
    ):
        if root_finder not in ("chord", "newton"):
            raise ValueError(
                f"Variational: root_finder must be 'chord' or 'newton', got {root_finder!r}."
            )
        check_integer(root_find_max_steps, "Variational: root_find_max_steps")
        if root_find_tol is not None:
            check_positive(root_find_tol, "Variational: root_find_tol")
            if not root_find_tol < 1:
                message = "Variational: root_find_tol must be < 1 (a relative tolerance)"
                raise ValueError(f"{message}, got {root_find_tol!r}.")
            root_find_tol = float(root_find_tol)
        self.gammas = composition_coefficients(order, composition)
        self.claimed_order = order
        self.root_find_max_steps = root_find_max_steps
        self.root_find_tol = root_find_tol
        self.fast_path = fast_path
        self.root_finder = root_finder

    def order(self, terms):
        return self.claimed_order

    def init(self, terms, t0, t1, y0, args):
        system = check_lagrangian(system_of(terms))
        return vector_field(system, physical_time(terms, t0), y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        system = check_lagrangian(system_of(terms))
        dtype = tree_dtype(y0)
        tol = newton_tolerance(dtype) if self.root_find_tol is None else self.root_find_tol
        start = jnp.asarray(physical_time(terms, t0), dtype=dtype)
        rates0 = solver_state
        if made_jump is not False:
            rates0 = lax.cond(
                made_jump, lambda: vector_field(system, start, y0, args), lambda: solver_state
            )
        # Backwards, diffrax reverses time and wraps the terms: the physical step is the control.
        h = jnp.asarray(terms.contr(t0, t1), dtype=dtype)
        h_safe = jnp.where(h == 0, jnp.ones_like(h), h)  # a zero-length step changes nothing

        def one(carry, gamma):
            t, y, rates, result = carry
            dt = gamma * h_safe
            y1, rates1, result1 = substep(
                system,
                t,
                dt,
                *y,
                rates,
                args,
                tol,
                self.root_find_max_steps,
                self.fast_path,
                self.root_finder == "chord",
            )
            result = RESULTS.where(result == RESULTS.successful, result1, result)
            return (t + dt, y1, rates1, result), None

        carry = (start, y0, rates0, RESULTS.successful)
        if len(self.gammas) == 1:
            carry, _ = one(carry, jnp.asarray(1.0, dtype=dtype))
        else:
            carry, _ = lax.scan(one, carry, jnp.asarray(np.array(self.gammas), dtype))
        _, y1, rates1, result = carry
        # On failure keep the last good state (`throw=False`).
        keep = (result == RESULTS.successful) & (h != 0)
        y1, rates1 = jtu.tree_map(lambda a, b: jnp.where(keep, a, b), (y1, rates1), (y0, rates0))
        k = jtu.tree_map(lambda a, b: jnp.stack([h * a, h * b]), rates0, rates1)
        failed = result != RESULTS.successful
        return y1, None, dict(y0=y0, y1=y1, k=k, failed=failed), rates1, result

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)
