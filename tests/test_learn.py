"""`sm.learn` and `sm.LearnedLagrangian`: a spherical pendulum's potential recovered from
simulated chunks (float64) with a checkpoint; float32 training (slow). The default-suite
test's time is mostly compilation (one solve of the data, one training step, one rollout)."""

import contextlib
import io

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree

import sphere_mech as sm

G_OVER_L = 9.81


def _chunks(num, times, dt, dtype=jnp.float64, seed=0):
    """`num` chunks of a spherical pendulum (`L = 1/2 |qdot|^2 - (g/l) q_z`)."""
    true = sm.ConstantInertiaLagrangian(jnp.eye(1), lambda t, q, a: G_OVER_L * q[0, 2])
    k1, k2 = jax.random.split(jax.random.PRNGKey(seed))
    q0 = sm.normalize(jax.random.normal(k1, (num, 1, 3), dtype))
    v0 = jnp.cross(2.0 * jax.random.normal(k2, (num, 1, 3), dtype), q0)
    ts = jnp.arange(times, dtype=dtype) * dt
    opts = dict(solver=sm.Projected(sm.RK4()), dt0=dt / 4, saveat=diffrax.SaveAt(ts=ts))
    return ts, sm.simulate_batch(true, (q0, v0), ts[-1], **opts).ys


SIM = dict(solver=sm.Projected(sm.RK4()), dt0=0.025)
TRAIN_SIM = dict(solver=sm.Projected(sm.RK4()), dt0=0.05)  # one step per observation


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    ts, states = _chunks(256 + 1, 21, 0.05)  # one solve: 256 chunks to learn from, one to check
    ts, states, held_out = ts[:6], [x[:256, :6] for x in states], (ts, [x[256] for x in states])
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=16, depth=2)
    path = tmp_path_factory.mktemp("learn") / "model.eqx"
    opts = dict(steps=400, batch_size=32, learning_rate=1e-2, simulate_options=TRAIN_SIM)
    with contextlib.redirect_stderr(io.StringIO()) as bar:  # the progress bar
        result = sm.learn(
            model, ts, states, checkpoint=path, checkpoint_every=100, progress=True, **opts
        )
    return model, result, path, held_out, (ts, states), bar.getvalue()


def _potential_error(model):
    """`U / M` against the true `(g / l) q_z` (both up to a constant), relative."""
    pts = sm.normalize(jax.random.normal(jax.random.PRNGKey(5), (64, 1, 3)))
    U = jax.vmap(lambda p: model.potential(0.0, p, None))(pts) / model.inertia(None)[0, 0]
    true = G_OVER_L * pts[:, 0, 2]
    return float(jnp.std((U - U.mean()) - (true - true.mean())) / jnp.std(true))


def test_learn_recovers_the_pendulum_potential(learned):
    model, result, path, (ts, (q, v)), _, bar = learned
    assert _potential_error(model) > 0.5  # the untrained model is far off
    assert _potential_error(result.model) < 0.03
    assert result.losses.shape == (400,) and result.losses[-1] < 1e-2 * result.losses[0]
    # the learned model is a library system: rolled out by sm.simulate
    sol = sm.simulate(result.model, (q[0], v[0]), ts[-1], saveat=diffrax.SaveAt(ts=ts), **SIM)
    assert float(jnp.max(jnp.abs(sol.ys[0] - q))) < 0.02
    # the checkpoint holds the trained model
    back = eqx.tree_deserialise_leaves(path, model)
    assert np.array_equal(back.inertia_factor, result.model.inertia_factor)
    # the progress bar (`progress=True`) reached the last step
    assert "learn: 100%" in bar and "400/400" in bar and "loss" in bar


