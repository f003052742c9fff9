"""simulate_batch: agreement with a loop over simulate, batched parameters, chunking,
sharding over two (simulated) CPU devices, per-trajectory failures, no recompilation."""

import os
import subprocess
import sys
import textwrap

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import cpu_devices

import sphere_mech as sm

N, BATCH = 3, 5
TS = jnp.linspace(0.0, 1.0, 6)
FIXED = dict(solver=sm.Projected(sm.RK4()), dt0=0.01, saveat=diffrax.SaveAt(ts=TS))


def states(seed, batch=BATCH, n=N):
    keys = jax.random.split(jax.random.PRNGKey(seed), batch)
    return jax.vmap(lambda k: sm.random_state(k, n))(keys)


def chains(masses, torque=None):
    lengths = jnp.array([1.0, 0.7, 1.3])
    return eqx.filter_vmap(lambda m: sm.chain_pendulum(m, lengths, torque=torque))(masses)


@pytest.fixture(scope="module")
def chain():
    return sm.chain_pendulum(jnp.array([1.0, 2.0, 0.5]), jnp.array([1.0, 0.7, 1.3]))


@pytest.fixture(scope="module")
def masses():
    return jnp.linspace(0.5, 2.0, BATCH)[:, None] * jnp.array([1.0, 2.0, 0.5])


def test_agrees_with_loop_over_simulate(chain):
    y0 = states(0)
    saveat = diffrax.SaveAt(ts=TS)
    sol = sm.simulate_batch(chain, y0, 1.0, saveat=saveat)  # adaptive: own steps each
    assert sol.ys[0].shape == (BATCH, TS.size, N, 3)
    for i in range(BATCH):
        ref = sm.simulate(chain, (y0[0][i], y0[1][i]), 1.0, saveat=saveat)
        for a, b in zip(sol.ys, ref.ys, strict=True):
            np.testing.assert_allclose(a[i], b, rtol=0, atol=1e-12)
        assert int(sol.stats["num_steps"][i]) == int(ref.stats["num_steps"])
    assert len(set(np.asarray(sol.stats["num_steps"]).tolist())) > 1  # per trajectory
    assert np.all(np.asarray(sol.result == sm.RESULTS.successful))


