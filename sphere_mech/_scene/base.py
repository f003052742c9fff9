"""The kinds of effect a scene is assembled from, and the checks their parameters share."""

import abc
import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import unit_tolerance
from .._misc import is_integer

MAX_MAGNITUDE = 1e100
"""The largest magnitude of a parameter: products of a few (`m g l`, `m v^2`) stay finite."""
MAX_COUNT = 100_000
"""The most items (links, particles, beads) one kinetic term may have."""


def as_float(x, name: str, what: str = "a number or an array of numbers") -> jax.Array:
    """`x` as a floating array (float64 when x64 is enabled); booleans, strings, `None` and
    ragged lists (anything NumPy does not read as an integer or floating array) are
    refused with a `ParameterError` naming the field `name` and saying it expected `what`."""
    traced = any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(x))
    if not traced:
        try:
            kind = np.asarray(x).dtype.kind
        except ValueError:  # ragged: "setting an array element with a sequence"
            kind = "O"
        if kind not in "iuf":
            raise ParameterError(name, f"{name}: expected {what}, got {x!r}")
        message = overflow(name, np.asarray(x, dtype=np.float64))
        if message:
            raise ParameterError(name, message)
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


def overflow(name: str, a: np.ndarray) -> str | None:
    """What to say if finite values of `a` overflow JAX's default float (float32 unless
    x64 is enabled), else `None` (before: `1e50` became `inf` and was reported as such)."""
    dtype = jnp.result_type(float)
    big = np.abs(a[np.isfinite(a)])
    if big.size and big.max() > jnp.finfo(dtype).max:
        return (
            f"{name} must be at most {float(jnp.finfo(dtype).max):.3g} in magnitude in {dtype} "
            f"(enable float64: jax.config.update('jax_enable_x64', True)), got {big.max():g}"
        )
    return None


def number(name: str):
    """The converter of the field `name`: `as_float`, its errors naming the field."""
    return lambda x: as_float(x, name)


class ParameterError(ValueError):
    """A `ValueError` naming its field (and, from a scene's checks, the effect)."""

    def __init__(self, field: str, message: str):
        super().__init__(message)
        self.field, self.effect = field, None


def _concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _show(x) -> str:
    return str(np.asarray(x).tolist())


def check_magnitude(name: str, x) -> None:
    """`x` finite and within `MAX_MAGNITUDE` elementwise, unless traced."""
    a = np.asarray(x) if _concrete(x) else None
    if a is None or not jnp.issubdtype(a.dtype, jnp.inexact):
        return
    bad = ~(np.abs(a).astype(np.float64) <= MAX_MAGNITUDE)  # NaN too; float32 compared in 64
    if np.any(bad):
        message = f"{name} must be finite and at most {MAX_MAGNITUDE:g} in magnitude"
        raise ParameterError(name, f"{message}, got {a[bad].flat[0]:g}")


def check_fields(module: eqx.Module) -> None:
    """`check_magnitude` on every floating array field of `module`."""
    for field in dataclasses.fields(module):
        x = getattr(module, field.name)
        if isinstance(x, jax.Array | np.ndarray):
            check_magnitude(field.name, x)


def check_shape(name: str, x, shape: tuple, what: str) -> None:
    if jnp.shape(x) != shape:
        raise ParameterError(name, f"{name} must be {what}, got shape {jnp.shape(x)}")


def check_vector(name: str, x, unit: bool = False, what: str = "a (3,) vector") -> None:
    """A finite `(3,)` vector (`what` names it in the shape error), of length 1 if `unit`."""
    check_shape(name, x, (3,), what)
    check_magnitude(name, x)
    tol = unit_tolerance(jnp.result_type(x))
    if unit and _concrete(x) and not abs(np.linalg.norm(x) - 1.0) <= tol:
        message = f"{name} must be a unit vector (length 1 within {tol:g}), got {_show(x)}"
        raise ParameterError(name, message)