def test_refine_improves_the_learned_potential(learned, capsys):
    """Gauss-Newton steps from `learn`'s model on the same chunks (groups of 96: the last
    of 3 padded): the least squares falls at each step from the one of a simulation
    written here, and the learned potential comes 3 times closer to the true one."""
    _, result, _, _, (ts, (q, v)), _ = learned
    refined = sm.refine(
        result.model,
        ts,
        (q, v),
        steps=3,
        group_size=96,
        simulate_options=TRAIN_SIM,
        progress=True,
        print_every=2,
    )
    out, err = capsys.readouterr()
    assert "refine: 100%" in err  # the bar, and a line every 2 steps and after the last
    assert [line.split()[2] for line in out.splitlines()] == ["2/3", "3/3"]
    sim = sm.simulate_batch(
        result.model, (q[:, 0], v[:, 0]), ts[-1], saveat=diffrax.SaveAt(ts=ts), **TRAIN_SIM
    )
    squares = [jnp.sum((x - y)[:, 1:] ** 2, (2, 3)) for x, y in zip(sim.ys, (q, v), strict=True)]
    assert refined.losses[0] == pytest.approx(float(jnp.mean(sum(squares))) / 6, rel=1e-9)
    assert refined.losses.shape == (4,) and np.all(np.diff(refined.losses) < 0)
    assert _potential_error(refined.model) < _potential_error(result.model) / 3


@pytest.mark.slow  # two more compilations: about 40 s
def test_refine_step_is_the_reweighted_gauss_newton_step():
    """One step of `refine` with a floor is the damped Gauss-Newton step of its reweighted
    least squares, here built from `jax.jacfwd` through `sm.simulate_batch` (forward
    mode, against `refine`'s reverse-mode Jacobians of its shooting residuals), with the
    weights `1 / (rms_c^2 + floor^2)` and Marquardt's damping (10 times the initial one for
    each rejected trial); 40 chunks in groups of 16 (the last one padded). Its losses are
    the mean of `log(rms_c^2 + floor^2)`."""
    ts, (q, v) = _chunks(40, 4, 0.05)
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=8, depth=1)
    floor, damping = 1e-3, 1e-2
    refined = sm.refine(
        model,
        ts,
        (q, v),
        steps=1,
        floor=floor,
        damping=damping,
        group_size=16,
        simulate_options=TRAIN_SIM,
    )
    # each rejected trial multiplies the damping by 10 (the untrained model: 4 of them)
    damping = damping * 10.0**refined.skipped
    params, rest = eqx.partition(model, eqx.is_inexact_array)
    p0, unravel = ravel_pytree(params)

    def residuals(p):
        sim = sm.simulate_batch(
            eqx.combine(unravel(p), rest),
            (q[:, 0], v[:, 0]),
            ts[-1],
            saveat=diffrax.SaveAt(ts=ts),
            adjoint=diffrax.ForwardMode(),
            **TRAIN_SIM,
        )
        r = [(x - y)[:, 1:].reshape(40, -1) for x, y in zip(sim.ys, (q, v), strict=True)]
        return jnp.concatenate(r, 1)

    r, J = residuals(p0), jax.jacfwd(residuals)(p0)
    spread = jnp.mean(r**2, -1) + floor**2
    A = jnp.einsum("c,crp,crs->ps", 1 / spread, J, J)
    g = jnp.einsum("c,crp,cr->p", 1 / spread, J, r)
    damped = A + jnp.diag(damping * jnp.diag(A) + 1e-12 * jnp.max(jnp.diag(A)))
    p1 = ravel_pytree(eqx.filter(refined.model, eqx.is_inexact_array))[0]
    np.testing.assert_allclose(p1 - p0, jnp.linalg.solve(damped, -g), rtol=1e-7, atol=1e-10)
    logs = [jnp.mean(jnp.log(jnp.mean(residuals(p) ** 2, -1) + floor**2)) for p in (p0, p1)]
    np.testing.assert_allclose(refined.losses, logs, rtol=1e-10)
    assert refined.losses[1] < refined.losses[0]


@pytest.mark.slow  # one more compilation (float32): about 30 s
def test_refine_float32():
    """`refine` of a float32 model: its Jacobians in float32, their sums in float64; the
    model stays float32 and the least squares falls at each step."""
    ts, states = _chunks(64, 4, 0.05, dtype=jnp.float32)
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=8, depth=1, dtype="float32")
    result = sm.refine(model, ts, states, steps=3, simulate_options=TRAIN_SIM)
    assert result.model.inertia_factor.dtype == jnp.float32
    assert np.all(np.isfinite(result.losses)) and np.all(np.diff(result.losses) < 0)


