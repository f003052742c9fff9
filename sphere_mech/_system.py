"""The abstract systems: `AbstractSystem` (every mechanical system on (S^2)^n) and its two
families, `AbstractLagrangianSystem` and `AbstractHamiltonianSystem`."""

import abc
import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu

from ._checks import check_function, check_scalar, check_time
from ._custom_types import Args, ForceFn, Points, Scalar, State, Tangents
from ._misc import all_finite, state_arrays, tree_dtype, tree_sub, tree_vdot
from ._spaces import AbstractSpace

SINGULAR_MESSAGE = (
    "the reduced mass matrix T^T (d^2 L / d v^2) T is singular or not finite: the "
    "Lagrangian is degenerate at this state (for example a zero mass or length); or dL/dq "
    "or the forces are NaN or infinite here"
)
NONFINITE_PARAMETERS = (
    "the equations of motion are not finite and args or the system's parameters contain "
    "NaN or infinite values"
)


def check_rates(x, message: str, system, args):
    """Error (at run time) when the rates `x` are not finite, blaming NaN or infinite
    leaves of `args` or `system` if any, else `message`."""
    inexact = lambda x: eqx.is_inexact_array(x) or isinstance(x, float | complex)
    params = eqx.filter((system, args), inexact)
    return eqx.branched_error_if(
        x, ~all_finite(x), jnp.where(all_finite(params), 1, 0), [NONFINITE_PARAMETERS, message]
    )


def as_time(t, like: jax.Array) -> jax.Array:
    """`t` as a scalar array of `like`'s floating dtype (differentiable)."""
    return jnp.asarray(t, dtype=tree_dtype(like))


class _Static:
    """A static leaf as part of a `jax.jit` cache key: by type and value when hashable
    (floats, functions; `1.0` and `np.float32(1.0)` promote differently, so they differ),
    else by identity (NumPy arrays, which stay concrete inside the trace)."""

    __slots__ = ("value", "hashable")

    def __init__(self, value):
        self.value = value
        try:
            hash(value)
            self.hashable = True
        except TypeError:
            self.hashable = False

    def __hash__(self):
        return hash((type(self.value), self.value)) if self.hashable else id(self.value)

    def __eq__(self, other):
        if not isinstance(other, _Static) or type(self.value) is not type(other.value):
            return False
        if self.hashable and other.hashable:
            return bool(self.value == other.value)
        return self.value is other.value


@functools.partial(jax.jit, static_argnums=(0, 1))
def _jitted_rates(treedef, static, dynamic):
    leaves = [s.value if s is not None else d for s, d in zip(static, dynamic, strict=True)]
    system, t, y, args = jtu.tree_unflatten(treedef, leaves)
    return system.rates(t, y, args)


def vector_field(system: "AbstractSystem", t, y, args):
    """`system.rates(t, y, args)` traced once per system, argument shapes and dtypes: its
    jaxpr is cached (as `jax.jit` caches) and reused by every later call in any trace.
    A solve evaluates the vector field in many places (each Runge-Kutta stage, the
    loop's first pass, and again under `jax.jvp`, `jax.vmap` and reverse mode, which
    transform the cached jaxpr instead of tracing Python again); the notebook's cable
    quadrotor traced `simulate` in 7.8 s without it and 4.1 s with it (forward-mode
    Jacobian 22.8 s and 7.4 s). The compiled program is the same (XLA inlines the call).
    JAX arrays (tracers included) are the jitted function's arguments; every other leaf
    (floats, functions, NumPy arrays) is static, as it is in `system.rates`."""
    leaves, treedef = jtu.tree_flatten((system, t, y, args))
    is_dynamic = [isinstance(x, jax.Array) for x in leaves]
    static = tuple(None if d else _Static(x) for x, d in zip(leaves, is_dynamic, strict=True))
    dynamic = [x if d else None for x, d in zip(leaves, is_dynamic, strict=True)]
    return _jitted_rates(treedef, static, dynamic)


def check_system(system, what: str) -> None:
    """Static check: `system` a sphere_mech system (an instance of `AbstractSystem`), else a
    `TypeError` saying what to wrap a bare `L` or `H` in, for `what` (the caller)."""
    if isinstance(system, AbstractSystem):
        return
    got = f"the class {system.__name__}" if isinstance(system, type) else type(system).__name__
    raise TypeError(
        f"{what} takes a mechanical system, an instance such as sm.Lagrangian(L), "
        f"sm.Hamiltonian(H) or a Scene (wrap a bare function L or H in one), got {got}."
    )