def test_batched_system_and_args_and_chunks(chain, masses):
    y0 = states(1)
    batch = sm.simulate_batch(chains(masses), y0, 1.0, batch_system=True, **FIXED)
    chunked = sm.simulate_batch(chains(masses), y0, 1.0, batch_system=True, chunk_size=2, **FIXED)
    for i in range(BATCH):
        one = chains(masses[i : i + 1])
        one = jax.tree.map(lambda x: x[0] if eqx.is_array(x) else x, one)
        ref = sm.simulate(one, (y0[0][i], y0[1][i]), 1.0, **FIXED)
        np.testing.assert_allclose(batch.ys[0][i], ref.ys[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(chunked.ys[1][i], ref.ys[1], rtol=0, atol=1e-12)
    # Batched args: gravity per trajectory through a user potential.
    system = sm.ConstantInertiaLagrangian(
        chain.inertia(), lambda t, q, g: g * jnp.sum(chain.masses() * chain.positions(q)[:, 2])
    )
    gs = jnp.linspace(1.0, 20.0, BATCH)
    sol = sm.simulate_batch(system, y0, 1.0, args=gs, **FIXED)
    for i in (0, BATCH - 1):
        ref = sm.simulate(system, (y0[0][i], y0[1][i]), 1.0, args=gs[i], **FIXED)
        np.testing.assert_allclose(sol.ys[0][i], ref.ys[0], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="leading batch axis"):
        sm.simulate_batch(system, y0, 1.0, args=gs[:2], **FIXED)
    # a Python number, and an unbatched system (each an IndexError from inside before)
    message = r"args\['g'\] must have a leading batch axis of size 5 .* got shape \(\); batch_args"
    with pytest.raises(ValueError, match=message):
        sm.simulate_batch(system, y0, 1.0, args={"g": 9.81}, **FIXED)
    message = r"system.*masses must have a leading batch axis of size 5 .* got shape \(3,\)"
    with pytest.raises(ValueError, match=message):
        sm.simulate_batch(chain, y0, 1.0, batch_system=True, **FIXED)
    with pytest.raises(ValueError, match=r"got \(3,\) \(one member of y0: y0 has a leading"):
        sm.simulate_batch(system, jax.tree.map(lambda x: x[0], y0), 1.0, args=gs, **FIXED)
    with pytest.raises(ValueError, match="devices must be a non-empty sequence"):
        sm.simulate_batch(system, y0, 1.0, args=gs, devices=[], **FIXED)


def test_nan_trajectory_is_reported_and_isolated(masses):
    y0 = states(2)
    good = sm.simulate_batch(chains(masses), y0, 1.0, batch_system=True, **FIXED)
    bad_masses = masses.at[2, 1].set(jnp.nan)
    sol = sm.simulate_batch(chains(bad_masses), y0, 1.0, batch_system=True, throw=False, **FIXED)
    failed = np.asarray(sol.result != sm.RESULTS.successful)
    assert np.array_equal(failed, np.arange(BATCH) == 2)
    assert bool((sol.result == sm.RESULTS.nonfinite_initial)[2])
    keep = np.array([0, 1, 3, 4])
    for a, b in zip(sol.ys, good.ys, strict=True):
        np.testing.assert_array_equal(a[keep], b[keep])
    with pytest.raises(RuntimeError, match=r"1 of 5 trajectories failed \(indices 2\)"):
        sm.simulate_batch(chains(bad_masses), y0, 1.0, batch_system=True, **FIXED)


@pytest.mark.parametrize("on_error", ["raise", "nan"])
def test_invalid_initial_state_is_reported_and_isolated(chain, on_error):
    """One NaN initial state loses only its own trajectory (code `invalid_initial`), the
    others bit-identical to a clean run, also under EQX_ON_ERROR=nan; with throw=True a
    ValueError names it. Adaptive steps with Projected: a NaN member that never stepped
    would change the others' first-stage evaluations (diffrax's unvmap_any)."""
    script = textwrap.dedent(f"""
        import os
        os.environ["EQX_ON_ERROR"] = "{on_error}"
        import jax, jax.numpy as jnp, numpy as np, diffrax, pytest
        jax.config.update("jax_enable_x64", True)
        import sphere_mech as sm
        keys = jax.random.split(jax.random.PRNGKey(0), 6)
        q0, v0 = jax.vmap(lambda k: sm.random_state(k, 3))(keys)
        chain = sm.chain_pendulum(jnp.array([1.0, 2.0, 0.5]), jnp.array([1.0, 0.7, 1.3]))
        kw = dict(saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, 1.0, 4)))
        clean = sm.simulate_batch(chain, (q0, v0), 1.0, throw=False, **kw)
        bad = (q0.at[3, 0, 0].set(jnp.nan), v0.at[4].add(0.5 * q0[4]))
        sol = sm.simulate_batch(chain, bad, 1.0, throw=False, **kw)
        codes = np.asarray(sol.result == sm.RESULTS.invalid_initial)
        assert codes.tolist() == [False] * 3 + [True, True, False], codes
        ok = np.asarray(sol.result == sm.RESULTS.successful)
        assert ok.tolist() == [True] * 3 + [False, False, True], ok
        for a, b in zip(sol.ys, clean.ys):
            a, b = np.asarray(a), np.asarray(b)
            np.testing.assert_array_equal(a[[0, 1, 2, 5]], b[[0, 1, 2, 5]])
            assert np.all(np.isinf(a[3:5]))
        assert np.asarray(sol.stats["num_steps"])[3:5].tolist() == [0, 0]
        with pytest.raises(ValueError, match=r"^simulate_batch: 2 of 6 initial states are "
                           r"invalid \\(indices 3, 4\\); initial state 3: q contains NaN"):
            sm.simulate_batch(chain, bad, 1.0, **kw)
        print("ok")
    """)
    if on_error == "raise":  # equinox's default: run here
        exec(script, {})
        return
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300
    )
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]