@pytest.mark.slow  # a second compilation (float32): about 40 s
def test_learn_float32(tmp_path):
    ts, states = _chunks(64, 4, 0.05, dtype=jnp.float32)
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=8, depth=1, dtype="float32")
    path = tmp_path / "model.eqx"
    sim = dict(solver=sm.Projected(sm.RK4()), dt0=0.05)
    result = sm.learn(
        model,
        ts,
        states,
        steps=30,
        batch_size=32,
        simulate_options=sim,
        learning_rate=1e-2,
        checkpoint=path,
        checkpoint_every=10,
    )
    assert result.model.inertia_factor.dtype == jnp.float32
    assert np.all(np.isfinite(result.losses)) and result.losses[-1] < result.losses[0]
    back = eqx.tree_deserialise_leaves(path, model)
    assert np.array_equal(back.inertia_factor, result.model.inertia_factor)


@pytest.mark.slow  # two more compilations: about 40 s
def test_learn_per_chunk_times_match_shared_times():
    """Chunks given their own times `(B, T)` (each shifted by its own offset: the system is
    autonomous) train as with the times shared `(T,)`, whose time stepping is not batched:
    the same losses and model. Step and offsets are binary fractions, so that each chunk's
    step times are exact and both runs take the same steps."""
    dt = 1 / 16
    ts, states = _chunks(64, 4, dt)
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=8, depth=1)
    sim = dict(solver=sm.Projected(sm.RK4()), dt0=dt)
    opts = dict(steps=4, batch_size=16, learning_rate=1e-2, simulate_options=sim)
    shared = sm.learn(model, ts, states, **opts)
    own = sm.learn(model, ts + 0.25 * jnp.arange(64)[:, None], states, **opts)
    assert np.all(np.diff(shared.losses) != 0)
    np.testing.assert_allclose(own.losses, shared.losses, rtol=1e-12)
    leaves = lambda m: jax.tree.leaves(eqx.filter(m, eqx.is_inexact_array))
    for a, b in zip(leaves(own.model), leaves(shared.model), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


@pytest.mark.slow  # two more compilations: about 30 s
def test_learn_blocks_match_single_steps(capsys):
    """The steps run in compiled blocks (here 6, one per progress line) or one at a time
    (`print_every=1`): the same minibatches in the same order, so the same losses; the
    minibatches cycle through epochs (64 chunks, batches of 24: 2 per epoch)."""
    ts, states = _chunks(64, 4, 0.05)
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=8, depth=1)
    opts = dict(steps=12, batch_size=24, learning_rate=1e-2, simulate_options=TRAIN_SIM)
    blocks = sm.learn(model, ts, states, print_every=6, **opts)
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[2] for line in lines] == ["6/12", "12/12"]
    single = sm.learn(model, ts, states, print_every=1, **opts)
    assert len(capsys.readouterr().out.splitlines()) == 12
    assert np.all(np.diff(blocks.losses) != 0)
    np.testing.assert_allclose(blocks.losses, single.losses, rtol=1e-10)


@pytest.mark.slow  # one more compilation: about 25 s
def test_learn_skips_steps_whose_loss_is_not_finite():
    """One chunk starts 1e150 times too fast, so the model's solve of it overflows: every
    minibatch holding it (one of 4 per epoch) has a non-finite loss and gradient; those
    steps are skipped and counted, the others train, and the model stays finite (an
    update with them would make every parameter NaN)."""
    ts, (q, v) = _chunks(64, 4, 0.05)
    v = v.at[5].multiply(1e150)
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=8, depth=1)
    opts = dict(steps=8, batch_size=16, learning_rate=1e-2, simulate_options=TRAIN_SIM)
    result = sm.learn(model, ts, (q, v), **opts)
    assert result.skipped == 2 and int(np.sum(~np.isfinite(result.losses))) == 2
    leaves = lambda m: jax.tree.leaves(eqx.filter(m, eqx.is_inexact_array))
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in leaves(result.model))
    trained = leaves(result.model)[0]
    assert not np.array_equal(trained, leaves(model)[0])


