"""Cost of `jax.value_and_grad` through `sm.simulate` and `sm.simulate_batch`, relative to
the forward pass, with the old default adjoint (`diffrax.RecursiveCheckpointAdjoint()`)
and the new default (`adjoint=None`: forward-mode Jacobian for at most
`FORWARD_COLUMNS` differentiated scalars in `simulate`, `BATCH_FORWARD_COLUMNS` in
`simulate_batch`, else the same checkpointed reverse mode).

The loss is a weighted sum of the final positions of chain pendulums (unit masses,
g = 9.81), differentiated with respect to the chain's n lengths. Cases: n = 2 and 8,
float32 and float64, fixed-step `Projected(RK4())` at dt0 = 1e-3 and adaptive
`Projected(Tsit5())` (default tolerances), one trajectory (`simulate`) and a batch
(`simulate_batch`, B = 256 at n = 2, 64 at n = 8). Times: after compilation, median (and
minimum) of repeats, the three programs of a row taking turns (so that a burst of load
from other processes hits all three); the ratios are value_and_grad time / forward time,
all measured in the same run.
Prints a markdown table and writes benchmarks/results/gradients.{md,png}.

`--rk4-batch`: only the batched fixed-step rows (RK4, n = 2 with B = 256 and n = 8 with
B = 64, float32 and float64), before and after `RK4(stagewise_reverse=True)` became the
default adjoint's reverse mode: checkpointed reverse mode with the whole step transposed
(`RecursiveCheckpointAdjoint()`, the default's reverse mode before), stage by stage
(`RK4(stagewise_reverse=True)`, its reverse mode now) and the default (forward mode
at n = 2, 2 differentiated scalars; reverse mode at n = 8); writes
benchmarks/results/gradients_rk4_batch.{md,png}.

`--where`: where the time of the batched RK4 rows' reverse pass goes (float64): the vector
field's reverse pass against its forward pass (`jax.vjp` with the forward recomputed, as the
stage-by-stage reverse pass does, each in a `lax.scan` of 300 evaluations), its forward
mode with 2 tangents (`jax.jvp` under `vmap`, as the default's forward mode at n = 2
runs it: the least such a pass can cost against the forward one), the floor of a
reverse pass that recomputes each step once (forward + recomputed forward + four vector
field pullbacks a step), and the checkpointed reverse pass with `checkpoints` at half, one
and four times the 300 steps (the default: `floor(sqrt(2 max_steps))` = 447); writes
benchmarks/results/gradients_where.{md,png}.

`--bare`: the same batched RK4 rows (n = 2 with B = 256, n = 8 with B = 64, float32 and
float64) against the smallest program that takes the same steps: the library's own step
(`Projected(RK4()).step` on a `MechanicsTerm`) in a plain `jax.lax.scan` of 300 steps under
`vmap`, without diffrax's loop, differentiated by JAX itself: reverse mode storing every
step's intermediates, reverse mode recomputing each step once (`jax.checkpoint` on the
step), and forward mode (`jax.jacfwd`, n columns). Whether the ratio comes from the
library's loop and adjoint or from the vector field's derivative; writes
benchmarks/results/gradients_bare.{md,png}.

`--chunks`: the batched RK4 row at B = 1024, n = 8, float64, at 16, 64 (the default at
n = 8), 256 and 1024 trajectories per `vmap` (`simulate_batch`'s `chunk_size`): whether
how the batch is split moves the ratio; writes benchmarks/results/gradients_chunks.{md,png}.

`--learned`: the training step of `sm.learn` on the tasks of
`benchmarks/learned_lagrangian.py` (a `LearnedLagrangian`: an MLP potential): its minibatch
loss (100 chunks, L1, each task's dtype and RK4 steps per observation) and the loss's
value_and_grad, reverse mode through the whole RK4 step transposed by JAX (`RK4()` under an
explicit `RecursiveCheckpointAdjoint`, as `learn` runs it) and stage by stage
(`RK4(stagewise_reverse=True)`, as the default adjoint's reverse mode runs it); writes
benchmarks/results/gradients_learned.{md,png}.

    python benchmarks/gradients.py [--quick | --rk4-batch | --where | --bare | --chunks |
                                    --learned]
"""

