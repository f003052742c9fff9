"""Arithmetic on pytrees of arrays (states, forces, parameters): the lowest layer."""

import functools
import operator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def is_integer(value) -> bool:
    """Whether `value` is a Python or NumPy integer (a bool is not)."""
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def check_integer(value, name: str, least: int = 1) -> None:
    """`value` an integer (not a bool) >= `least`, else a `ValueError` naming it: "`name`
    must be a positive integer" (`least` 1) or "an integer >= `least`", with the value."""
    if not is_integer(value) or value < least:
        kind = "a positive integer" if least == 1 else f"an integer >= {least}"
        raise ValueError(f"{name} must be {kind}, got {value!r}.")


def check_bool(value, name: str, error=ValueError) -> None:
    """`value` a Python or NumPy bool, else `error(message)` naming it: "`name` must be True
    or False" (a string such as `"no"` is truthy, so it would silently mean `True`)."""
    if not isinstance(value, bool | np.bool_):
        raise error(f"{name} must be True or False, got {value!r}.")


def as_python(value):
    """A NumPy scalar (`np.int64(2)`, `np.True_`) as the Python one, for a static field;
    anything else unchanged, for the field's check to refuse or keep."""
    return value.item() if isinstance(value, np.generic) else value


def check_positive(value, name: str, zero: bool = False) -> None:
    """`value` one finite number > 0, or >= 0 with `zero` (a Python or NumPy number or a
    0-d array, not a bool; a tracer passes), else a `ValueError` naming it: "`name` must be
    a finite number > 0" (">= 0")."""
    if isinstance(value, jax.core.Tracer):
        return
    scalar = np.ndim(value) == 0 and not isinstance(value, bool | str)
    bound = ">=" if zero else ">"
    try:
        x = float(value) if scalar else np.nan
    except (TypeError, ValueError):
        x = np.nan
    if not (x >= 0 if zero else x > 0) or x == np.inf:
        raise ValueError(f"{name} must be a finite number {bound} 0, got {value!r}.")


def float_dtype(dtype, name: str = "dtype"):
    """`dtype` as a floating `numpy.dtype` JAX runs in (`None`: JAX's default float), else a
    `ValueError` naming it ("`name` must be a floating dtype JAX runs in, got ...")."""
    dtype = jnp.zeros(()).dtype if dtype is None else jnp.dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating) or dtype != jax.dtypes.canonicalize_dtype(dtype):
        x64 = " (float64 needs jax_enable_x64)" if dtype == jnp.float64 else ""
        raise ValueError(f"{name} must be a floating dtype JAX runs in{x64}, got {dtype}.")
    return dtype


def as_array(x):
    """A state leaf as a JAX array; nested lists as float arrays (JAX's default float)."""
    return jnp.asarray(x, dtype=float) if isinstance(x, list) else jnp.asarray(x)


def state_arrays(q, v):
    """The state `(q, v)` with every leaf a JAX array; nested lists as float arrays."""
    return jax.tree.map(as_array, (q, v), is_leaf=lambda x: isinstance(x, list))


def tree_add(a, b):
    """`a + b` leaf by leaf."""
    return jax.tree.map(operator.add, a, b)


def tree_sub(a, b):
    """`a - b` leaf by leaf."""
    return jax.tree.map(operator.sub, a, b)


def tree_scale(s, a):
    """`s * a` for a scalar `s`, leaf by leaf."""
    return jax.tree.map(lambda x: s * x, a)


def tree_vdot(a, b):
    """`sum a * b` over every leaf: a force (or momentum) paired with a velocity."""
    pairs = zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True)
    return functools.reduce(operator.add, [jnp.sum(x * y) for x, y in pairs])


def tree_dtype(tree):
    """The floating dtype of a state (every leaf together)."""
    return jnp.result_type(*jax.tree.leaves(tree))


def tree_zeros_like(tree):
    """Zeros of the state's structure."""
    return jax.tree.map(jnp.zeros_like, tree)


def tree_max_abs(tree):
    """`max |x|` over every leaf."""
    return functools.reduce(jnp.maximum, [jnp.max(jnp.abs(x)) for x in jax.tree.leaves(tree)])


def all_finite(tree) -> jax.Array:
    """Whether every leaf of `tree` (Python numbers too) is finite; `True` without leaves."""
    leaves = [jnp.all(jnp.isfinite(jnp.asarray(x))) for x in jax.tree.leaves(tree)]
    return functools.reduce(jnp.logical_and, leaves, jnp.array(True))


def fill_zeros(tangents, primals):
    """Symbolic zero tangents (`None`) of floating array primals as arrays of zeros."""
    fill = lambda t, p: jnp.zeros_like(p) if t is None and eqx.is_inexact_array(p) else t
    return jax.tree.map(fill, tangents, primals, is_leaf=lambda x: x is None)


def rows(mask, x):
    """`mask` (one entry per member) broadcast against `x` (members along axis 0)."""
    return jnp.reshape(mask, mask.shape + (1,) * (jnp.ndim(x) - 1))


def as_arrays(tree):
    """Python and NumPy floats among `tree`'s leaves as JAX arrays (no recompiling for a new
    value); ints and bools stay static (they may describe structure)."""
    is_float = lambda x: (
        isinstance(x, float | complex | np.floating)
        or (isinstance(x, np.ndarray) and np.issubdtype(x.dtype, np.inexact))
    )
    return jax.tree.map(lambda x: jnp.asarray(x) if is_float(x) else x, tree)