class AbstractSystem(eqx.Module):
    """A mechanical system with state `(q, v)`: `q` `(n, 3)` unit vectors, `v` tangent,
    named by `state_name`: `qdot`, `omega` (Lagrangian forms), `mu`, `pi` (Hamiltonian);
    `angular` for `omega`, `pi` (`q_i x` the linear one). `forces`: `None` or
    `forces(t, q, v, args) -> (n, 3)` (virtual work `sum_i f_i . delta q_i`). `space`:
    `Spheres()` for plain arrays, a `Product` (dict states) for mixed spaces; every form,
    check and solver asks it for projections, tangent bases and angular variables.
    Concrete systems implement `rates`, `energy` and `velocity`."""

    forces: eqx.AbstractVar[ForceFn | None]
    space: eqx.AbstractVar[AbstractSpace]
    state_name: eqx.AbstractClassVar[str]
    angular: eqx.AbstractClassVar[bool]

    def __check_init__(self):
        if self.forces is not None:
            spelled = f"forces(t, q, {self.state_name}, args) -> (n, 3)"
            check_function(self.forces, "forces", spelled, 4)

    @abc.abstractmethod
    def rates(self, t, y: State, args: Args) -> State:
        """`d(q, v)/dt`: the vector field handed to diffrax, unchecked (Runge-Kutta stages
        may be slightly off the spheres).

        **Arguments:**
        - `t`, `y`, `args`: time, the state `(q, v)` and the user's `args`.

        **Returns:** `(qdot, vdot)`, `(n, 3)` arrays."""

    @abc.abstractmethod
    def energy(self, t, q: Points, v: Tangents, args: Args = None) -> Scalar:
        """Total energy (the Hamiltonian) at the state `(q, v)`.

        **Arguments:**
        - `t`, `q`, `v`, `args`: time, `(n, 3)` unit vectors, the state variable, `args`.

        **Returns:** a scalar."""

    @abc.abstractmethod
    def velocity(self, t, q: Points, v: Tangents, args: Args = None) -> Tangents:
        """`qdot` at the state `(q, v)`.

        **Arguments:**
        - `t`, `q`, `v`, `args`: as in `energy`.

        **Returns:** `qdot`, `(n, 3)`."""

    @property
    def state_space(self) -> AbstractSpace:
        """The space of the states `(q, v)`: `space`, in angular variables when the system's
        are angular (only rotations differ: body `(k, 3)` vectors)."""
        return self.space.angular() if self.angular else self.space

    @property
    def has_forces(self) -> bool:
        """Whether non-conservative forces act (static)."""
        return self.forces is not None

    def generalized_force(self, t, q: Points, v: Tangents, args: Args = None):
        """The generalized force at `(q, v)` (virtual work `sum_i f_i . delta q_i`).

        **Arguments:**
        - `t`, `q`, `v`, `args`: as in `energy`.

        **Returns:** `f`, `(n, 3)`, or `None` without forces (nothing compiled)."""
        if self.forces is None:
            return None
        f = self.forces(as_time(t, q), q, v, args)
        self.space.check_forces(f, q)
        # in the state's dtype: a float64 constant in `forces` must not promote a float32 state
        f = jax.tree.map(lambda f_, q_: jnp.asarray(f_, dtype=q_.dtype), f, q)
        return self.space.force_covector(q, f)

    def power(self, t, q: Points, v: Tangents, args: Args = None) -> Scalar:
        """Power of the generalized forces, `sum_i f_i . qdot_i`.

        **Arguments:**
        - `t`, `q`, `v`, `args`: as in `energy`.

        **Returns:** a scalar (zero without forces)."""
        f = self.generalized_force(t, q, v, args)
        if f is None:
            return jnp.zeros((), dtype=tree_dtype(q))
        return tree_vdot(f, self.velocity(t, q, v, args))

    def check_state(self, q: Points, v: Tangents) -> State:
        """Raise a clear error if `(q, v)` is not a valid state (shapes, unit length and
        tangency within `unit_tolerance`).

        **Arguments:**
        - `q`, `v`: `(n, 3)` unit vectors and the second state variable, tangent at `q`
          (nested lists are read as float arrays, as `simulate` reads them).

        **Returns:** the state `(q, v)`, as arrays."""
        q, v = state_arrays(q, v)
        self.state_space.check_shapes(q, v, self.state_name)
        return self.state_space.check_values(q, v, self.state_name)

    def to_linear(self, q: Points, v: Tangents) -> Tangents:
        """The linear variable (`qdot` or `mu`) of the state variable `v`.

        **Arguments:**
        - `q`, `v`: `(n, 3)` unit vectors and the state variable.

        **Returns:** `omega x q` for angular forms, `v` otherwise."""
        return self.space.to_linear(q, v) if self.angular else v

    def from_linear(self, q: Points, x: Tangents) -> Tangents:
        """The state variable of the linear variable `x` (`qdot` or `mu`).

        **Arguments:**
        - `q`, `x`: `(n, 3)` unit vectors and `qdot` or `mu`.

        **Returns:** `q x x` for angular forms, `x` otherwise."""
        return self.space.from_linear(q, x) if self.angular else x

    def from_covector(self, q: Points, x: Tangents) -> Tangents:
        """The momentum variable of the state (`mu` or `pi`) of a linear covector `x`
        (one that pairs with `qdot`, such as `mu = P dL/dqdot`).

        **Arguments:**
        - `q`, `x`: `(n, 3)` unit vectors and the covector, tangent at `q`.

        **Returns:** `q x x` for angular forms (`2 vee(R^T x)` on rotations), `x`
        otherwise."""
        return self.space.from_covector(q, x) if self.angular else x


