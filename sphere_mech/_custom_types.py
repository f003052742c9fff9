"""Array type aliases shared across the package."""

from collections.abc import Callable
from typing import Any

import jax
from jaxtyping import Array, Float

Points = Float[Array, "n 3"]
"""`n` unit vectors, one point on each of n two-spheres."""
Tangents = Float[Array, "n 3"]
"""Tangent vectors at `Points` (velocities, angular velocities or momenta)."""
Scalar = Float[Array, ""]
State = tuple[Points, Tangents]
"""`(q, v)`: a configuration and the system's second state variable."""
Args = Any
"""Whatever PyTree the user threads through to `L`, `H` and `forces`."""
ForceFn = Callable[[Scalar, Points, Tangents, Args], Tangents]
"""`forces(t, q, v, args) -> (n, 3)`, with virtual work `sum_i f_i . delta q_i`."""
Key = jax.Array
