"""Validation of user input: static problems raise `ValueError` at trace time, value
problems go through `equinox.error_if` (inside jit/vmap/grad)."""

import inspect

import jax
import jax.numpy as jnp
import numpy as np

from ._geometry import constraint_error, rotation_error

UNIT_TOLERANCE = {np.dtype("float64"): 1e-6, np.dtype("float32"): 1e-4}


def unit_tolerance(dtype) -> float:
    """How far from unit length (and from tangency) an input state may be: the checked
    entry points accept `max_i ||q_i| - 1| <= tol`, `max_i |q_i . v_i| <= tol (1 + max_i |v_i|)`.

    **Arguments:**
    - `dtype`: the floating dtype of the state.

    **Returns:** `tol`: `1e-6` for float64, `1e-4` for float32."""
    return UNIT_TOLERANCE.get(np.dtype(dtype), 1e-4)


def check_shapes(q, v, v_name: str = "v", q_name: str = "q") -> None:
    """Static checks: `q` is `(n, 3)` and `v` has the same shape."""
    q_shape, v_shape = jnp.shape(q), jnp.shape(v)
    if len(q_shape) != 2 or q_shape[-1] != 3:
        raise ValueError(
            f"{q_name} must have shape (n, 3) (one unit vector per sphere), got {q_shape}."
        )
    if q_shape[0] == 0:
        raise ValueError(f"{q_name} must hold at least one point (n >= 1), got shape (0, 3).")
    if v_shape != q_shape:
        raise ValueError(
            f"{v_name} must have the same shape as {q_name}, {q_shape}, got {v_shape} "
            f"({q_name} and the velocity or momentum must describe the same number of "
            "spheres)."
        )
    check_floating((q_name, q), (v_name, v))


def check_floating(*named) -> None:
    """Static check: each `(name, x)` of `named` is a float32 or float64 array (half
    precision ran until `max_steps`: its rounding is above every default tolerance)."""
    for name, x in named:
        if jnp.result_type(x) not in UNIT_TOLERANCE:
            raise ValueError(
                f"{name} must be a floating-point array of float32 or float64, got "
                f"{jnp.result_type(x)}."
            )


def nonfinite(x, name: str) -> tuple[jax.Array, str]:
    """`(problem, message)`: whether `x` has a NaN or infinity, and what to say then."""
    return ~jnp.all(jnp.isfinite(x)), f"{name} contains NaN or infinite values."


def off_unit(q, q_name: str = "q") -> tuple[jax.Array, str]:
    """`(problem, message)`: whether some `|q_i|` is off 1 by more than `unit_tolerance`."""
    tol = unit_tolerance(jnp.result_type(q))
    return constraint_error(q) > tol, (
        f"{q_name} is not on the spheres: some |q_i| differs from 1 by more than {tol:g} "
        "(normalize q, e.g. with sphere_mech.normalize)."
    )


def off_tangent(q, v, v_name: str = "v") -> tuple[jax.Array, str]:
    """`(problem, message)`: whether some `v_i` is not tangent within `unit_tolerance`."""
    tol = unit_tolerance(jnp.result_type(q))
    normal = jnp.max(jnp.abs(jnp.sum(q * v, axis=-1)))
    scale = 1.0 + jnp.max(jnp.linalg.norm(v, axis=-1))
    return normal > tol * scale, (
        f"{v_name} is not tangent to the spheres: some q_i . {v_name}_i exceeds {tol:g} "
        f"(relative); remove the normal part, e.g. with sphere_mech.project(q, {v_name})."
    )


def is_real(x) -> bool:
    """A real number or array of them: a Python or NumPy int or float (not a bool), or an
    array (or tracer) of an integer or floating dtype; not a string or a complex number."""
    if isinstance(x, bool | str | bytes | complex):
        return False
    if isinstance(x, int | float | np.integer | np.floating):
        return True
    return isinstance(x, jax.Array | np.ndarray) and (
        jnp.issubdtype(x.dtype, jnp.integer) or jnp.issubdtype(x.dtype, jnp.floating)
    )


def check_time(t, name: str = "t") -> None:
    """Static check: `t` a real scalar (a number, a 0-d array or tracer), else a
    `ValueError` naming it (a string or a bool would be read as a number)."""
    if not is_real(t) or jnp.ndim(t) != 0:
        raise ValueError(f"{name} must be a real scalar time, got {t!r}.")


def check_scalar(value, what: str):
    """Static check that a user function returned a scalar."""
    shape = jnp.shape(value)
    if shape != ():
        raise ValueError(f"{what} must return a scalar, got an array of shape {shape}.")
    return value


def check_function(
    fn, name: str, spelled: str, arity: int, keywords: tuple[str, ...] = (), error=ValueError
) -> None:
    """Static check: `fn` is a function taking `arity` positional arguments and the
    `keywords` (where `inspect.signature` reads it), else `error(message)` naming `name`
    and `spelled` (`error`: an exception class or a function of the message)."""
    if not callable(fn):
        raise error(f"{name} must be a function {spelled}, got {type(fn).__name__}.")
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):  # a builtin or C function: nothing to read
        return
    try:
        signature.bind(*range(arity), **dict.fromkeys(keywords))
    except TypeError:
        also = f" and the keywords {', '.join(keywords)}" if keywords else ""
        raise error(
            f"{name} must be a function {spelled} ({arity} arguments{also}), got "
            f"one with signature {signature}."
        ) from None


def off_rotation(R, q_name: str = "q") -> tuple[jax.Array, str]:
    """`(problem, message)`: whether some `R_j` is not a rotation: `R_j^T R_j` differs
    from `I` by more than `unit_tolerance` in some entry, or `det R_j < 0`."""
    tol = unit_tolerance(jnp.result_type(R))
    off = (rotation_error(R) > tol) | jnp.any(jnp.linalg.det(R) < 0)
    return off, (
        f"{q_name} is not a rotation: some R^T R differs from I by more than {tol:g} "
        "(orthonormalize it, e.g. with sphere_mech.nearest_rotation) or has det R < 0 (a "
        "reflection, which no orthonormalization turns into a rotation)."
    )


def off_rotation_tangent(R, V, v_name: str = "v") -> tuple[jax.Array, str]:
    """`(problem, message)`: whether some `R_j^T V_j` is not skew within `unit_tolerance`
    (relative to `1 + max |V|`)."""
    tol = unit_tolerance(jnp.result_type(R))
    M = jnp.swapaxes(R, -1, -2) @ V
    return jnp.max(jnp.abs(M + jnp.swapaxes(M, -1, -2))) > tol * (1.0 + jnp.max(jnp.abs(V))), (
        f"{v_name} is not tangent to the rotations: some R^T {v_name} is not skew within "
        f"{tol:g} (relative); write it as R @ hat(Omega), or project it."
    )
