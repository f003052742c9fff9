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
def forward_mode_hint(adjoint: diffrax.AbstractAdjoint | None):
    """JAX's refusal of forward mode through a reverse-mode `adjoint` (the default, `None`,
    or e.g. `diffrax.RecursiveCheckpointAdjoint()`: a `jax.custom_vjp`) becomes an error
    that names that adjoint and says what to pass instead."""
    try:
        yield
    except TypeError as error:
        if "custom_vjp" not in str(error):
            raise
        which = "the default adjoint" if adjoint is None else f"adjoint={adjoint!r}"
        raise TypeError(
            "forward-mode differentiation (jax.jvp, jax.jacfwd) of a run needs "
            f"adjoint=diffrax.ForwardMode(); {which} is reverse mode"
        ) from error


def default_adjoint_run(solve_with, inputs) -> diffrax.Solution:
    r"""`solve_with(adjoint, *inputs)` differentiated in reverse mode, the adjoint chosen at
    trace time by `default_adjoint` from the number $P$ of differentiated scalars: for
    $P \le$ `FORWARD_COLUMNS` (`BATCH_FORWARD_COLUMNS` if the options say `batched`) the
    Jacobian in them, computed in forward mode during the run (memory: $P + 1$ solver states
    and the $P \times$ outputs Jacobian), times the cotangent; else
    `diffrax.RecursiveCheckpointAdjoint()` (memory: $\lfloor\sqrt{2 \cdot
    \text{max\_steps}}\rfloor$ loop-state checkpoints, 447 by default), through which an
    `RK4` step is differentiated one stage at a time (`stagewise_reverse`). Neither depends on
    the number of steps. A sharded batch (`opts.sharded`) always takes forward mode. No
    forward mode (`jax.jvp`): pass `adjoint=diffrax.ForwardMode()`.

    The run is closure-converted first: arrays that the system's functions, an event or the
    options close over (a parameter captured by `L`) are explicit inputs, differentiated
    like `args`; the last element of `inputs` is the `Options`, whose arrays (save times)
    are differentiated too."""
    run = eqx.filter_closure_convert(
        lambda inputs: solve_with(diffrax.RecursiveCheckpointAdjoint(), *inputs), inputs
    )
    return _run((run, inputs), solve_with=solve_with, closed_over=_ClosedOver(run.consts))


@dataclasses.dataclass(frozen=True, eq=False)
class _ClosedOver:
    """The values a run closes over, as its first conversion found them: kept alive, and
    no PyTree (a keyword of `_run`, which is not differentiated)."""

    values: list

    def positions(self, values) -> list:
        """For each of `values`, its position among these if it is a tracer among them."""
        where = {id(v): i for i, v in enumerate(self.values) if isinstance(v, jax.core.Tracer)}
        return [where.get(id(v)) if isinstance(v, jax.core.Tracer) else None for v in values]


@eqx.filter_custom_vjp
def _run(run_and_inputs, *, solve_with, closed_over) -> diffrax.Solution:
    run, inputs = run_and_inputs
    return run(inputs)


def _choice(perturbed, run_and_inputs):
    """The differentiated leaves, the rest, and the adjoint for them."""
    x, rest = eqx.partition(run_and_inputs, perturbed)
    columns = sum(leaf.size for leaf in jax.tree.leaves(x))
    opts = run_and_inputs[1][-1]
    return x, rest, default_adjoint(columns, opts.batched, opts.sharded)


@_run.def_fwd
def _fwd(perturbed, run_and_inputs, *, solve_with, closed_over):
    x, rest, adjoint = _choice(perturbed, run_and_inputs)
    stagewise = not isinstance(adjoint, diffrax.ForwardMode)

    def solve(inputs):
        *inputs, opts = inputs
        if stagewise:
            opts = dataclasses.replace(opts, solver=stagewise_reverse(opts.solver))
        return solve_with(adjoint, *inputs, opts)

    # The run again with this adjoint, the values it closes over that the first conversion
    # found (the same objects) replaced by those passed in, which carry the derivatives.
    again = eqx.filter_closure_convert(solve, run_and_inputs[1])
    positions = closed_over.positions(again.consts)

    def outputs(x):
        run, inputs = eqx.combine(x, rest)
        consts = [
            c if i is None else run.consts[i] for c, i in zip(again.consts, positions, strict=True)
        ]
        sol = eqx.tree_at(lambda a: a.consts, again, consts)(inputs)
        return eqx.filter(sol, eqx.is_inexact_array), sol

    if stagewise:
        out, pullback, sol = jax.vjp(outputs, x, has_aux=True)
        return sol, (pullback, out)
    x_flat, unravel = ravel_pytree(x)

    def flat_outputs(x_flat):
        out, sol = outputs(unravel(x_flat))
        return ravel_pytree(out)[0], (out, sol)

    jacobian, (out, sol) = jax.jacfwd(flat_outputs, has_aux=True)(x_flat)
    return sol, (jacobian, out)


@_run.def_bwd
def _bwd(residuals, grad_sol, perturbed, run_and_inputs, *, solve_with, closed_over):
    x, _, adjoint = _choice(perturbed, run_and_inputs)
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