def test_invalid_member_has_no_event_and_no_dense_output():
    """An invalid initial state ran its stand-in (member 0): its event mask and dense
    output were the stand-in's (True; member 0's trajectory). A NumPy `chunk_size` (here
    two chunks of 2) passed the check, then failed to trace."""
    pendulum = sm.chain_pendulum([1.0], [0.7])
    theta = jnp.array([0.3, 0.6, 0.9, 1.2])
    q = jnp.stack([jnp.sin(theta), 0 * theta, -jnp.cos(theta)], axis=-1)[:, None]
    cross = lambda t, y, args, **kw: y[0][0, 0]
    event = diffrax.Event(cross, root_finder=optx.Newton(rtol=1e-12, atol=1e-12))
    sol = sm.simulate_batch(
        pendulum,
        (q.at[2, 0, 0].set(jnp.nan), jnp.zeros_like(q)),
        1.0,
        batch_args=False,
        throw=False,
        event=event,
        saveat=diffrax.SaveAt(t1=True, dense=True),
        chunk_size=np.int64(3),
    )
    assert np.asarray(sol.event_mask).tolist() == [True, True, False, True]
    assert np.asarray(sol.result == sm.RESULTS.invalid_initial).tolist() == [0, 0, 1, 0]
    dense = np.asarray(jax.vmap(lambda i: i.evaluate(0.1))(sol.interpolation)[0])
    assert np.all(np.isfinite(dense[[0, 1, 3]])) and not np.any(np.isfinite(dense[2]))
    assert np.all(np.isinf(np.asarray(sol.ys[0][2])))


TRACES = {"count": 0}


def no_torque(t, q, qdot, args):
    """A zero torque on the first link (a user function in the chains) that counts its
    traces: once per compilation of every function that evaluates it."""
    TRACES["count"] += 1
    return jnp.zeros(3, q.dtype)


def test_no_recompilation_when_values_change(masses):
    kwargs = dict(batch_system=True, **FIXED)
    sm.simulate_batch(chains(masses, no_torque), states(3), 1.0, **kwargs)
    traces = TRACES["count"]
    assert traces > 0  # the counter sees simulate_batch's traces
    sm.simulate_batch(chains(2.0 * masses, no_torque), states(4), 1.2, **kwargs)
    sm.simulate_batch(chains(masses + 0.1, no_torque), states(5), 1.1, t0=-0.1, **kwargs)
    assert TRACES["count"] == traces  # no new trace: no new compilation


SHARDED = textwrap.dedent(
    """
    import diffrax, jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    import sphere_mech as sm

    assert len(jax.devices()) == 2
    chain = sm.chain_pendulum(jnp.array([1.0, 2.0]), jnp.array([1.0, 0.5]))
    kw = dict(solver=sm.Projected(sm.RK4()), dt0=0.01,
              saveat=diffrax.SaveAt(ts=jnp.linspace(0.0, 0.5, 3)))
    keys = jax.random.split(jax.random.PRNGKey(0), 6)
    y0 = jax.vmap(lambda k: sm.random_state(k, 2))(keys)
    single = sm.simulate_batch(chain, y0, 0.5, devices=jax.devices()[:1], **kw)
    sharded = sm.simulate_batch(chain, y0, 0.5, **kw)
    assert len(sharded.ys[0].sharding.device_set) == 2
    assert not sharded.ys[0].sharding.is_fully_replicated
    odd = sm.simulate_batch(chain, tuple(y[:5] for y in y0), 0.5, **kw)  # padded to 6
    assert odd.ys[0].shape == (5, 3, 2, 3)
    one = sm.simulate_batch(chain, tuple(y[:1] for y in y0), 0.5, **kw)  # no padding device
    assert len(one.ys[0].sharding.device_set) == 1
    for a, b, c, d in zip(sharded.ys, single.ys, odd.ys, one.ys):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-14)
        np.testing.assert_allclose(c, b[:5], rtol=0, atol=1e-14)
        np.testing.assert_allclose(d, b[:1], rtol=0, atol=1e-14)
    print("ok")
    """
)


def test_sharded_equals_unsharded_on_two_cpu_devices():
    env = dict(os.environ, **cpu_devices(2))
    out = subprocess.run(
        [sys.executable, "-c", SHARDED], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().endswith("ok")


def test_chunks_are_as_even_as_can_be():
    """At most `chunk_size` trajectories per `vmap`, in chunks as even as can be: 257 in two
    chunks of 129 (before: padded to 512, one chunk of 256 and one of 256 copies)."""
    from sphere_mech._batch import _chunk_size

    for local, at_most, expected in [(257, 256, 129), (256, 256, 256), (1000, 256, 250), (5, 2, 2)]:
        chunk = _chunk_size(np.int64(at_most), 1, local, "cpu")
        assert (
            type(chunk) is int
            and chunk == expected
            and -(-local // chunk) * chunk - local < -(-local // at_most)
        )
