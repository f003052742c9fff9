"""`RESULTS`, diffrax's result codes extended with sphere_mech's, and the one way every
entry point turns a failed run into an error."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils


class RESULTS(diffrax.RESULTS):  # pyright: ignore[reportGeneralTypeIssues]
    """diffrax's (and optimistix's) result codes plus sphere_mech's. Compare codes
    (`sol.result == sm.RESULTS.nonfinite`); `sm.RESULTS[code]` is the message."""

    nonfinite_initial = (
        "The equations of motion are not finite at the initial state: a singular reduced "
        "mass matrix (degenerate Lagrangian, e.g. a zero mass or length), a Legendre "
        "transform that is not invertible there (sm.legendre), a potential or force that "
        "is NaN or infinite there, or NaN parameters."
    )
    event_root_failed = (
        "The root finder of `event` did not converge while locating the event (on the "
        "dense output of the step where its condition changed sign): give "
        "diffrax.Event(root_finder=...) looser tolerances, or make the condition function "
        "smooth near its zero (a sign or a cube root defeats Newton's method); without a "
        "root finder the run stops at the end of that step."
    )
    invalid_initial = (
        "The initial state is invalid: q0 or v0 contains NaN or infinite values, q0 is "
        "off its space (a unit vector off its sphere, a matrix that is not a rotation) or "
        "v0 not tangent to it (beyond sm.unit_tolerance). With "
        "throw=True simulate_batch raises a ValueError naming the states and the problem."
    )


_NAMES = (  # lineax's, optimistix's, diffrax's and ours:
    "successful max_steps_reached singular breakdown stagnation conlim nonfinite_input "
    "nonlinear_max_steps_reached nonlinear_divergence "
    "nonfinite dt_min_reached event_occurred max_steps_rejected internal_error "
    "nonfinite_initial event_root_failed invalid_initial"
).split()
ITEMS = tuple(getattr(RESULTS, name) for name in _NAMES)
"""Every item of `RESULTS`, numbered by place (`code`); a code that a new diffrax,
optimistix or lineax adds fails the check below at import (add its name)."""
if len(ITEMS) != len(RESULTS):
    raise ImportError(f"sphere_mech.RESULTS has {len(RESULTS)} codes, _results.ITEMS {len(ITEMS)}")

_NEWTON = (
    " The Newton iterations of an implicit step did not converge (or met a singular "
    "Jacobian): use a smaller dt0, an adaptive step-size controller (it retries a failed "
    "step with a smaller one), or a root finder with more iterations."
)
_HINTS = {
    "max_steps_reached": " If most steps were rejected (sol.stats with throw=False) "
    "the step size collapsed, which happens when the vector field is NaN or singular near "
    "the state reached; otherwise loosen rtol/atol.",
    "nonfinite": " The state became NaN (the step diverged or the vector field is "
    "not defined there: a singular mass matrix, NaN parameters or forces): use a smaller "
    "dt0 or an adaptive step-size controller.",
    "nonlinear_max_steps_reached": _NEWTON,
    "nonlinear_divergence": _NEWTON,
    "singular": _NEWTON,
}


def code(result) -> jax.Array:
    """The number (index in `ITEMS`, `int32`, batch axes kept) of a result code, by the
    items' public `==`: concrete for a concrete code, inside `jit` too."""
    with jax.ensure_compile_time_eval():
        matches = [result == item for item in ITEMS]
    if any(isinstance(m, jax.core.Tracer) for m in matches):
        return jnp.argmax(jnp.stack(matches, axis=-1), axis=-1).astype(jnp.int32)
    return np.argmax(np.stack([gathered(m) for m in matches], axis=-1), axis=-1).astype(np.int32)


def gathered(x) -> np.ndarray:
    """A concrete array as NumPy, whole: an array that spans the devices of several processes
    (`jax.distributed`) is gathered from all of them, a collective that every process calls
    (each process then holds the same values, so all take the same branch and raise the same
    message with global indices)."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


def _number(item) -> int:
    """The number (`code`) of an item of `ITEMS`, without comparing."""
    return next(i for i, x in enumerate(ITEMS) if x is item)


_OK = (_number(RESULTS.successful), _number(RESULTS.event_occurred))


def failed(values) -> jax.Array:
    """Which code values are failures: neither success nor a terminating event."""
    return (values != _OK[0]) & (values != _OK[1])


def _messages(max_steps) -> list[str]:
    """The error message of every code, indexed by its value."""
    limit = lambda name: f"max_steps={max_steps}; " if name == "max_steps_reached" else ""
    return [
        f"{RESULTS[item]}{_HINTS.get(name, '')} ({limit(name)}with throw=False "
        "nothing is raised and sol.result holds the code)"
        for name, item in zip(_NAMES, ITEMS, strict=True)
    ]


def raise_on_failure(sol: diffrax.Solution, max_steps, what: str) -> diffrax.Solution:
    """Raise if any trajectory of `sol` failed (an event is no failure): a `RuntimeError`
    naming how many, which and why, or when traced an `eqx.branched_error_if` saying so."""
    ok = (sol.result == RESULTS.successful) | (sol.result == RESULTS.event_occurred)
    if not isinstance(ok, jax.core.Tracer) and bool(np.all(gathered(ok))):
        return sol  # the usual case, decided without numbering the codes (`code`)
    values = jnp.ravel(code(sol.result))
    if isinstance(values, jax.core.Tracer):
        first = values[jnp.argmax(failed(values))]
        prefixed = [f"{what}: {m}" for m in _messages(max_steps)]
        ys = eqx.branched_error_if(sol.ys, jnp.any(failed(values)), first, prefixed)
        return eqx.tree_at(lambda s: s.ys, sol, ys, is_leaf=lambda x: x is None)
    raise_on_codes(np.asarray(values), max_steps, what)
    return sol


def raise_on_codes(values: np.ndarray, max_steps, what: str) -> None:
    """Raise a `RuntimeError` naming how many of the flat code values failed, which and why."""
    bad = np.flatnonzero(failed(values))
    if bad.size == 0:
        return
    where = describe_failures(bad, values.size, "trajectories failed", "trajectory")
    raise RuntimeError(f"{what}:{where} {_messages(max_steps)[values[bad[0]]]}")


def describe_failures(bad: np.ndarray, size: int, failed: str, one: str) -> str:
    """`" 2 of 8 <failed> (indices 3, 5); <one> 3:"` for the failed members `bad` of a
    batch of `size` (`""` for one)."""
    if size == 1:
        return ""
    shown = ", ".join(map(str, bad[:10])) + (", ..." if bad.size > 10 else "")
    return f" {bad.size} of {size} {failed} (indices {shown}); {one} {bad[0]}:"
