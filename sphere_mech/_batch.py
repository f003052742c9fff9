"""`simulate_batch`: many trajectories at once, vmapped, chunked and sharded over devices."""

import contextlib
import dataclasses
import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._adjoint import forward_mode_hint
from ._misc import check_integer, rows
from ._results import RESULTS, raise_on_failure
from ._simulate import simulate
from ._solve import prepare, shared_signature, solve
from ._system import AbstractSystem

BATCH_AXIS = "batch"
CPU_CHUNK_LINKS = 512
"""On CPU, chunks of about `CPU_CHUNK_LINKS / n` trajectories (a power of two) stay in cache:
2-3x faster than one vmap over thousands. Other backends integrate the whole local batch."""


def _pad(tree, size):
    """Pad every leaf to `size` along axis 0 with copies of entry 0 (a valid trajectory)."""
    pad = lambda x: jnp.concatenate([x, jnp.repeat(x[:1], size - x.shape[0], axis=0)])
    return jax.tree.map(pad, tree)


def batch_devices(devices, size: int) -> list:
    """`devices` (default: all of JAX's default backend, of every process), at most `size`;
    an empty sequence raises."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("devices must be a non-empty sequence of JAX devices, or None (all).")
    return devices[:size]


def one_device(devices: list):
    """A context in which JAX's default device is `devices[0]` when it is the only device and
    one of this process's (so a run on one device runs there; arrays the caller committed
    to another device keep it)."""
    if len(devices) > 1 or devices[0].process_index != jax.process_index():
        return contextlib.nullcontext()
    return jax.default_device(devices[0])


def batch_mesh(devices: list) -> Mesh | None:
    """The 1-D mesh of the batch axis over `devices`, or `None` for a single device."""
    return Mesh(np.array(devices), (BATCH_AXIS,)) if len(devices) > 1 else None


def on_devices(fn, mesh: Mesh | None, shared, *batched):
    """`fn(shared, *batched)`, with `batched` split along axis 0 over `mesh` (its length a
    multiple of the device count) and `shared` replicated: each device applies `fn` to its
    slice (`jax.shard_map`); with no mesh, one call on the whole batch."""
    if mesh is None:
        return fn(shared, *batched)
    spec = PartitionSpec(BATCH_AXIS)
    specs = dict(in_specs=(PartitionSpec(),) + (spec,) * len(batched), out_specs=spec)
    return jax.shard_map(fn, mesh=mesh, check_vma=False, **specs)(shared, *batched)


def map_on_devices(fn, mesh: Mesh | None, *batched):
    """`jax.vmap(fn)(*batched)`, split over `mesh`: padded to a multiple of its device count
    with copies of entry 0, the padding stripped."""
    if mesh is None:
        return jax.vmap(fn)(*batched)
    size = jax.tree.leaves(batched)[0].shape[0]
    padded = -(-size // mesh.size) * mesh.size
    out = on_devices(lambda _, *b: jax.vmap(fn)(*b), mesh, None, *_pad(batched, padded))
    return jax.tree.map(lambda x: x[:size], out)


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
    sol = jax.tree.map(lambda x: x[:size], on_devices(solve, mesh, shared, batched, y0))
    # invalid initial states ran a stand-in: their own code, no steps, nothing saved (inf),
    # no event, a dense output of no step (`inf` at t0, NaN elsewhere)
    invalid = lambda ok, r: RESULTS.where(ok, r, RESULTS.invalid_initial)
    result = jax.vmap(invalid)(valid, sol.result)
    discard = lambda fill: lambda x: jnp.where(rows(valid, x), x, fill)
    ts, ys = jax.tree.map(discard(jnp.inf), (sol.ts, sol.ys))
    stats = jax.tree.map(discard(0), sol.stats)
    event_mask = jax.tree.map(discard(False), sol.event_mask)
    interpolation = sol.interpolation
    if interpolation is not None:
        no_step = (interpolation.ts_size, interpolation.infos, interpolation.y0_if_trivial)
        no_step = (discard(1)(no_step[0]),) + jax.tree.map(discard(jnp.inf), no_step[1:])
        interpolation = eqx.tree_at(
            lambda i: (i.ts_size, i.infos, i.y0_if_trivial), interpolation, no_step
        )
    fields = lambda s: (s.result, s.ts, s.ys, s.stats, s.event_mask, s.interpolation)
    new = (result, ts, ys, stats, event_mask, interpolation)
    return eqx.tree_at(fields, sol, new, is_leaf=lambda x: x is None)


def _on_mesh(tree, mesh):
    """Arrays that span several processes (each passed its slice) split along `mesh`."""
    sharding = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))
    spans = lambda x: (
        isinstance(x, jax.Array)
        and not isinstance(x, jax.core.Tracer)
        and not x.is_fully_addressable
    )
    return jax.tree.map(lambda x: jax.device_put(x, sharding) if spans(x) else x, tree)


def _chunk_size(chunk_size, n, local, platform):
    """Trajectories per `vmap` on a device holding `local`: at most `chunk_size`, the chunks
    of one device as even as can be (257 in chunks of at most 256: two of 129, not 512)."""
    if chunk_size is None:
        if platform != "cpu":
            return local
        chunk_size = 2 ** int(math.log2(max(1, CPU_CHUNK_LINKS // n)))
    check_integer(chunk_size, "chunk_size")
    chunk_size = int(chunk_size)  # a NumPy integer too: static (the chunks' shapes)
    return -(-local // -(-local // chunk_size))


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
    """Integrate a batch of trajectories: `simulate` over a leading batch axis, compiled
    once per structure (new values of `y0`, `args` or parameters do not recompile).

    **Arguments:**
    - `system`, `t1`, `t0`, `solver`, `dt0`, `rtol`, `atol`, `stepsize_controller`,
      `saveat`, `max_steps`, `adjoint`, `event`, `progress`: as in `sphere_mech.simulate`,
      shared by every trajectory (`system` too unless `batch_system=True`). The default
      adjoint uses forward mode for at most 2 differentiated scalars here (8 in
      `simulate`): under `vmap` forward mode's cost grows with every column.
    - `y0`: `(q0, v0)`, arrays of shape `(batch, n, 3)` (dicts of them on a mixed space).
    - `args`: passed to the system; its array leaves have a leading batch axis (one value
      per trajectory) unless `batch_args=False`.
    - `batch_args`: `False` shares `args` between all trajectories (no batch axis).
    - `batch_system`: if True, every array leaf of `system` has a leading batch axis, e.g.
      `eqx.filter_vmap(sm.chain_pendulum)(masses, lengths)` for a batch of chains.
    - `throw`: `True` (default) raises for an invalid initial state (NaN, off the spheres,
      not tangent) before the solve and for failed trajectories after it, naming how many,
      which and the first one's cause. `False` never raises for a run-time failure:
      `sol.result` holds each trajectory's `sm.RESULTS` code (NaN parameters:
      `nonfinite_initial`; invalid initial state: `invalid_initial`); a failed trajectory
      moves the others by 1e-14 to 1e-10 at most, through `Projected`'s first stages
      (docs/batched.md). With an adaptive controller a NaN vector field rejects steps until
      `max_steps`, which the batch waits for (fixed steps stop it).
    - `chunk_size`: the most trajectories per `vmap` on a device (default: about `512 / n`
      on CPU, keeping the working set in cache; the whole batch elsewhere), in chunks as
      even as can be; results do not change.
    - `devices`: devices to shard the batch over with `shard_map` (default: all of JAX's
      default backend, of every process after `jax.distributed.initialize`; at most one
      per trajectory); the batch is padded to a multiple of their count and the padding
      stripped (a size that count does not divide comes back whole on every device: a
      `jax.Array`'s shards are equal). One device: the run and its results stay on it
      (JAX's default device while it runs). Across processes every process passes the
      whole batch, or its slice as global arrays; `throw=True` raises the same message on
      every process. On several devices gradients take forward mode (docs/distributed.md).

    **Returns:** a `diffrax.Solution` whose every array has a leading batch axis:
    `sol.ys = (q, v)` of shape `(batch, times, n, 3)`, `sol.result` and
    `sol.stats["num_steps"]` per trajectory, sharded over the devices.
    """
    batched = dict(batched=True, batch_args=batch_args, batch_system=batch_system)
    run = prepare(system, y0, args, **batched, t1=t1, **options)
    size = len(run.valid)
    devices = batch_devices(devices, size)
    mesh = batch_mesh(devices)
    opts = dataclasses.replace(run.opts, sharded=mesh is not None)  # forward-mode gradients
    inputs = (run.system, run.args, run.t0, run.t1, run.dt0, opts)
    dynamic, static = eqx.partition(inputs, eqx.is_array)
    mask = (batch_system, batch_args) + jax.tree.map(lambda _: False, dynamic[2:])  # prefixes
    batched, shared = eqx.partition(dynamic, mask)
    n_rows = system.space.rows(jax.tree.map(lambda x: x[0], run.y0[0]))
    chunk = _chunk_size(chunk_size, n_rows, -(-size // len(devices)), devices[0].platform)
    padded = -(-size // (chunk * len(devices))) * chunk * len(devices)
    y0 = run.y0
    if mesh is not None:  # each process's slices (global arrays), laid on the batch's mesh
        batched, y0 = _on_mesh((batched, y0), mesh)
    with forward_mode_hint(run.opts.adjoint), one_device(devices):
        sol = _solve_batch(static, chunk, mesh, shared, batched, y0, run.valid, size, padded)
    return raise_on_failure(sol, run.opts.max_steps, "simulate_batch") if run.throw else sol


simulate_batch.__signature__ = shared_signature(simulate_batch, simulate)