import argparse
import json

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

jax.config.update("jax_enable_x64", True)
from _harness import (  # noqa: E402
    RESULTS,
    bars,
    load,
    machine,
    publish,
    pyplot,
    random_states,
    save_figure,
    table,
    timings,
)

import sphere_mech as sm  # noqa: E402
from sphere_mech._adjoint import BATCH_FORWARD_COLUMNS, FORWARD_COLUMNS  # noqa: E402

OLD = diffrax.RecursiveCheckpointAdjoint()
SOLVERS = {  # name: (solver, dt0, t1)
    "RK4 (fixed, dt 1e-3)": (sm.Projected(sm.RK4()), 1e-3, 0.3),
    "Tsit5 (adaptive)": (sm.Projected(diffrax.Tsit5()), 1e-2, 1.0),
}
BATCH = {2: 256, 8: 64}


def _machine(loads, flags: str) -> str:
    """The tables' line on where and how they were measured."""
    return (
        f"Machine: {machine(loads)}, JAX on {jax.devices()[0].platform}; "
        f"`python benchmarks/gradients.py{flags}`.\n\n"
    )


def ratio_figure(labels, series, name, loads, flags, targets=((4, "goal: 4x"),), log=False):
    """Grouped bars of the ratios `series` (`{legend: a ratio per label}`) per row label,
    with the horizontal `targets` (`(value, legend)`), written as `name`."""
    fig, ax = pyplot().subplots(figsize=(min(12, 4 + 0.7 * len(labels)), 3.8))
    bars(ax, labels, series, fontsize=7)
    for (value, label), style in zip(targets, ("--", ":"), strict=False):
        ax.axhline(value, color="k", ls=style, lw=0.8, label=label)
    ax.set(ylabel="value_and_grad / forward", yscale="log" if log else "linear")
    ax.set_title(f"{machine(loads)}\n`python benchmarks/gradients.py{flags}`", fontsize=7)
    ax.legend(fontsize=7)
    save_figure(fig, name)


def _states(n, batch, dtype):
    q, v = random_states(n, batch, speed=0.5)
    return q.astype(dtype), v.astype(dtype)


def loss_fn(n, dtype, solver_name, batch, solver=None, chunk_size=None):
    """`loss(lengths, adjoint)` of one case (with `solver` in place of the case's, and
    `simulate_batch`'s `chunk_size`), and its initial lengths."""
    default_solver, dt0, t1 = SOLVERS[solver_name]
    solver = solver or default_solver
    q, v = _states(n, batch or 1, dtype)
    weights = jnp.arange(1.0, 4.0, dtype=dtype)

    def loss(lengths, adjoint):
        chain = sm.chain_pendulum(jnp.ones(n, dtype), lengths, 9.81)
        kw = dict(solver=solver, dt0=dt0, adjoint=adjoint)
        if batch:
            q1 = sm.simulate_batch(chain, (q, v), t1, chunk_size=chunk_size, **kw).ys[0][:, -1]
            return jnp.sum(jax.vmap(chain.positions)(q1) @ weights)
        q1 = sm.simulate(chain, (q[0], v[0]), t1, **kw).ys[0][-1]
        return jnp.sum(chain.positions(q1) @ weights)

    return loss, jnp.linspace(1.0, 0.7, n, dtype=dtype)