class AbstractLagrangianSystem(AbstractSystem):
    """A system given by a Lagrangian `L(t, q, v, args)` (`v`: `qdot`, form 1, or `omega`,
    form 2); `quadratic_in_velocity` (`L` at most quadratic in `v`) makes the inverse
    Legendre map one linear solve instead of Newton's method."""

    quadratic_in_velocity: eqx.AbstractVar[bool]

    @abc.abstractmethod
    def lagrangian(self, t, q: Points, v: Tangents, args: Args) -> Scalar:
        """The Lagrangian in the system's own velocity variable.

        **Arguments:**
        - `t`, `q`, `v`, `args`: time, `(n, 3)` unit vectors, `qdot` or `omega`, `args`.

        **Returns:** a scalar."""

    @abc.abstractmethod
    def _vdot(self, t, q: Points, v: Tangents, args: Args) -> Tangents:
        """`dv/dt` from the Euler-Lagrange equations, with no input checks."""

    def rates(self, t, y, args):
        q, v = y
        return self.to_linear(q, v), self._vdot(t, q, v, args)

    def acceleration(self, t, q: Points, v: Tangents, args: Args = None) -> Tangents:
        """`qddot` at the state `(q, v)` (Proposition 1; in form 2 the time derivative of
        `omega x q`). Checks the state and raises on a singular reduced mass matrix.

        **Arguments:**
        - `t`, `q`, `v`, `args`: as in `lagrangian`, `v` tangent at `q`.

        **Returns:** `qddot`, `(n, 3)`."""
        check_time(t)
        q, v = self.check_state(q, v)
        qddot = jax.jvp(self.to_linear, (q, v), self.rates(t, (q, v), args))[1]
        return check_rates(qddot, SINGULAR_MESSAGE, self, args)

    def velocity(self, t, q, v, args=None):
        return self.to_linear(*state_arrays(q, v))

    def lagrangian_qdot(self, t, q: Points, qdot: Tangents, args: Args) -> Scalar:
        """The Lagrangian as a function of `qdot`, whatever the form.

        **Arguments:**
        - `t`, `q`, `qdot`, `args`: as in `lagrangian`, with velocities `qdot`.

        **Returns:** a scalar."""
        return self.lagrangian(t, q, self.from_linear(q, qdot), args)

    def _dL_dv(self, t, q, v, args) -> Tangents:
        L = lambda v_: check_scalar(self.lagrangian(t, q, v_, args), "L(t, q, v, args)")
        return jax.grad(L)(v)

    def momentum(self, t, q: Points, v: Tangents, args: Args = None) -> Tangents:
        """The conjugate momentum `P dL/dv` (`mu` in form 1, `pi` in form 2).

        **Arguments:**
        - `t`, `q`, `v`, `args`: as in `lagrangian`.

        **Returns:** the momentum, `(n, 3)`, tangent at `q`."""
        q, v = state_arrays(q, v)
        return self.state_space.project(q, self._dL_dv(t, q, v, args))

    def energy(self, t, q, v, args=None):
        """The energy `E = sum_i v_i . dL/dv_i - L`.

        **Arguments:**
        - `t`, `q`, `v`, `args`: as in `lagrangian`.

        **Returns:** a scalar."""
        q, v = state_arrays(q, v)
        return tree_vdot(v, self._dL_dv(t, q, v, args)) - self.lagrangian(t, q, v, args)

    @abc.abstractmethod
    def velocity_from_momentum(self, t, q: Points, p: Tangents, args: Args = None, **options):
        """The inverse Legendre map: the tangent velocity `v` with `P dL/dv = p`.

        **Arguments:**
        - `t`, `q`, `p`, `args`: as in `lagrangian`, with the momentum `p` (`mu` or `pi`).
        - `options`: `guess`, `quadratic`, `tol`, `max_steps` of the general method (Newton).

        **Returns:** `(v, result)`: the velocity and a `diffrax.RESULTS` code, `successful`
        or `singular` (never raised here; `sm.RESULTS.promote(result)` makes it one of
        `sm.RESULTS`, which sits in a layer above the systems)."""