def test_learn_skips_updates_that_are_not_finite():
    """Adam without its epsilon divides the MLP's output bias's update by zero (a constant
    in `U` does not move anything: its gradient is exactly zero): every such step is
    skipped and counted, and the model stays the given one, finite."""
    ts, states = _chunks(8, 3, 0.05)
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=4, depth=1)
    opts = dict(steps=3, batch_size=8, simulate_options=TRAIN_SIM)
    result = sm.learn(model, ts, states, optimizer=optax.adam(1e-2, eps=0.0), **opts)
    assert result.skipped == 3 and np.all(np.isfinite(result.losses))
    same = lambda a, b: np.array_equal(ravel_pytree(a)[0], ravel_pytree(b)[0])
    assert same(
        eqx.filter(result.model, eqx.is_inexact_array), eqx.filter(model, eqx.is_inexact_array)
    )


def test_refine_refuses_chunks_whose_simulation_is_not_finite():
    """A chunk started 1e150 times too fast overflows the model's solve: `refine` names it
    instead of returning the model unchanged with a NaN objective."""
    ts, (q, v) = _chunks(8, 3, 0.05)
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=4, depth=1)
    message = r"^refine: 1 of 8 chunks have non-finite residuals \(indices 5\); chunk 5: "
    with pytest.raises(ValueError, match=message + "the model's simulation"):
        sm.refine(model, ts, (q, v.at[5].multiply(1e150)), simulate_options=TRAIN_SIM)


def test_default_training_solver_with_only_dt0_given():
    """`simulate_options` with only `dt0` keeps the documented default solver, fixed steps
    of `Projected(RK4())` (not `simulate`'s adaptive default); without `dt0`, the first
    observation spacing."""
    from sphere_mech._fit.learn import _default_sim

    ts = jnp.stack([jnp.arange(3) * 0.05, jnp.arange(3) * 0.04])
    for given, dt0 in (({"dt0": 0.025}, 0.025), ({}, 0.04)):
        sim = _default_sim(ts, given, "learn")
        assert type(sim["solver"]) is sm.Projected and type(sim["solver"].solver) is sm.RK4
        assert sim["dt0"] == pytest.approx(dt0)


def _axial_invariants(q):
    """`(x^2 + y^2, z)` of the one unit vector: invariant under rotations about z."""
    return jnp.stack([q[0, 0] ** 2 + q[0, 1] ** 2, q[0, 2]])


def test_learned_lagrangian_features_give_their_symmetry():
    """With `features` the MLP reads them (here 2 axial invariants), so the potential has
    their symmetry exactly; the default model (3 coordinates) does not."""
    key = jax.random.PRNGKey(1)
    axial = sm.LearnedLagrangian(1, key=key, width=8, depth=2, features=_axial_invariants)
    plain = sm.LearnedLagrangian(1, key=key, width=8, depth=2)
    assert axial.potential_net.in_size == 2 and plain.potential_net.in_size == 3
    q = sm.normalize(jax.random.normal(jax.random.PRNGKey(2), (16, 1, 3)))
    angle = jax.random.uniform(jax.random.PRNGKey(3), (16, 1), maxval=2 * np.pi)
    c, s, (x, y, z) = jnp.cos(angle), jnp.sin(angle), jnp.moveaxis(q, -1, 0)
    turned = jnp.stack([c * x - s * y, s * x + c * y, z], -1)  # about z
    U = lambda m, p: jax.vmap(lambda x: m.potential(0.0, x, None))(p)
    np.testing.assert_allclose(U(axial, turned), U(axial, q), rtol=1e-12, atol=1e-14)
    assert float(jnp.max(jnp.abs(U(plain, turned) - U(plain, q)))) > 1e-3
    with pytest.raises(ValueError, match="features must return a 1-D array"):
        sm.LearnedLagrangian(1, key=key, features=lambda q: q)