def check_axes(name: str, x) -> None:
    """`(m, 3)` rows, `1 <= m <= 3`, orthonormal within `unit_tolerance` (unless traced)."""
    if jnp.ndim(x) != 2 or jnp.shape(x)[1] != 3 or not 1 <= jnp.shape(x)[0] <= 3:
        check_shape(name, x, None, "an (m, 3) array of m = 1, 2 or 3 directions")
    if _concrete(x):
        x, tol = np.asarray(x), unit_tolerance(jnp.result_type(x))
        error = np.max(np.abs(x @ x.T - np.eye(x.shape[0])))
        if not error <= tol:
            what = f"orthonormal rows (unit length, mutually perpendicular, within {tol:g})"
            raise ParameterError(name, f"{name} must be {what}, got {_show(x)}")


def check_sign(name: str, x, unit: str = "", *, strict: bool = True, scalar=False) -> None:
    """`x > 0` (`>= 0` if not strict) elementwise, unless traced; a scalar if `scalar`."""
    if scalar:
        check_shape(name, x, (), "a scalar")
    check_magnitude(name, x)
    if _concrete(x) and not np.all(np.asarray(x) > 0 if strict else np.asarray(x) >= 0):
        message = f"{name} must be {'>' if strict else '>='} 0{unit}, got {_show(x)}"
        raise ParameterError(name, message)


def check_index(owner, name: str, i, n: int) -> None:
    """An integer (not a bool or a float) with Python's convention: `-n <= i < n`."""
    if not (is_integer(i) and -n <= i < n):
        what = f"an integer sphere index in [-{n}, {n}) (the scene has {n} spheres)"
        raise ParameterError(name, f"{type(owner).__name__}.{name} must be {what}, got {i!r}")


def per_item(count: int | None, count_name: str, **arrays) -> list[jax.Array]:
    """Arrays of one value per item, scalars broadcast to `count` (argument `count_name`;
    default: the 1-D arrays' length; at most `MAX_COUNT`, checked before allocating)."""
    if count is not None and not (is_integer(count) and 1 <= count <= MAX_COUNT):
        message = f"{count_name} must be an integer from 1 to {MAX_COUNT}, got {count!r}"
        raise ParameterError(count_name, message)
    arrays = {k: as_float(v, k) for k, v in arrays.items()}
    if count is None:
        count = max((jnp.shape(v)[0] for v in arrays.values() if jnp.ndim(v) == 1), default=1)
    if not 1 <= count <= MAX_COUNT:
        message = f"{', '.join(arrays)}: need from 1 to {MAX_COUNT} values, got {count}"
        raise ParameterError(next(iter(arrays)), message)
    out = [jnp.broadcast_to(x, (count,)) if jnp.ndim(x) == 0 else x for x in arrays.values()]
    for name, x in zip(arrays, out, strict=True):
        check_shape(name, x, (count,), f"a scalar or {count} values, one per sphere")
    return out


class _Checked(eqx.Module):
    """Every floating array field finite and within `MAX_MAGNITUDE`; an optional `check`."""

    def __check_init__(self):
        check_fields(self)

    def check(self, scene) -> None:
        """Raise `ValueError` if this does not fit `scene` (indices, counts); an optional
        hook, by default checking nothing."""


class AbstractEffect(_Checked):
    """Anything a scene can list: parameters are array leaves (checked in `__check_init__`),
    counts and indices static (checked against the scene in `check`)."""


class Drawing(NamedTuple):
    """What a picture shows of a kinetic term, its masses numbered from 0 (its own):
    polylines `links`, each `(support, masses)` (the fixed `(3,)` point, or a moving
    `Base`'s, and the masses joined in order); `spheres`, `(centre, radius)` of each
    sphere several masses share; `free`, the masses on no link."""

    links: tuple[tuple[np.ndarray, tuple[int, ...]], ...] = ()
    spheres: tuple[tuple[np.ndarray, float], ...] = ()
    free: tuple[int, ...] = ()


