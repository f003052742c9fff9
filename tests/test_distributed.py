"""simulate_batch beyond one device: a gradient through a batch sharded over two CPU devices
(one process), and two processes joined by `jax.distributed` on localhost (`throw=True`
raising the same message on both, a `jax.grad`), each compared with one device; in the slow
set, `sm.fit` split over two devices and over two processes."""

import os
import socket
import subprocess
import sys
import textwrap

import pytest
from helpers import cpu_devices

COMMON = """
import os, sys
import diffrax, equinox as eqx, jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import sphere_mech as sm
if len(sys.argv) > 1:  # rank and port: join the other process first
    jax.distributed.initialize(f"localhost:{sys.argv[2]}", 2, process_id=int(sys.argv[1]))

B = 5  # odd: padded to 6 on two devices
KW = dict(solver=sm.Projected(sm.RK4()), dt0=0.05)
y0 = jax.vmap(lambda k: sm.random_state(k, 2))(jax.random.split(jax.random.PRNGKey(0), B))
P = jnp.array([1.0, 2.0, 1.0, 0.5])  # masses and lengths: 4 columns, reverse mode on one device
W = jnp.arange(1.0, B + 1)[:, None, None, None]


def loss(p, y0, devices):
    chain = sm.chain_pendulum(p[:2], p[2:])
    sol = sm.simulate_batch(chain, y0, 0.5, devices=devices, **KW)
    return jnp.sum(W * sol.ys[1] ** 2) + jnp.sum(W * sol.ys[0] * y0[0][:, None])


def close(a, b, tol=1e-12):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=tol, atol=tol)

"""

TWO_DEVICES = (
    COMMON
    + """
assert len(jax.devices()) == 2
grad = jax.value_and_grad(loss, argnums=(0, 1))
one = grad(P, y0, jax.devices()[:1])
two = grad(P, y0, None)
close(one, two)
# one device, not the default one: the run stays on it
sol = sm.simulate_batch(sm.chain_pendulum(P[:2], P[2:]), y0, 0.5, devices=jax.devices()[1:], **KW)
assert all(x.devices() == {jax.devices()[1]} for x in jax.tree.leaves(sol.ys)), sol.ys[0].devices()
# forward mode with adjoint=diffrax.ForwardMode()
ones = jax.tree.map(jnp.ones_like, y0)
fwd = lambda d: jax.jvp(
    lambda y: jnp.sum(W * sm.simulate_batch(sm.chain_pendulum(P[:2], P[2:]), y, 0.5, devices=d,
                                             adjoint=diffrax.ForwardMode(), **KW).ys[1] ** 2),
    (y0,), (ones,))
close(fwd(jax.devices()[:1]), fwd(None))
print("ok")
"""
)

TWO_PROCESSES = (
    COMMON
    + """
from jax.experimental import multihost_utils
assert len(jax.devices()) == 2 and len(jax.local_devices()) == 1
# every process passes the whole batch; each integrates its slice
one = jax.value_and_grad(loss)(P, y0, jax.local_devices())
two = jax.value_and_grad(loss)(P, y0, None)
close(one, multihost_utils.process_allgather(two, tiled=True))
# or only its slice, as global arrays: 4 states, 2 on each process
mesh = jax.sharding.Mesh(np.array(jax.devices()), ("b",))
batch = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("b"))
mine = slice(2 * jax.process_index(), 2 * jax.process_index() + 2)
sliced = tuple(jax.make_array_from_process_local_data(batch, np.asarray(y[mine])) for y in y0)
masses = jnp.ones((4, 2)).at[3, 1].set(jnp.nan)  # member 3: on the second process
chains = eqx.filter_vmap(lambda m: sm.chain_pendulum(m, P[2:]))(masses)
sol = sm.simulate_batch(chains, sliced, 0.5, batch_system=True, throw=False, **KW)
bad = multihost_utils.process_allgather(sol.result == sm.RESULTS.nonfinite_initial, tiled=True)
assert bad.tolist() == [False, False, False, True]
full = sm.simulate_batch(chains, tuple(y[:4] for y in y0), 0.5, batch_system=True,
                         throw=False, **KW)  # the whole batch on every process
close(*(multihost_utils.process_allgather(s.ys, tiled=True) for s in (sol, full)))
try:
    sm.simulate_batch(chains, sliced, 0.5, batch_system=True, **KW)
except RuntimeError as error:
    print("MESSAGE", error)
print("ok")
"""
)


FIT = (
    COMMON
    + """TS = jnp.linspace(0.0, 0.4, 9)
model = lambda m: sm.chain_pendulum(jnp.stack([1.0, m]), P[2:])
observe = lambda system, t, q, v: q
obs = sm.simulate_batch(model(P[1]), y0, TS[-1], saveat=diffrax.SaveAt(ts=TS),
                        devices=jax.local_devices()[:1], **KW).ys[0]
obs = obs + 1e-3 * jnp.sin(jnp.arange(obs.size)).reshape(obs.shape)  # "noise"


def fitted(devices):  # the second mass from 5 records of 2 segments: 10 solves over devices
    r = sm.fit(model, jnp.array(1.5), TS, obs, observe, y0=y0, segments=2, simulate_options=KW,
               devices=devices)
    assert r.converged and abs(r.params - P[1]) < 3 * r.stderr, (r.params, r.stderr)
    if devices is not None and len(devices) == 1:  # the run stays on that device
        assert r.jacobian.devices() == set(devices), r.jacobian.devices()
    return r.params, r.stderr, r.loss


if len(sys.argv) == 1:  # two devices of one process
    assert len(jax.devices()) == 2
    close(fitted(jax.devices()[1:]), fitted(None), 1e-9)
    try:
        sm.fit(model, jnp.array(1.5), TS, obs, observe, y0=y0, jac="bwd", simulate_options=KW)
    except ValueError as error:
        assert "jac='bwd' (reverse mode) fails through a solve split" in str(error)
    else:
        raise AssertionError("jac='bwd' was accepted on two devices")
else:  # across two processes
    assert len(jax.devices()) == 2 and len(jax.local_devices()) == 1
    close(fitted(jax.local_devices()), fitted(None), 1e-9)
print("ok")
"""
)


def _run(script, *argv, env=None):
    env = dict(os.environ, **(env or {}))
    cmd = [sys.executable, "-c", textwrap.dedent(script), *map(str, argv)]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _finish(proc, timeout=240):
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"timed out after {timeout} s: {err[-3000:]}")
    assert proc.returncode == 0, err[-3000:]
    assert out.strip().endswith("ok"), out[-3000:]
    return out


def test_gradient_through_a_batch_sharded_over_two_cpu_devices():
    _finish(_run(TWO_DEVICES, env=cpu_devices(2)))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def test_two_processes_on_localhost():
    port = _free_port()
    procs = [_run(TWO_PROCESSES, rank, port, env=cpu_devices(1)) for rank in (0, 1)]
    outs = [_finish(p) for p in procs]
    messages = [line for out in outs for line in out.splitlines() if line.startswith("MESSAGE")]
    assert len(messages) == 2 and messages[0] == messages[1]
    assert "1 of 4 trajectories failed (indices 3); trajectory 3:" in messages[0]
    assert "not finite at the initial state" in messages[0]


@pytest.mark.slow
def test_fit_split_over_two_devices_and_over_two_processes():
    _finish(_run(FIT, env=cpu_devices(2)), timeout=900)
    port = _free_port()
    for proc in [_run(FIT, rank, port, env=cpu_devices(1)) for rank in (0, 1)]:
        _finish(proc, timeout=900)