def test_learn_rejects_bad_input(tmp_path):
    ts = jnp.arange(3) * 0.05
    q = sm.normalize(jax.random.normal(jax.random.PRNGKey(0), (4, 3, 1, 3)))
    states = (q, jnp.zeros_like(q))
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=4, depth=1)
    with pytest.raises(ValueError, match="ts must have shape"):
        sm.learn(model, ts[:2], states, steps=1)
    one = r"states must have two leading axes \(B, T\).*\(3, 1, 3\) have 1 \(\(3,\)\)"
    for fit in (sm.learn, sm.refine, sm.fit_accelerations):  # one chunk, its axis left off
        with pytest.raises(ValueError, match=one):
            fit(model, ts, jax.tree.map(lambda x: x[0], states))
    with pytest.raises(ValueError, match="may not set 'adjoint'"):
        sm.learn(model, ts, states, steps=1, simulate_options={"adjoint": None})
    with pytest.raises(ValueError, match=r"^dt0 must have the sign of t1 - t0"):  # untraced
        sm.learn(model, ts, states, steps=1, simulate_options={"dt0": -0.01})
    for floor in (0.0, np.inf):
        with pytest.raises(ValueError, match="refine: floor must be a finite number > 0"):
            sm.refine(model, ts, states, floor=floor)
    for damping in (-1.0, np.inf):
        with pytest.raises(ValueError, match="refine: damping must be a finite number > 0"):
            sm.refine(model, ts, states, damping=damping)
    with pytest.raises(ValueError, match="refine: steps must be a positive integer, got 0"):
        sm.refine(model, ts, states, steps=0)
    with pytest.raises(ValueError, match="learn: steps must be a positive integer, got 2.5"):
        sm.learn(model, ts, states, steps=2.5)
    with pytest.raises(ValueError, match="learn: checkpoint_every must be a positive integer"):
        sm.learn(model, ts, states, steps=1, checkpoint_every=-1)
    # before any training, not at the first write
    missing = tmp_path / "missing" / "model.eqx"
    with pytest.raises(ValueError, match="learn: checkpoint .* folder that does not exist"):
        sm.learn(model, ts, states, steps=1, checkpoint=missing)
    with pytest.raises(ValueError, match="refine: checkpoint .* folder that does not exist"):
        sm.refine(model, ts, states, checkpoint=missing)
    with pytest.raises(ValueError, match=r"loss\(r\) must return a scalar \(r: \(4, 1, 3, 6\)\)"):
        sm.learn(model, ts, states, steps=1, loss=lambda r: r)
    with pytest.raises(ValueError, match="may not set 'adjoint'"):
        sm.refine(model, ts, states, simulate_options={"adjoint": None})
    with pytest.raises(ValueError, match="inertia must have shape"):
        sm.LearnedLagrangian(2, key=jax.random.PRNGKey(1), inertia=jnp.eye(1))
    # the inertia checked as ConstantInertiaLagrangian checks it (the same words)
    for inertia in (-jnp.eye(1), jnp.full((1, 1), jnp.nan), jnp.array([[1.0, 0.5], [0, 1]])):
        n = inertia.shape[0]
        with pytest.raises(ValueError, match="inertia must be a symmetric positive-definite"):
            sm.LearnedLagrangian(n, key=jax.random.PRNGKey(1), inertia=inertia)
        with pytest.raises(ValueError, match="inertia must be a symmetric positive-definite"):
            sm.ConstantInertiaLagrangian(inertia, lambda t, q, a: 0.0)
    with pytest.raises(ValueError, match="width must be a positive integer, got 0"):
        sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), width=0)
    # the chunks, before any solve: their first states as simulate_batch checks initial
    # states (the same words), every observation finite, the model's number of links
    bad = (q.at[2, 0].multiply(2.0), states[1])
    message = r"^learn: 1 of 4 initial states are invalid \(indices 2\); initial state 2: "
    with pytest.raises(ValueError, match=message + "q is not on the spheres"):
        sm.learn(model, ts, bad, steps=1)
    with pytest.raises(ValueError, match=message.replace("learn", "refine")):
        sm.refine(model, ts, bad)
    nan = (q.at[1, 2, 0, 1].set(jnp.nan), states[1])
    message = r"^learn: 1 of 4 chunks have a non-finite observation \(indices 1\); chunk 1: "
    with pytest.raises(ValueError, match=message + "observation 2 is NaN or infinite"):
        sm.learn(model, ts, nan, steps=1)
    two = sm.LearnedLagrangian(2, key=jax.random.PRNGKey(1), width=4, depth=1)
    with pytest.raises(ValueError, match=r"the state has 1 spheres but the system has 2"):
        sm.learn(two, ts, states, steps=1)
    with pytest.raises(ValueError, match=r"the state has 1 spheres but the system has 2"):
        sm.simulate(two, (q[0, 0], states[1][0, 0]), 0.1)
    with pytest.raises(ValueError, match="same leading axes"):
        sm.learn(model, ts, (q, states[1][:, :2]), steps=1)
    with pytest.raises(ValueError, match=r"^states must be a pair \(q, v\)"):
        sm.learn(model, ts, (q, *states), steps=1)
    # the times: finite and strictly increasing, shared or each chunk's own (named)
    with pytest.raises(ValueError, match=r"^learn: ts must be finite and strictly increasing"):
        sm.learn(model, ts[::-1], states, steps=1)
    rows = jnp.stack([ts, ts, ts.at[2].set(0.0), ts])
    message = r"^refine: 1 of 4 chunks have times that are not finite and increasing \(indices 2\)"
    with pytest.raises(ValueError, match=message):
        sm.refine(model, rows, states)
    # the options of the default optimizer and the minibatches
    with pytest.raises(ValueError, match="learn: learning_rate must be a finite number > 0"):
        sm.learn(model, ts, states, steps=1, learning_rate=jnp.nan)
    with pytest.raises(ValueError, match="learn: seed must be an integer >= 0, got -1"):
        sm.learn(model, ts, states, steps=1, seed=-1)
    with pytest.raises(ValueError, match="input_scale must be a finite number > 0, got inf"):
        sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), input_scale=np.inf)
    with pytest.raises(ValueError, match="input_scale must be a finite number > 0, got Array"):
        sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), input_scale=jnp.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="dtype must be a floating dtype JAX runs in, got int32"):
        sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), dtype="int32")
    with jax.enable_x64(False), pytest.raises(ValueError, match="float64 needs jax_enable_x64"):
        sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), dtype="float64")  # was float32
    with pytest.raises(TypeError, match="learn: optimizer must be an optax GradientTransf"):
        sm.learn(model, ts, states, steps=1, optimizer="adam")
    # a checkpoint that is a folder (written as it is, or with `.eqx` appended)
    (tmp_path / "out.eqx").mkdir()
    for folder in (tmp_path, tmp_path / "out"):
        with pytest.raises(ValueError, match="learn: checkpoint .* is a folder, not a file path"):
            sm.learn(model, ts, states, steps=1, checkpoint=folder)