def measure(n, dtype, solver_name, batch, repeats):
    loss, lengths = loss_fn(n, dtype, solver_name, batch)
    forward = eqx.filter_jit(lambda x: loss(x, None))
    old = eqx.filter_jit(jax.value_and_grad(lambda x: loss(x, OLD)))
    new = eqx.filter_jit(jax.value_and_grad(lambda x: loss(x, None)))
    g_old, g_new = old(lengths)[1], new(lengths)[1]
    tol = 1e-6 if dtype == jnp.float64 else 2e-2
    assert np.allclose(g_old, g_new, rtol=tol, atol=tol), (g_old, g_new)
    return timings([lambda f=f: f(lengths) for f in (forward, old, new)], repeats)


def rk4_batch_row(n, dtype, repeats):
    """Forward, whole-step reverse, stage-by-stage reverse and the default."""
    name = "RK4 (fixed, dt 1e-3)"
    loss, lengths = loss_fn(n, dtype, name, BATCH[n])
    stagewise = sm.Projected(sm.RK4(stagewise_reverse=True))
    loss_s, _ = loss_fn(n, dtype, name, BATCH[n], stagewise)
    programs = [
        eqx.filter_jit(lambda x: loss(x, None)),
        eqx.filter_jit(jax.value_and_grad(lambda x: loss(x, OLD))),
        eqx.filter_jit(jax.value_and_grad(lambda x: loss_s(x, OLD))),
        eqx.filter_jit(jax.value_and_grad(lambda x: loss(x, None))),
    ]
    grads = [p(lengths)[1] for p in programs[1:]]
    tol = 1e-10 if dtype == jnp.float64 else 2e-2
    for g in grads[1:]:
        assert np.allclose(g, grads[0], rtol=tol, atol=tol), (g, grads[0])
    return timings([lambda f=f: f(lengths) for f in programs], repeats)


def batch_rows(row, repeats):
    """`(n, B, dtype, *row(n, dtype, repeats))` for the batched RK4 cases (n = 2 with
    B = 256, n = 8 with B = 64; float32, float64), and the load average around them."""
    rows, loads = [], [load()]
    for n in BATCH:
        for dtype in (jnp.float32, jnp.float64):
            times = row(n, dtype, repeats)
            loads.append(load())
            rows.append((n, BATCH[n], jnp.dtype(dtype).name, *times))
            print(f"  {rows[-1][:3]}: {times[0].median * 1e3:.2f} ms", flush=True)
    return rows, loads


def rk4_batch(repeats=7):
    """The batched RK4 rows, before and after the stage-by-stage reverse mode."""
    rows, loads = batch_rows(rk4_batch_row, repeats)
    text = table(
        [
            "n",
            "B",
            "dtype",
            "forward [ms]",
            "reverse, whole step (before)",
            "reverse, stage by stage (now)",
            "default (forward mode at n = 2; reverse, stage by stage, at n = 8)",
            "min over repeats: whole step / stage by stage / default",
        ],
        [
            (
                n,
                b,
                dt,
                f"{f.median * 1e3:.2f}",
                *(f"{t.median / f.median:.1f}" for t in (old, staged, new)),
                " / ".join(f"{t.min / f.min:.1f}" for t in (old, staged, new)),
            )
            for n, b, dt, f, old, staged, new in rows
        ],
    )
    publish(
        "value_and_grad time / forward time of `simulate_batch` with `Projected(RK4())` at "
        "dt0 = 1e-3 over 0.3 s (300 steps), medians of 7 repeats.\n\n"
        + _machine(loads, " --rk4-batch")
        + text
        + "\n",
        "gradients_rk4_batch.md",
    )
    names = ("whole step (before)", "stage by stage (now)", "default")
    ratio_figure(
        [f"n={n} B={b}\n{dt}" for n, b, dt, *_ in rows],
        {k: [r[4 + i].median / r[3].median for r in rows] for i, k in enumerate(names)},
        "gradients_rk4_batch.png",
        loads,
        " --rk4-batch",
    )


