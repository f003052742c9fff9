"""The default adjoint: forward or reverse mode chosen by the number of differentiated scalars."""

import contextlib
import dataclasses

import diffrax
import equinox as eqx
import jax
from jax.flatten_util import ravel_pytree

from ._misc import fill_zeros
from ._solvers.rk4 import RK4

FORWARD_COLUMNS = 8
"""Forward mode for one trajectory (`simulate`) with at most this many differentiated
scalars, else reverse mode. On a 2-core CPU forward mode measured 1.9x (float64) to 2.7x
(float32) faster at 8 columns and about even at 16 (`benchmarks/gradients.py`): small
arrays cost per operation, and forward mode widens the operations instead of adding more."""
BATCH_FORWARD_COLUMNS = 2
"""The same for a trajectory of `simulate_batch`: under `vmap` forward mode's cost grows with
every column. Against the stage-by-stage reverse mode (chains, `Projected(RK4())`, 300 steps,
B = 256 and 1024, 2-core CPU, 2026-12-02; `benchmarks/gradients.py --rk4-batch` at 2): at 1
column forward mode took 2.0x to 2.2x the forward pass against 4.4x to 4.9x; at 2 columns
the two were within 19% of each other (reverse mode lower in 11 of 12 pairs); at 8, reverse
mode 3.5x faster. At 2 forward mode is kept for its memory: it holds no checkpoints (the
value_and_grad at n = 2, float64, needed 2.0 MB of working memory at B = 4096 in forward
mode against 193 MB in reverse mode, about 47 kB a trajectory).
A batch sharded over several devices or processes (`Options.sharded`) always uses forward
mode: reverse mode's checkpointed loop fails inside `shard_map` (equinox compares the
types of its loop state, which inside `shard_map` carry the manual mesh only once traced:
"Closure-converted function called with different dynamic arguments"; diffrax #765,
equinox PR #1261). Forward mode gives the same gradient (to rounding) at a cost that grows
with the number of differentiated scalars per trajectory."""


@contextlib.contextmanager
def forward_mode_hint():
    """JAX's refusal of forward mode through the default adjoint (a `jax.custom_vjp`)
    becomes an error that says what to pass instead."""
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
    r"""`solve_with(adjoint, *inputs, opts)` in reverse mode, the adjoint chosen at trace time
    by `default_adjoint` from the number $P$ of differentiated scalars: for
    $P \le$ `FORWARD_COLUMNS` (`BATCH_FORWARD_COLUMNS` if `opts.batched`) the Jacobian in
    them, computed in forward mode during the run (memory: $P + 1$ solver states and the
    $P \times$ outputs Jacobian), times the cotangent; else
    `diffrax.RecursiveCheckpointAdjoint()` (memory: $\lfloor\sqrt{2 \cdot
    \text{max\_steps}}\rfloor$ loop-state checkpoints, 447 by default), through which an
    `RK4` step is differentiated one stage at a time (`stagewise_reverse`). Neither depends on
    the number of steps. A sharded batch (`opts.sharded`) always takes forward mode. No
    forward mode (`jax.jvp`): pass `adjoint=diffrax.ForwardMode()`."""
    return solve_with(diffrax.RecursiveCheckpointAdjoint(), *inputs, opts)


def _split(perturbed, inputs, opts):
    """The differentiated leaves of `inputs`, the rest, and the adjoint for them."""
    x, rest = eqx.partition(inputs, perturbed)
    columns = sum(leaf.size for leaf in jax.tree.leaves(x))
    return x, rest, default_adjoint(columns, opts.batched, opts.sharded)


@default_adjoint_run.def_fwd
def _fwd(perturbed, inputs, *, opts, solve_with):
    x, rest, adjoint = _split(perturbed, inputs, opts)
    if not isinstance(adjoint, diffrax.ForwardMode):
        opts = dataclasses.replace(opts, solver=stagewise_reverse(opts.solver))

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


def stagewise_reverse(solver: diffrax.AbstractSolver) -> diffrax.AbstractSolver:
    """`solver` with each `RK4` in it (e.g. in `Projected`) differentiated one stage at a
    time in reverse mode (`RK4(stagewise_reverse=True)`): the same steps and gradient, a
    step's backward pass about twice as fast on CPU (`benchmarks/gradients.py`)."""
    is_rk4 = lambda x: type(x) is RK4  # not isinstance: it sees through `Projected(RK4())`
    stagewise = lambda x: RK4(stagewise_reverse=True) if is_rk4(x) else x
    return jax.tree.map(stagewise, solver, is_leaf=is_rk4)


def default_adjoint(
    columns: int, batched: bool = False, sharded: bool = False
) -> diffrax.AbstractAdjoint:
    """`diffrax.ForwardMode()` for at most `FORWARD_COLUMNS` (`BATCH_FORWARD_COLUMNS` if
    `batched`) differentiated scalars or if `sharded` (over several devices), else
    `diffrax.RecursiveCheckpointAdjoint()`."""
    if sharded or columns <= (BATCH_FORWARD_COLUMNS if batched else FORWARD_COLUMNS):
        return diffrax.ForwardMode()
    return diffrax.RecursiveCheckpointAdjoint()