def test_estimate_accelerations_on_great_circles():
    """Uniform motion on great circles (two spheres, `qddot = -w^2 q` exactly): the Hermite
    estimates at the interior observations to 1e-9 relative, with weights near 1; a chunk
    whose last observation is off by 1e-3 gets small weights, the others keep theirs."""
    rng = np.random.default_rng(0)
    num, T, dt = 8, 5, 0.05
    ts = np.arange(T) * dt
    axes = np.linalg.qr(rng.standard_normal((num, 2, 3, 3)))[0]  # per chunk and sphere
    w = rng.uniform(0.5, 6.0, (num, 2))
    angle = w[..., None] * ts  # (num, 2, T)
    e1, e2 = axes[..., 0], axes[..., 1]  # (num, 2, 3)
    q = np.cos(angle)[..., None] * e1[:, :, None] + np.sin(angle)[..., None] * e2[:, :, None]
    qdot = w[..., None, None] * (
        -np.sin(angle)[..., None] * e1[:, :, None] + np.cos(angle)[..., None] * e2[:, :, None]
    )
    q, qdot = q.transpose(0, 2, 1, 3), qdot.transpose(0, 2, 1, 3)  # (num, T, 2, 3)
    acc, weights = sm.estimate_accelerations(ts, (q, qdot))
    exact = -(w[:, None, :, None] ** 2) * q[:, 1:-1]
    assert acc.shape == (num, T - 2, 2, 3) and weights.shape == (num, T - 2)
    assert float(jnp.max(jnp.abs(acc - exact))) < 1e-9 * float(np.max(np.abs(exact)))
    assert float(jnp.min(weights)) > 0.99
    q_bad = q.copy()
    q_bad[3, -1] += 1e-3
    _, weights = sm.estimate_accelerations(ts, (q_bad, qdot))
    assert float(jnp.max(weights[3])) < 0.1
    assert float(jnp.min(np.delete(np.asarray(weights), 3, axis=0))) > 0.99
    with pytest.raises(ValueError, match="T >= 3 observations"):
        sm.estimate_accelerations(ts[:2], (q[:, :2], qdot[:, :2]))