def rates_derivative_costs(n, batch, repeats, evaluations=300, tangents=2):
    """Seconds per batched evaluation of the chain's vector field: forward, `jax.vjp`
    (forward recomputed, cotangent pulled back to the lengths and the state) and `jax.jvp`
    with `tangents` tangents (the first lengths, under `vmap` as `jax.jacfwd` runs them,
    each carried through the evaluations as forward mode carries it through the steps)."""
    y, lengths = _states(n, batch, jnp.float64), jnp.linspace(1.0, 0.7, n)
    basis = jnp.eye(n)[:tangents]

    def rates(lengths, y):
        chain = sm.chain_pendulum(jnp.ones(n), lengths, 9.81)
        return jax.vmap(lambda y: chain.rates(0.0, y, None))(y)

    nudge = lambda y, k: jax.tree.map(lambda a, b: a + 1e-9 * b, y, k)

    @eqx.filter_jit
    def forward(lengths, y):
        body = lambda y, _: (nudge(y, rates(lengths, y)), None)
        return jax.lax.scan(body, y, None, evaluations)[0]

    @eqx.filter_jit
    def pullback(lengths, y):
        def body(carry, _):
            y, g = carry
            k, pull = jax.vjp(rates, lengths, y)
            g_lengths, g_y = pull(k)
            return (nudge(y, g_y), g + g_lengths), None

        return jax.lax.scan(body, (y, lengths), None, evaluations)[0]

    @eqx.filter_jit
    def push_forward(lengths, y):
        def body(carry, _):
            y, dy = carry
            one = lambda t, dy: jax.jvp(rates, (lengths, y), (t, dy))
            k, dk = jax.vmap(one, out_axes=(None, 0))(basis, dy)
            return (nudge(y, k), nudge(dy, dk)), None

        dy = jax.tree.map(lambda a: jnp.zeros((tangents, *a.shape)), y)
        return jax.lax.scan(body, (y, dy), None, evaluations)[0]

    programs = (forward, pullback, push_forward)
    times = timings([lambda f=f: f(lengths, y) for f in programs], repeats)
    return [t.median / evaluations for t in times]


def where_row(n, counts, repeats):
    """Forward, the default and stage-by-stage reverse mode with each of `counts`
    checkpoints, float64."""
    name = "RK4 (fixed, dt 1e-3)"
    loss, lengths = loss_fn(n, jnp.float64, name, BATCH[n])
    stagewise = sm.Projected(sm.RK4(stagewise_reverse=True))
    loss_s, _ = loss_fn(n, jnp.float64, name, BATCH[n], stagewise)
    adjoint = lambda k: diffrax.RecursiveCheckpointAdjoint(checkpoints=k)
    programs = [
        eqx.filter_jit(lambda x: loss(x, None)),
        eqx.filter_jit(jax.value_and_grad(lambda x: loss(x, None))),
        *(eqx.filter_jit(jax.value_and_grad(lambda x, k=k: loss_s(x, adjoint(k)))) for k in counts),
    ]
    grads = [p(lengths)[1] for p in programs[1:]]
    for g in grads[1:]:
        assert np.allclose(g, grads[0], rtol=1e-10, atol=1e-10), (g, grads[0])
    return timings([lambda f=f: f(lengths) for f in programs], repeats)