class AbstractHamiltonianSystem(AbstractSystem):
    """A system given by a Hamiltonian `H(t, q, p, args)` in its momentum `p` (`mu`,
    form 3, or `pi`, form 4). Hamilton's equations need gradients of `H` only."""

    H: eqx.AbstractVar[Callable]

    def __check_init__(self):
        check_function(self.H, "H", f"H(t, q, {self.state_name}, args)", 4)

    @abc.abstractmethod
    def _hamilton(self, q, p, dH_dp, dH_dq_less_f) -> State:
        """`(qdot, pdot)` from the gradients of `H` and `dH/dq - f`."""

    def rates(self, t, y, args):
        q, p = y
        dH_dq, dH_dp = self._gradients(t, q, p, args)
        f = self.generalized_force(t, q, p, args)
        return self._hamilton(q, p, dH_dp, dH_dq if f is None else tree_sub(dH_dq, f))

    def _gradients(self, t, q, p, args):
        H = lambda q_, p_: check_scalar(self.H(as_time(t, q), q_, p_, args), "H(t, q, p, args)")
        return jax.grad(H, argnums=(0, 1))(q, p)

    def energy(self, t, q, p, args=None):
        """The Hamiltonian `H(t, q, p, args)`.

        **Arguments:**
        - `t`, `q`, `p`, `args`: time, `(n, 3)` unit vectors, `mu` or `pi`, `args`.

        **Returns:** a scalar."""
        q, p = state_arrays(q, p)
        return check_scalar(self.H(t, q, p, args), "H(t, q, p, args)")

    def velocity(self, t, q, p, args=None):
        """`qdot = P dH/dmu`; in angular variables `dH/dpi x q`.

        **Arguments:**
        - `t`, `q`, `p`, `args`: as in `energy`.

        **Returns:** `qdot`, `(n, 3)`."""
        q, p = state_arrays(q, p)
        dH_dp = self._gradients(t, q, p, args)[1]
        return self.to_linear(q, dH_dp) if self.angular else self.space.project(q, dH_dp)

    def vector_field(self, t, q: Points, p: Tangents, args: Args = None) -> State:
        """`(qdot, pdot)` from Hamilton's equations, after checking the state.

        **Arguments:**
        - `t`, `q`, `p`, `args`: as in `energy`; `p` tangent at `q`.

        **Returns:** `(qdot, pdot)` (`(qdot, mudot)` in form 3, `(qdot, pidot)` in form 4)."""
        check_time(t)
        q, p = self.check_state(q, p)
        message = (
            "Hamilton's equations are not finite at this state: H or its gradient is NaN "
            "or infinite (a degenerate Hamiltonian; for sm.legendre(system): the Legendre "
            "transform is not invertible at this state, e.g. a zero mass or a sphere "
            "without kinetic energy; or NaN parameters)"
        )
        return check_rates(self.rates(t, (q, p), args), message, self, args)