KERNELS = sm.SphereKernels(levels=((40, 1.4, 180.0), (160, 1.15, 60.0)))


def test_sphere_kernels():
    """Each kernel is 1 at the point of the sphere nearest its source and `((rho - 1) /
    |x - rho u|)^power` anywhere (also off the sphere), per link; bad levels are refused."""
    units, radii = KERNELS.centers()
    cosines = units @ np.array([0.0, 0.0, -1.0])
    assert len(units) == 40 + int(np.sum(sm._fit.learn._fibonacci(160) @ [0, 0, -1] >= 0.5))
    assert np.all(cosines[40:] >= 0.5 - 1e-12) and np.allclose(np.linalg.norm(units, axis=1), 1)
    assert np.allclose(np.diag(np.asarray(jax.vmap(lambda u: KERNELS(u[None]))(units))), 1.0)
    x = np.array([[0.3, -0.2, -1.1], [0.0, 0.9, 0.1]])  # two links, off the sphere
    expected = ((radii - 1) / np.linalg.norm(x[:, None] - radii[:, None] * units, axis=-1)) ** 3
    np.testing.assert_allclose(KERNELS(jnp.asarray(x)), expected.reshape(-1), rtol=1e-12)
    for levels, words in (
        (((10, 1.0, 90.0),), "rho must be > 1"),
        (((0, 1.2, 90.0),), "count must be a positive integer"),
        (((10, 1.2),), r"each level is \(count, rho, cap\)"),
    ):
        with pytest.raises(ValueError, match=words):
            sm.SphereKernels(levels=levels)
    with pytest.raises(ValueError, match="axis must be a nonzero 3-vector"):
        sm.SphereKernels(axis=(0.0, 0.0, 0.0))


def test_fit_accelerations_recovers_a_kernel_potential():
    """A potential in the span of the kernels (with gravity), observed in 64 chunks of 5
    states: one step of `fit_accelerations` from the zero model recovers its force (the
    tangential gradient) at held-out points to 1e-4 of its size, without any solve."""
    kernels = sm.SphereKernels(levels=((60, 1.3, 180.0),))
    true = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(0), depth=0, features=kernels)
    weights = 0.3 * jax.random.normal(
        jax.random.PRNGKey(1), true.potential_net.layers[0].weight.shape
    )
    true = eqx.tree_at(
        lambda m: (m.potential_net.layers[0].weight, m.potential_linear),
        true,
        (weights, jnp.array([[0.0, 0.0, G_OVER_L]])),
    )
    k1, k2 = jax.random.split(jax.random.PRNGKey(2))
    q0 = sm.normalize(jnp.array([0.0, 0.0, -1.0]) + 0.4 * jax.random.normal(k1, (64, 1, 3)))
    v0 = sm.project(q0, 1.5 * jax.random.normal(k2, (64, 1, 3)))
    ts = jnp.arange(5) * 0.05
    opts = dict(rtol=1e-11, atol=1e-12, saveat=diffrax.SaveAt(ts=ts))
    states = sm.simulate_batch(true, (q0, v0), ts[-1], **opts).ys
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(3), depth=0, features=kernels)
    assert float(jnp.abs(model.potential(0.0, q0[0], None))) == 0.0  # depth 0 starts at zero
    result = sm.fit_accelerations(model, ts, states)
    assert result.losses.shape == (2,) and result.losses[1] < 1e-8 * result.losses[0]

    def forces(m, q):
        return jax.vmap(lambda x: sm.project(x, jax.grad(lambda y: m.potential(0.0, y, None))(x)))(
            q
        )

    held = sm.normalize(jnp.array([0.0, 0.0, -1.0]) + 0.3 * jax.random.normal(k2, (32, 1, 3)))
    true_f, fitted_f = forces(true, held), forces(result.model, held)
    # measured: 2e-5 of it (the accelerations are estimated to about 1e-5)
    assert float(jnp.max(jnp.abs(fitted_f - true_f))) < 1e-4 * float(jnp.max(jnp.abs(true_f)))
    np.testing.assert_array_equal(result.model.inertia(None), model.inertia(None))  # held


