"""The default adjoint of `simulate` and `simulate_batch` (`adjoint=None`): forward or
reverse mode chosen per derivative from the number of differentiated scalars, as
diffrax keeps its adjoints beside its solve."""

import contextlib

import diffrax
import equinox as eqx
import jax
from jax.flatten_util import ravel_pytree

from ._misc import fill_zeros

FORWARD_COLUMNS = 8
"""The default adjoint differentiates one trajectory (`simulate`) in forward mode when at
most this many scalars are differentiated (e.g. the lengths of a chain of up to 8 links),
else in reverse mode. On a 2-core CPU, forward mode measured 1.9x (float64) to 2.7x
(float32) faster than reverse mode at 8 columns (`benchmarks/gradients.py`) and about
even at 16 (1.4x faster in float64, 1.3x slower in float32): one trajectory's arrays
are small, its cost is per operation, and forward mode widens the operations instead
of adding more."""
BATCH_FORWARD_COLUMNS = 2
"""The same threshold for a trajectory of `simulate_batch`: under `vmap` the arrays are
wide already, forward mode's cost grows with every column and reverse mode's does not
(at 8 columns reverse mode measured 3.5x faster; at 2 forward mode 1.1x to 1.6x
faster)."""


@contextlib.contextmanager
def forward_mode_hint():
    """Around a run: JAX's refusal of forward mode through the default adjoint (a
    `jax.custom_vjp`, as is `diffrax.RecursiveCheckpointAdjoint`) becomes an error that
    says what to pass instead."""
    try:
        yield
    except TypeError as error:
        if "custom_vjp" not in str(error):
            raise
        raise TypeError(
            "forward-mode differentiation (jax.jvp, jax.jacfwd) of a run needs "
            "adjoint=diffrax.ForwardMode(); the default adjoint is reverse mode"
        ) from error


@eqx.filter_custom_vjp
def default_adjoint_run(inputs, *, opts, solve_with) -> diffrax.Solution:
    r"""`solve_with` differentiated in reverse mode by the default adjoint
    (`adjoint=None`), chosen at trace time by `default_adjoint` from the number $P$ of
    differentiated scalars (the parameters, states and times being differentiated) and
    whether the run is one trajectory of `simulate_batch`:

    - $P \le$ `FORWARD_COLUMNS` (8; `BATCH_FORWARD_COLUMNS`, 2, in a batch): the
      Jacobian of the run's outputs with respect to those $P$ scalars is computed
      during the run in forward mode
      (`diffrax.ForwardMode`, $P$ tangents carried along the steps) and the backward
      pass multiplies the cotangent by it. Memory: $P + 1$ copies of the solver's state
      during the run, and the $P \times$ (saved outputs) Jacobian kept for the backward
      pass, independent of the number of steps and of `max_steps`.
    - more: `diffrax.RecursiveCheckpointAdjoint()`, reverse mode with online
      checkpointing. Memory: $\lfloor\sqrt{2 \cdot \text{max\_steps}}\rfloor$
      checkpoints (447 for the default `max_steps = 100_000`), each a copy of the
      solver's loop state (the state $(q, v)$, times, the stages a solver keeps between
      steps), independent of how many steps the run takes.

    Like `RecursiveCheckpointAdjoint`, it does not support forward mode (`jax.jvp`,
    `jax.jacfwd`): pass `adjoint=diffrax.ForwardMode()` for that.

    `solve_with(adjoint, *inputs, opts)` runs the solve; `opts.batched` says whether it
    is one trajectory of `simulate_batch`."""
    return solve_with(diffrax.RecursiveCheckpointAdjoint(), *inputs, opts)


def _split(perturbed, inputs, opts):
    """The differentiated leaves of `inputs`, the rest, and the adjoint for them."""
    x, rest = eqx.partition(inputs, perturbed)
    columns = sum(leaf.size for leaf in jax.tree.leaves(x))
    return x, rest, default_adjoint(columns, opts.batched)


@default_adjoint_run.def_fwd
def _fwd(perturbed, inputs, *, opts, solve_with):
    x, rest, adjoint = _split(perturbed, inputs, opts)

    def outputs(x):
        sol = solve_with(adjoint, *eqx.combine(x, rest), opts)
        return eqx.filter(sol, eqx.is_inexact_array), sol

    if not isinstance(adjoint, diffrax.ForwardMode):
        out, pullback, sol = jax.vjp(outputs, x, has_aux=True)
        return sol, (pullback, out)
    x_flat, unravel = ravel_pytree(x)

    def flat_outputs(x_flat):
        out, sol = outputs(unravel(x_flat))
        return ravel_pytree(out)[0], (out, sol)

    jacobian, (out, sol) = jax.jacfwd(flat_outputs, has_aux=True)(x_flat)
    return sol, (jacobian, out)


@default_adjoint_run.def_bwd
def _bwd(residuals, grad_sol, perturbed, inputs, *, opts, solve_with):
    x, _, adjoint = _split(perturbed, inputs, opts)
    pullback_or_jacobian, out = residuals
    cotangent = fill_zeros(eqx.filter(grad_sol, eqx.is_inexact_array), out)
    if not isinstance(adjoint, diffrax.ForwardMode):
        return pullback_or_jacobian(cotangent)[0]
    jacobian, unravel = pullback_or_jacobian, ravel_pytree(x)[1]
    return unravel(jacobian.T @ ravel_pytree(cotangent)[0].astype(jacobian.dtype))


def default_adjoint(columns: int, batched: bool = False) -> diffrax.AbstractAdjoint:
    """The adjoint that `adjoint=None` differentiates a run with when `columns` scalars
    are differentiated: `diffrax.ForwardMode()` for at most `FORWARD_COLUMNS` (one
    trajectory) or `BATCH_FORWARD_COLUMNS` (`batched`: one of `simulate_batch`), else
    `diffrax.RecursiveCheckpointAdjoint()` (see `default_adjoint_run`)."""
    if columns <= (BATCH_FORWARD_COLUMNS if batched else FORWARD_COLUMNS):
        return diffrax.ForwardMode()
    return diffrax.RecursiveCheckpointAdjoint()
