"""`simulate_batch`: many trajectories at once, vmapped, chunked and sharded over devices."""

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, PartitionSpec

from ._adjoint import forward_mode_hint
from ._misc import rows
from ._results import RESULTS, raise_on_failure
from ._simulate import simulate
from ._solve import prepare, shared_signature, solve
from ._system import AbstractSystem

BATCH_AXIS = "batch"
CPU_CHUNK_LINKS = 512
"""On CPU, trajectories are integrated in chunks of about `CPU_CHUNK_LINKS / n` (a power
of two): a chunk's working set then stays in cache, which measured 2-3x faster than one
vmap over thousands of trajectories. Other backends integrate the whole local batch."""


def _leading(tree, size, what):
    """Static check that every array leaf of `tree` has leading axis `size`."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree, is_leaf=eqx.is_array):
        if eqx.is_array(leaf) and (leaf.ndim == 0 or leaf.shape[0] != size):
            raise ValueError(
                f"{what}{jax.tree_util.keystr(path)} must have a leading batch axis of size "
                f"{size} (the batch size of y0), got shape {leaf.shape}."
            )


def _pad(tree, size):
    """Pad every leaf to `size` along axis 0 with copies of entry 0 (a valid trajectory,
    so padding never fails); the padding is stripped after the solve."""

    def pad(x):
        if x.shape[0] == size:
            return x
        return jnp.concatenate([x, jnp.broadcast_to(x[:1], (size - x.shape[0],) + x.shape[1:])])

    return jax.tree.map(pad, tree)


def _local_solve(static, chunk, shared, batched, y0):
    """The trajectories held by one device: `lax.map` over chunks of `vmap`."""

    def block(inputs):
        system, args, t0, t1, dt0, opts = eqx.combine(inputs[0], shared, static)
        return solve(system, inputs[1], t0, t1, dt0, args, opts)

    if chunk >= jax.tree.leaves(y0)[0].shape[0]:
        return jax.vmap(block)((batched, y0))
    return jax.lax.map(block, (batched, y0), batch_size=chunk)


@eqx.filter_jit
def _solve_batch(static, chunk, mesh, shared, batched, y0, valid, size, padded):
    batched, y0 = _pad((batched, y0), padded)
    solve = lambda s, b, y: _local_solve(static, chunk, s, b, y)
    if mesh is not None:
        spec = PartitionSpec(BATCH_AXIS)
        solve = jax.shard_map(
            solve,
            mesh=mesh,
            in_specs=(PartitionSpec(), spec, spec),
            out_specs=spec,
            check_vma=False,
        )
    sol = jax.tree.map(lambda x: x[:size], solve(shared, batched, y0))
    # Invalid initial states ran a stand-in (`initial_states`): their own code, nothing
    # saved (`inf`, as for a run that fails at its initial state) and no steps.
    result = jax.vmap(lambda ok, r: RESULTS.where(ok, r, RESULTS.invalid_initial))(
        valid, sol.result
    )
    discard = lambda fill: lambda x: jnp.where(rows(valid, x), x, fill)
    ts, ys = jax.tree.map(discard(jnp.inf), (sol.ts, sol.ys))
    stats = jax.tree.map(discard(0), sol.stats)
    return eqx.tree_at(
        lambda s: (s.result, s.ts, s.ys, s.stats),
        sol,
        (result, ts, ys, stats),
        is_leaf=lambda x: x is None,
    )


def _chunk_size(chunk_size, n, local, platform):
    if chunk_size is None:
        if platform != "cpu":
            return local
        chunk_size = 2 ** int(math.log2(max(1, CPU_CHUNK_LINKS // n)))
    if chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive integer, got {chunk_size}.")
    return min(chunk_size, local)


def simulate_batch(
    system: AbstractSystem,
    y0,
    t1,
    *,
    args=None,
    batch_args: bool = True,
    batch_system: bool = False,
    chunk_size: int | None = None,
    devices=None,
    **options,
) -> diffrax.Solution:
    """Integrate a batch of trajectories: `simulate` over a leading batch axis.

    **Arguments:**
    - `system`, `t1`, `t0`, `solver`, `dt0`, `rtol`, `atol`, `stepsize_controller`,
      `saveat`, `max_steps`, `adjoint`, `event`: as in `sphere_mech.simulate` (the same
      keyword options, one list of them), shared by every trajectory (`system` too
      unless `batch_system=True`). The
      default adjoint (`None`) uses forward mode for at most 2 differentiated scalars
      here (8 in `simulate`): under `vmap` forward mode's cost grows with every column
      and reverse mode's does not.
    - `y0`: `(q0, v0)`, arrays of shape `(batch, n, 3)` (on a mixed space, dicts of
      arrays, each with the leading batch axis).
    - `args`: passed to the system; its array leaves have a leading batch axis (one value
      per trajectory: masses, gains, ...) unless `batch_args=False`.
    - `batch_args`: `False` shares `args` between all trajectories (no batch axis).
    - `batch_system`: if True, every array leaf of `system` has a leading batch axis, e.g.
      `eqx.filter_vmap(sm.chain_pendulum)(masses, lengths)` for a batch of chains.
    - `throw`: as in `simulate`: `True` (default) raises after the solve if any
      trajectory failed, naming how many, which, and the first one's cause (the same
      message as `simulate`); `False` never raises for a run-time failure: `sol.result`
      holds each trajectory's own `sm.RESULTS` code (NaN parameters give
      `RESULTS.nonfinite_initial`, an invalid initial state `RESULTS.invalid_initial`)
      and a failed trajectory does not affect the others (but see docs/batched.md for
      differences of 1e-14 to 1e-11 through `Projected`'s first stages). Initial states
      are checked one by one: with `throw=True` an invalid one (NaN, off the spheres,
      not tangent) raises a `ValueError` before the solve, naming which.
      (With an adaptive controller a trajectory whose vector field is NaN keeps
      rejecting steps until `max_steps`, which the batch waits for; fixed-step solvers
      stop it at its first step.)
    - `chunk_size`: trajectories integrated together by one `vmap` on a device (default:
      about `512 / n` on CPU, which keeps the working set in cache; the whole batch on
      other backends). Results do not depend on it.
    - `devices`: devices to shard the batch over (default: all of JAX's default backend).
      With more than one, the batch is split along a 1-D `Mesh` with `shard_map`; batch
      sizes that do not divide the device count are padded and the padding stripped; a
      batch smaller than the device count uses only as many devices as trajectories.
    - `progress`: diffrax's progress bar over the batch's time.

    Compiles once per structure (shapes, dtypes, solver and options): new values of
    `y0`, `args` or the system's parameters reuse the compiled program.

    **Returns:** a `diffrax.Solution` whose every array has a leading batch axis:
    `sol.ys = (q, v)` of shape `(batch, times, n, 3)`, `sol.result` and
    `sol.stats["num_steps"]` per trajectory. The output is sharded over the devices.
    """
    run = prepare(system, y0, args, batched=True, batch_system=batch_system, t1=t1, **options)
    one_state = jax.tree.map(lambda x: x[0], run.y0)
    size = len(run.valid)
    if batch_args and args is not None:
        _leading(args, size, "args")
    if batch_system:
        _leading(eqx.filter(system, eqx.is_array), size, "system")
    dynamic, static = eqx.partition(
        (run.system, run.args, run.t0, run.t1, run.dt0, run.opts), eqx.is_array
    )
    mask = jax.tree.map(lambda _: False, dynamic)
    mask = (batch_system, batch_args) + mask[2:]  # prefixes: all of system / args or none
    batched, shared = eqx.partition(dynamic, mask)
    # A batch smaller than the device count uses as many devices as trajectories: the
    # others would only integrate padding.
    devices = (jax.devices() if devices is None else list(devices))[:size]
    mesh = Mesh(np.array(devices), (BATCH_AXIS,)) if len(devices) > 1 else None
    per_device = -(-size // len(devices))
    chunk = _chunk_size(
        chunk_size, system.space.rows(one_state[0]), per_device, devices[0].platform
    )
    padded = -(-size // (chunk * len(devices))) * chunk * len(devices)
    with forward_mode_hint():
        sol = _solve_batch(static, chunk, mesh, shared, batched, run.y0, run.valid, size, padded)
    return raise_on_failure(sol, run.opts.max_steps, "simulate_batch") if run.throw else sol


simulate_batch.__signature__ = shared_signature(simulate_batch, simulate)