class AbstractKinetic(AbstractEffect):
    """A block of spheres carrying one point mass each, with a constant scalar inertia:
    kinetic energy `1/2 sum_jk M_jk qdot_j . qdot_k` on its own spheres."""

    masses: eqx.AbstractVar[jax.Array]

    @property
    def n(self) -> int:
        """Number of spheres (= number of masses), static."""
        return self.masses.shape[0]

    @abc.abstractmethod
    def point_masses(self) -> jax.Array:
        """The masses the spheres carry (`masses` plus any payload). **Returns:** `(n,)` (kg)."""

    @abc.abstractmethod
    def inertia(self) -> jax.Array:
        """The block's scalar inertia matrix. **Returns:** `M`, `(n, n)`."""

    @abc.abstractmethod
    def inverse_inertia_bands(self) -> tuple[jax.Array, jax.Array]:
        """The bands of `M^-1`, tridiagonal for every kinetic term here (the O(n) fast path).
        **Returns:** its diagonal `(n,)` and off-diagonal `(n - 1,)`."""

    @abc.abstractmethod
    def positions(self, q: jax.Array) -> jax.Array:
        """Positions of the masses in the support frame.

        **Arguments:**
        - `q`: this block's unit vectors, `(n, 3)`.

        **Returns:** the positions, `(n, 3)` (m)."""

    @abc.abstractmethod
    def parents(self) -> tuple[int, ...]:
        """The joint structure, for joint damping and joint torques. **Returns:** each sphere's
        parent's local index (-1: the support)."""

    @abc.abstractmethod
    def bends(self) -> tuple[tuple[int, int], ...]:
        """Where bending stiffness acts. **Returns:** the local index pairs `(i, i + 1)` of
        consecutive links (may be none)."""

    @abc.abstractmethod
    def drawing(self) -> Drawing:
        """What a picture of this block shows (`sm.animate`, `sphere-mech run`'s figures),
        with concrete parameters, outside `jit`. **Returns:** a `Drawing`, numbered locally."""


class AbstractPotential(AbstractEffect):
    """A conservative effect: a potential energy `U(t, q)` of the scene's configuration."""

    @abc.abstractmethod
    def potential(self, t, q, scene, args) -> jax.Array:
        """The potential energy of the scene's configuration.

        **Arguments:**
        - `t`, `q`: time and the scene's unit vectors, `(n, 3)`.
        - `scene`, `args`: the `Scene` (positions, masses and joints) and the user's `args`.

        **Returns:** a scalar (J)."""


class AbstractForce(AbstractEffect):
    """A non-conservative or driven effect: a generalized force `f` with virtual work
    `sum_i f_i . delta q_i`."""

    @abc.abstractmethod
    def generalized_force(self, t, q, qdot, scene, args) -> jax.Array:
        """The generalized force, virtual work `sum_i f_i . delta q_i`.

        **Arguments:**
        - `t`, `q`, `qdot`: time, the scene's unit vectors and their velocities, `(n, 3)`.
        - `scene`, `args`: the `Scene` (positions, masses and joints) and the user's `args`.

        **Returns:** `f`, `(n, 3)`."""


class AbstractCommand(_Checked):
    """A flight command: `command(t) -> (x_d, b1_d)`, the desired position `(3,)` (m) and
    heading `(3,)` (the desired body `e1`, not parallel to the thrust) at time `t`. The
    controller takes its derivatives by autodiff: it must be smooth where it is flown
    (a step is smooth on either side of its time)."""

    @abc.abstractmethod
    def __call__(self, t) -> tuple[jax.Array, jax.Array]:
        """`(x_d, b1_d)` at `t`."""


class AbstractDrive(_Checked):
    """A controller for a torque or force: `drive(t, q, qdot, args) -> (3,)` (`(m,)` for a
    `BaseForce`, `(4,)` thrust and moments for `Rotors`; scene files write it as an inline
    table). Its floating arrays and `check` are as an effect's."""

    @abc.abstractmethod
    def __call__(self, t, q, qdot, args) -> jax.Array:
        """The torque or force."""