def where(repeats=7):
    """The vector field's pullback, the recompute floor and the checkpoint counts."""
    steps = 300
    counts = (steps // 2, steps, 4 * steps)
    rows, loads = [], [load()]
    for n in BATCH:
        rate_f, rate_b, rate_t = rates_derivative_costs(n, BATCH[n], repeats)
        forward, *reverse = where_row(n, counts, repeats)
        floor = (2 * forward.median + 4 * steps * rate_b) / forward.median
        loads.append(load())
        rows.append((n, BATCH[n], rate_f, rate_b, rate_t, forward, floor, reverse))
        print(f"  n = {n}: {forward.median * 1e3:.2f} ms", flush=True)
    text = table(
        [
            "n",
            "B",
            "vector field [us]",
            "its pullback / forward",
            "its jvp, 2 tangents / forward",
            "solve, forward [ms]",
            "floor (recompute once)",
            "default (forward mode at n = 2: 2 scalars)",
            *(f"checkpoints = {k}" for k in counts),
        ],
        [
            (
                n,
                b,
                f"{rf * 1e6:.1f}",
                f"{rb / rf:.2f}",
                f"{rt / rf:.2f}",
                f"{f.median * 1e3:.2f}",
                f"{floor:.1f}",
                *(f"{t.median / f.median:.1f}" for t in reverse),
            )
            for n, b, rf, rb, rt, f, floor, reverse in rows
        ],
    )
    publish(
        "Where the reverse pass's time goes: `simulate_batch` with `Projected(RK4())`, dt0 = "
        "1e-3 over 0.3 s (300 steps), float64, medians of 7 repeats; ratios are "
        "value_and_grad time / forward time. The floor: a forward pass, the forward "
        "recomputed once, and four pullbacks of the vector field a step (its measured "
        "pullback time). The jvp: the vector field's `jax.jvp` with 2 tangents under "
        "`vmap`, as forward mode runs it.\n\n" + _machine(loads, " --where") + text + "\n",
        "gradients_where.md",
    )
    series = {"floor (recompute once)": [r[6] for r in rows]}
    series["default"] = [r[7][0].median / r[5].median for r in rows]
    for i, k in enumerate(counts):
        series[f"checkpoints = {k}"] = [r[7][1 + i].median / r[5].median for r in rows]
    labels = [f"n={n} B={b}" for n, b, *_ in rows]
    ratio_figure(labels, series, "gradients_where.png", loads, " --where")


def bare_loss(n, dtype, remat=False):
    """`loss(lengths)` of the batched RK4 case as a plain `lax.scan` of the library's step
    (`remat`: `jax.checkpoint` on the step, recomputed once in reverse mode)."""
    solver, dt0, t1 = SOLVERS["RK4 (fixed, dt 1e-3)"]
    steps = round(t1 / dt0)
    q, v = _states(n, BATCH[n], dtype)
    weights = jnp.arange(1.0, 4.0, dtype=dtype)

    def loss(lengths):
        chain = sm.chain_pendulum(jnp.ones(n, dtype), lengths, 9.81)
        term = sm.MechanicsTerm(chain)

        def step(y, k):
            t0 = k * jnp.asarray(dt0, dtype)
            y1 = solver.step(term, t0, t0 + dt0, y, None, None, False)[0]
            return y1, None

        step = jax.checkpoint(step) if remat else step
        run = lambda y: jax.lax.scan(step, y, jnp.arange(steps, dtype=dtype))[0][0]
        q1 = jax.vmap(lambda q, v: run((q, v)))(q, v)
        return jnp.sum(jax.vmap(chain.positions)(q1) @ weights)

    return loss


def bare_row(n, dtype, repeats):
    """The library's forward and default value_and_grad, then the plain scan's forward,
    reverse mode (stored, recomputed) and forward mode."""
    loss, lengths = loss_fn(n, dtype, "RK4 (fixed, dt 1e-3)", BATCH[n])
    bare, bare_remat = bare_loss(n, dtype), bare_loss(n, dtype, remat=True)
    with_value = lambda f: lambda x: (f(x), jax.jacfwd(f)(x))
    programs = [
        eqx.filter_jit(lambda x: loss(x, None)),
        eqx.filter_jit(jax.value_and_grad(lambda x: loss(x, None))),
        eqx.filter_jit(bare),
        eqx.filter_jit(jax.value_and_grad(bare)),
        eqx.filter_jit(jax.value_and_grad(bare_remat)),
        eqx.filter_jit(with_value(bare)),
    ]
    values = [p(lengths) for p in programs]
    tol = 1e-10 if dtype == jnp.float64 else 2e-2
    for value, grad in values[3:]:
        assert np.allclose(value, values[1][0], rtol=tol), (value, values[1][0])
        assert np.allclose(grad, values[1][1], rtol=tol, atol=tol), (grad, values[1][1])
    return timings([lambda f=f: f(lengths) for f in programs], repeats)


def bare(repeats=7):
    """The batched RK4 rows against the plain scan."""
    rows, loads = batch_rows(bare_row, repeats)
    text = table(
        [
            "n",
            "B",
            "dtype",
            "library: forward [ms]",
            "library: default value_and_grad / forward",
            "plain scan: forward [ms]",
            "plain scan: reverse, stored / forward",
            "plain scan: reverse, recomputed / forward",
            "plain scan: forward mode (n columns) / forward",
        ],
        [
            (
                n,
                b,
                dt,
                f"{t[0].median * 1e3:.2f}",
                f"{t[1].median / t[0].median:.1f}",
                f"{t[2].median * 1e3:.2f}",
                *(f"{x.median / t[2].median:.1f}" for x in t[3:]),
            )
            for n, b, dt, *t in rows
        ],
    )
    publish(
        "The library's batched RK4 solve (`simulate_batch`, `Projected(RK4())`, dt0 = 1e-3 "
        "over 0.3 s, 300 steps) against the same steps in a plain `jax.lax.scan` of the "
        "library's step under `vmap`, differentiated by JAX itself (the gradients agree: "
        "1e-10 in float64, 2e-2 in float32); medians of 7 repeats, the six programs of a "
        "row taking turns; ratios are value_and_grad time / the same program's forward "
        "time (forward mode: value and `jax.jacfwd`).\n\n"
        + _machine(loads, " --bare")
        + text
        + "\n",
        "gradients_bare.md",
    )
    names = ("plain scan: reverse, stored", "reverse, recomputed", "forward mode (n columns)")
    series = {"library: default": [r[4].median / r[3].median for r in rows]}
    for i, k in enumerate(names):
        series[k] = [r[6 + i].median / r[5].median for r in rows]
    labels = [f"n={n} B={b}\n{dt}" for n, b, dt, *_ in rows]
    ratio_figure(labels, series, "gradients_bare.png", loads, " --bare", log=True)


def chunks(repeats=5, n=8, batch=1024, sizes=(16, 64, 256, 1024)):
    """The batched RK4 row at B = 1024, n = 8, float64, with each of `sizes` trajectories
    per `vmap` (`simulate_batch`'s `chunk_size`; its default at n = 8: 64)."""
    name, dtype = "RK4 (fixed, dt 1e-3)", jnp.float64
    rows, loads = [], [load()]
    for size in sizes:
        loss, lengths = loss_fn(n, dtype, name, batch, chunk_size=size)
        forward = eqx.filter_jit(lambda x, loss=loss: loss(x, None))
        gradient = eqx.filter_jit(jax.value_and_grad(lambda x, loss=loss: loss(x, None)))
        calls = [lambda f=f, x=lengths: f(x) for f in (forward, gradient)]
        rows.append((size, *timings(calls, repeats)))
        loads.append(load())
        print(f"  chunk {size}: {rows[-1][1].median * 1e3:.1f} ms", flush=True)
    fastest = min(f.median for _, f, _ in rows)
    text = table(
        [
            "chunk size",
            "forward [ms]",
            "value_and_grad [ms]",
            "value_and_grad / forward",
            "value_and_grad / fastest forward",
        ],
        [
            (
                size,
                f"{f.median * 1e3:.1f}",
                f"{g.median * 1e3:.1f}",
                f"{g.median / f.median:.1f}",
                f"{g.median / fastest:.1f}",
            )
            for size, f, g in rows
        ],
    )
    publish(
        f"The batched RK4 row at B = {batch}, n = {n}, float64 (`simulate_batch`, "
        "`Projected(RK4())`, dt0 = 1e-3 over 0.3 s, the default adjoint) with each chunk "
        f"size; medians of {repeats} repeats, a row's two programs taking turns.\n\n"
        + _machine(loads, " --chunks")
        + text
        + "\n",
        "gradients_chunks.md",
    )
    series = {
        "value_and_grad / forward": [g.median / f.median for _, f, g in rows],
        "value_and_grad / fastest forward": [g.median / fastest for _, f, g in rows],
    }
    labels = [f"chunk {size}" for size, *_ in rows]
    ratio_figure(labels, series, "gradients_chunks.png", loads, " --chunks")


LEARNED = ("magnet", "chain3", "chain5")
"""The tasks, each timed in its training dtype and RK4 steps per observation, read from its
results (`results/learned_lagrangian/<task>.json`)."""


def learned_row(system, repeats, batch=100):
    """Forward, and value_and_grad with the whole step and stage by stage, of `learn`'s
    loss on one minibatch of `system`'s training chunks (`learn`'s own shooting problem),
    and the model's MLP width."""
    import learned_lagrangian as ll

    from sphere_mech._fit.learn import _Chunks

    trained = json.loads((RESULTS / "learned_lagrangian" / f"{system}.json").read_text())
    # Results written before `--dtype` existed (the chains') trained in float64.
    dtype, substeps = trained.get("dtype", "float64"), trained["substeps"]
    tk = ll.task(system)
    ts, chunks = ll.training_chunks(tk, batch)

    def loss(rk4):
        sim = ll.training_options(tk, rk4, substeps)
        problem = _Chunks.build(ll.new_model(tk, dtype=dtype), ts, chunks, sim, "grad", "learn")
        data = problem.pick(np.arange(batch))
        return lambda u: ll.l1(problem.residuals((u, None), data)[0]), problem

    (whole, problem), (stagewise, _) = loss(sm.RK4()), loss(sm.RK4(stagewise_reverse=True))
    programs = [eqx.filter_jit(whole)] + [
        eqx.filter_jit(jax.value_and_grad(f)) for f in (whole, stagewise)
    ]
    u0 = problem.unknowns[0]
    grads = [ravel_pytree(p(u0)[1])[0] for p in programs[1:]]
    tol = 1e-10 if dtype == "float64" else 1e-4
    assert np.allclose(grads[0], grads[1], rtol=tol, atol=tol * np.abs(grads[0]).max())
    times = timings([lambda f=f: f(u0) for f in programs], repeats)
    return dtype, substeps, times, ll.MODEL[system]["width"]


def learned(repeats=15):
    rows, loads, widths = [], [load()], {}
    for system in LEARNED:
        dtype, substeps, times, widths[system] = learned_row(system, repeats)
        rows.append((system, dtype, substeps, *times))
        loads.append(load())
        print(f"  {system}: {times[0].median * 1e3:.1f} ms", flush=True)
    text = table(
        [
            "task",
            "dtype",
            "RK4 steps per observation",
            "forward [ms]",
            "value_and_grad, whole step (learn) [ms]",
            "stage by stage [ms]",
            "whole step / forward",
            "stage by stage / forward",
        ],
        [
            (
                system,
                dtype,
                substeps,
                f"{f.median * 1e3:.1f}",
                f"{w.median * 1e3:.1f}",
                f"{s.median * 1e3:.1f}",
                f"{w.median / f.median:.1f}",
                f"{s.median / f.median:.1f}",
            )
            for system, dtype, substeps, f, w, s in rows
        ],
    )
    publish(
        "`sm.learn`'s training step on the tasks of `benchmarks/learned_lagrangian.py`: the "
        "minibatch loss (100 chunks of 5 observations, L1) and its value_and_grad in the "
        "task's model (`LearnedLagrangian`, its MLP's width "
        + ", ".join(f"{w} on {system}" for system, w in widths.items())
        + ") and dtype, reverse mode through the whole RK4 step (as `learn` runs it) "
        f"and stage by stage (the default adjoint's reverse mode); medians of {repeats} "
        "repeats, a row's three programs taking turns.\n\n"
        + _machine(loads, " --learned")
        + text
        + "\n",
        "gradients_learned.md",
    )
    series = {
        "whole step (learn)": [w.median / f.median for *_, f, w, _ in rows],
        "stage by stage": [st.median / f.median for *_, f, _, st in rows],
    }
    labels = [f"{system}\n{dtype}" for system, dtype, *_ in rows]
    ratio_figure(labels, series, "gradients_learned.png", loads, " --learned")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="n = 2, float64 only")
    parser.add_argument("--rk4-batch", action="store_true", help="the batched RK4 rows only")
    parser.add_argument("--where", action="store_true", help="where the reverse pass's time goes")
    parser.add_argument("--bare", action="store_true", help="against a plain lax.scan")
    parser.add_argument("--chunks", action="store_true", help="B = 1024 at each chunk size")
    parser.add_argument("--learned", action="store_true", help="learn's training step")
    parsed = parser.parse_args()
    if parsed.learned:
        return learned()
    if parsed.chunks:
        return chunks()
    if parsed.where:
        return where()
    if parsed.bare:
        return bare()
    if parsed.rk4_batch:
        return rk4_batch()
    quick = parsed.quick
    ns, dtypes = ((2,), (jnp.float64,)) if quick else ((2, 8), (jnp.float32, jnp.float64))
    rows, loads = [], [load()]
    for n in ns:
        for dtype in dtypes:
            for solver_name in SOLVERS:
                for batch in (0, BATCH[n]):
                    fwd, old, new = measure(n, dtype, solver_name, batch, 7)
                    loads.append(load())
                    api = f"simulate_batch (B = {batch})" if batch else "simulate"
                    rows.append((n, jnp.dtype(dtype).name, solver_name, api, fwd, old, new))
                    print(f"  {rows[-1][:4]}: {fwd.median * 1e3:.2f} ms", flush=True)
    text = table(
        [
            "n",
            "dtype",
            "solver",
            "call",
            "forward [ms]",
            "value_and_grad / forward, old default (RecursiveCheckpointAdjoint)",
            "new default",
            "old / new",
            "forward, min [ms]",
            "old / new, min",
        ],
        [
            (
                n,
                dt,
                s,
                api,
                f"{f.median * 1e3:.2f}",
                f"{o.median / f.median:.1f}",
                f"{w.median / f.median:.1f}",
                f"{o.median / w.median:.1f}",
                f"{f.min * 1e3:.2f}",
                f"{o.min / w.min:.1f}",
            )
            for n, dt, s, api, f, o, w in rows
        ],
    )
    suffix = "_quick" if quick else ""
    publish(
        "value_and_grad time / forward time.\n\n"
        + _machine(loads, " --quick" * quick)
        + f"Forward-mode Jacobian when at most {FORWARD_COLUMNS} scalars are "
        f"differentiated in `simulate`, {BATCH_FORWARD_COLUMNS} in `simulate_batch` "
        "(here the n lengths).\n\n" + text + "\n",
        f"gradients{suffix}.md",
    )
    labels = [
        f"n={n} {dt[-2:]}\n{s.split()[0]} {'B' if 'batch' in api else '1'}"
        for n, dt, s, api, *_ in rows
    ]
    series = {
        "old default (checkpointed)": [o.median / f.median for *_, f, o, _ in rows],
        "new default": [w.median / f.median for *_, f, _, w in rows],
    }
    targets = ((4, "target: fixed 4x, adaptive 6x"), (6, None))
    ratio_figure(labels, series, f"gradients{suffix}.png", loads, " --quick" * quick, targets, True)


if __name__ == "__main__":
    main()