def test_fit_accelerations_rejects_bad_input():
    ts = jnp.arange(3) * 0.05
    q = sm.normalize(jax.random.normal(jax.random.PRNGKey(0), (4, 3, 1, 3)))
    states = (q, jnp.zeros_like(q))
    model = sm.LearnedLagrangian(1, key=jax.random.PRNGKey(1), depth=0, features=KERNELS)
    with pytest.raises(ValueError, match=r"ts must have shape \(T,\) or \(B, T\) with T >= 3"):
        sm.fit_accelerations(model, ts[:2], (q[:, :2], q[:, :2] * 0))
    for ridge in (0.0, np.nan):
        with pytest.raises(ValueError, match="fit_accelerations: ridge must be a finite number"):
            sm.fit_accelerations(model, ts, states, ridge=ridge)
    with pytest.raises(ValueError, match="fit_accelerations: steps must be a positive integer"):
        sm.fit_accelerations(model, ts, states, steps=0)
    hamiltonian = sm.Hamiltonian(lambda t, q, p, a: 0.5 * jnp.sum(p**2) + q[0, 2])
    with pytest.raises(ValueError, match=r"state \(q, qdot\) \(form 1\).*Hamiltonian"):
        sm.fit_accelerations(hamiltonian, ts, states)
    with pytest.raises(ValueError, match="fit_accelerations: inertia must be True or False, got 1"):
        sm.fit_accelerations(model, ts, states, inertia=1)
    chain = sm.chain_pendulum(jnp.ones(1), jnp.ones(1))
    with pytest.raises(
        ValueError, match="inertia=True fits a LearnedLagrangian's inertia, got Scene"
    ):
        sm.fit_accelerations(chain, ts, states, inertia=True)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_fit_accelerations_recovers_an_unknown_inertia(dtype):
    """A 2-link chain (unequal masses and lengths) observed in 48 chunks of 5 states: with
    `inertia=True` Levenberg-Marquardt steps (at the default initial damping for it,
    1e-3) from the identity inertia and zero potential
    recover the chain's inertia up to the common factor (`M / M_00`) and the gravity term
    of its potential in the same units, to 1e-4, in float64 and in float32 (measured: 2e-8
    and 9e-7; before the damped step's floor scaled with the dtype, the float32 fit moved
    the second link's inertia, which the accelerations at the identity do not see, by 550
    and diverged: `M / M_00` off by 1e3)."""
    masses, lengths = jnp.array([1.3, 0.7]), jnp.array([0.8, 1.2])
    chain = sm.chain_pendulum(masses, lengths, 1.0)
    k1, k2 = jax.random.split(jax.random.PRNGKey(4))
    q0 = sm.normalize(jnp.array([0.0, 0.0, -1.0]) + 0.6 * jax.random.normal(k1, (48, 2, 3)))
    v0 = sm.project(q0, jax.random.normal(k2, (48, 2, 3)))
    ts = jnp.arange(5) * 0.05
    opts = dict(rtol=1e-11, atol=1e-12, saveat=diffrax.SaveAt(ts=ts))
    states = sm.simulate_batch(chain, (q0, v0), ts[-1], **opts).ys
    no_features = lambda q: jnp.zeros(1, q.dtype)  # the potential: the linear term alone
    model = sm.LearnedLagrangian(
        2, key=jax.random.PRNGKey(5), depth=0, features=no_features, dtype=dtype
    )
    result = sm.fit_accelerations(model, ts, states, steps=20, inertia=True)
    assert result.model.inertia_factor.dtype == dtype
    assert result.losses[-1] < 1e-6 * result.losses[0]
    M, fitted = chain.inertia(None), result.model.inertia(None)
    np.testing.assert_allclose(fitted / fitted[0, 0], M / M[0, 0], rtol=1e-4)
    # gravity (g = 1): U = sum_i l_i (m_i + ... + m_n) q_i . e3, in units of M_00
    weights = lengths * jnp.cumsum(masses[::-1])[::-1] / M[0, 0]
    linear = result.model.potential_linear / fitted[0, 0]
    np.testing.assert_allclose(linear[:, 2], weights, rtol=1e-4)
    assert float(jnp.max(jnp.abs(linear[:, :2]))) < 1e-4 * float(weights[0])
    held = result.model.inertia_factor[0, 0]  # the common factor, held
    assert float(held) == float(model.inertia_factor[0, 0])
