"""Derivatives of `simulate` and `simulate_batch` with the default adjoint (`adjoint=None`):
against central finite differences, the checkpointed reverse-mode adjoint (the old
default) and forward mode (`diffrax.ForwardMode`); and the adjoint it picks, with the
memory that costs."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest
from helpers import central_differences

import sphere_mech as sm
from sphere_mech._adjoint import (
    BATCH_FORWARD_COLUMNS,
    FORWARD_COLUMNS,
    default_adjoint,
    stagewise_reverse,
)
from sphere_mech._linalg import (
    DENSE_UNROLL_MAX,
    DenseLU,
    dense_solve,
    spd_solve,
    tridiagonal_spd_solve,
)

N, T1 = 2, 0.3
LENGTHS = jnp.array([1.0, 0.7])
GRADIENT_RUNS = {  # the solver options of the differentiated runs, by kind of steps
    "fixed": dict(solver=sm.Projected(sm.RK4()), dt0=0.01),
    "adaptive": dict(solver=sm.Projected(diffrax.Tsit5()), rtol=1e-10, atol=1e-12),
}
WEIGHTS = jnp.array([1.0, 2.0, 3.0])


def _states(batch=3):
    keys = jax.random.split(jax.random.PRNGKey(1), batch)
    return jax.vmap(lambda k: sm.random_state(k, N, speed=0.5))(keys)


def _loss(batch, kind, adjoint, **kw):
    """A weighted sum of the final states, as a function of the chain's lengths."""
    q, v = _states()

    def loss(lengths):
        chain = sm.chain_pendulum(jnp.ones(N), lengths, 9.81)
        opts = dict(adjoint=adjoint, **GRADIENT_RUNS[kind], **kw)
        if batch:
            q1 = sm.simulate_batch(chain, (q, v), T1, **opts).ys[0][:, -1]
        else:
            q1 = sm.simulate(chain, (q[0], v[0]), T1, **opts).ys[0][-1]
        return jnp.sum(q1 @ WEIGHTS)

    return loss


def _compiled_value_and_grad(max_steps):
    loss = _loss(False, "fixed", None, max_steps=max_steps)
    return jax.jit(jax.value_and_grad(loss)).lower(LENGTHS).compile()


@pytest.fixture(scope="module")
def value_and_grad_default():
    """`value_and_grad` of the loss of `simulate` with the default options, compiled."""
    return _compiled_value_and_grad(100_000)


def test_default_gradient_matches_differences_and_old_adjoint(value_and_grad_default):
    loss = _loss(False, "fixed", None)
    value, grad = value_and_grad_default(LENGTHS)
    old = _loss(False, "fixed", diffrax.RecursiveCheckpointAdjoint())
    value_old, grad_old = eqx.filter_jit(jax.value_and_grad(old))(LENGTHS)
    assert value == pytest.approx(float(value_old), rel=1e-13)
    np.testing.assert_allclose(grad, grad_old, rtol=1e-10, atol=1e-12)
    fd = central_differences(eqx.filter_jit(loss), LENGTHS)
    np.testing.assert_allclose(grad, fd, rtol=1e-7, atol=1e-9)
    assert np.all(np.abs(grad) > 1e-2)  # a gradient that could be wrong


def test_second_derivatives_forward_over_reverse(value_and_grad_default):
    """`jax.hessian` (forward mode over the default adjoint's reverse mode) against
    central differences of the compiled gradient; reverse over reverse is refused by JAX
    (diffrax's loops have no reverse mode of their reverse mode), as documented."""
    loss = _loss(False, "fixed", None)
    hessian = eqx.filter_jit(jax.hessian(loss))(LENGTHS)
    fd = central_differences(lambda x: value_and_grad_default(x)[1], LENGTHS)
    np.testing.assert_allclose(hessian, fd, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(hessian, hessian.T, rtol=1e-10)
    assert np.all(np.abs(np.diag(hessian)) > 1e-2)  # a Hessian that could be wrong
    with pytest.raises(ValueError, match="Reverse-mode differentiation does not work"):
        jax.grad(lambda x: jax.grad(loss)(x)[0])(LENGTHS)


@pytest.mark.parametrize(
    ("batch", "kind"),
    [(True, "fixed"), (False, "adaptive")],
    ids=["simulate_batch-fixed", "simulate-adaptive"],
)
def test_default_gradient_matches_forward_mode_and_differences(batch, kind):
    loss = _loss(batch, kind, None)
    grad = eqx.filter_jit(jax.grad(loss))(LENGTHS)
    forward = eqx.filter_jit(jax.jacfwd(_loss(batch, kind, diffrax.ForwardMode())))(LENGTHS)
    np.testing.assert_allclose(grad, forward, rtol=1e-12, atol=1e-13)
    fd = central_differences(eqx.filter_jit(loss), LENGTHS)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-8)
    assert np.all(np.abs(grad) > 1e-2)  # a gradient that could be wrong


def test_many_columns_reverse_mode_matches_forward_mode():
    """More than `FORWARD_COLUMNS` differentiated scalars (each trajectory's initial
    state: 12) go through checkpointed reverse mode, here under `simulate_batch`'s
    `vmap`; against diffrax's forward mode."""
    y0 = _states(2)
    chain = sm.chain_pendulum(jnp.ones(N), LENGTHS, 9.81)

    def final(y0, adjoint):
        sol = sm.simulate_batch(chain, y0, T1, adjoint=adjoint, **GRADIENT_RUNS["fixed"])
        return jnp.sum(sol.ys[0][:, -1] @ WEIGHTS) + jnp.sum(sol.ys[1][:, -1] ** 2)

    rev = eqx.filter_jit(jax.grad(lambda y: final(y, None)))(y0)
    fwd = eqx.filter_jit(jax.jacfwd(lambda y: final(y, diffrax.ForwardMode())))(y0)
    for a, b in zip(rev, fwd, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize(
    "batch", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["simulate", "simulate_batch"]
)
def test_between_the_thresholds(batch):
    """Four differentiated scalars (two masses, two lengths): forward mode for one
    trajectory (at most `FORWARD_COLUMNS`), reverse mode for a trajectory of a batch
    (more than `BATCH_FORWARD_COLUMNS`; slow: the same path as
    `test_many_columns_reverse_mode_matches_forward_mode`); against central differences."""
    q, v = _states()

    def loss(x):
        chain = sm.chain_pendulum(x[:N], x[N:], 9.81)
        opts = dict(adjoint=None, **GRADIENT_RUNS["fixed"])
        if batch:
            return jnp.sum(sm.simulate_batch(chain, (q, v), T1, **opts).ys[0][:, -1] @ WEIGHTS)
        return jnp.sum(sm.simulate(chain, (q[0], v[0]), T1, **opts).ys[0][-1] @ WEIGHTS)

    x = jnp.concatenate([jnp.array([1.0, 1.5]), LENGTHS])
    grad = eqx.filter_jit(jax.grad(loss))(x)
    fd = central_differences(eqx.filter_jit(loss), x)
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-8)
    assert np.all(np.abs(grad) > 1e-3)  # a gradient that could be wrong


@pytest.mark.parametrize("columns", [1, FORWARD_COLUMNS], ids=["forward", "reverse"])
def test_closed_over_values_and_save_times(columns):
    """The default adjoint differentiates through a parameter that `L`, the forces and an
    event's condition close over, and through a save time (before: a CustomVJPException
    and equinox's "Unexpected tangent"), in forward mode (2 scalars) and reverse mode (9):
    equal to the same parameter passed in `args` through diffrax's checkpointed adjoint,
    and, for the save time, to central differences."""
    q, v = _states()
    lengths = jnp.linspace(1.0, 1.4, columns)

    def loss(x, closed, adjoint=None):
        k, time = x[:-1], x[-1]
        gravity = lambda args: 9.81 * jnp.mean(args if closed is None else closed)
        L = lambda t, q, qdot, args: 0.5 * jnp.sum(qdot**2) - gravity(args) * jnp.sum(q[:, 2])
        forces = lambda t, q, qdot, args: -0.1 * gravity(args) * qdot
        # Never fires (z <= 1), but its condition reads the parameter.
        event = diffrax.Event(lambda t, y, args, **kw: 2.0 + gravity(args) - y[0][0, 2])
        sol = sm.simulate(
            sm.Lagrangian(L, forces=forces),
            (q[0], v[0]),
            T1,
            args=k if closed is None else None,
            saveat=diffrax.SaveAt(ts=jnp.stack([0.1, time])),
            event=event,
            adjoint=adjoint,
            **GRADIENT_RUNS["fixed"],
        )
        assert sol.ts.shape == (2,)
        return jnp.sum(sol.ys[0][-1] @ WEIGHTS) + jnp.sum(sol.ys[1][-1] ** 2)

    x = jnp.append(lengths, 0.205)  # between two steps: the dense output is smooth there
    grad = eqx.filter_jit(jax.grad(lambda x: loss(x, x[:-1])))(x)
    checkpointed = diffrax.RecursiveCheckpointAdjoint()
    reference = eqx.filter_jit(jax.grad(lambda x: loss(x, None, checkpointed)))(x)
    np.testing.assert_allclose(grad, reference, rtol=1e-11, atol=1e-13)
    fd = central_differences(eqx.filter_jit(lambda x: loss(x, None)), x)
    np.testing.assert_allclose(grad[-1], fd[-1], rtol=1e-6)
    assert np.all(np.abs(grad) > 1e-3)  # a gradient that could be wrong


def test_choice_and_memory_of_the_default_adjoint(value_and_grad_default):
    """Forward mode (a Jacobian, no checkpoints) up to `FORWARD_COLUMNS` scalars, else
    `RecursiveCheckpointAdjoint` with diffrax's `sqrt(2 max_steps)` checkpoints (as
    documented in `sphere_mech._solve`); the gradient's working memory with respect to
    two lengths does not grow with `max_steps` (447 checkpoints at 100 000 against 14
    at 100 would)."""
    assert BATCH_FORWARD_COLUMNS < 4 <= FORWARD_COLUMNS  # test_between_the_thresholds
    assert isinstance(default_adjoint(FORWARD_COLUMNS), diffrax.ForwardMode)
    assert isinstance(default_adjoint(BATCH_FORWARD_COLUMNS, True), diffrax.ForwardMode)
    batched = default_adjoint(BATCH_FORWARD_COLUMNS + 1, True)
    assert isinstance(batched, diffrax.RecursiveCheckpointAdjoint)
    reverse = default_adjoint(FORWARD_COLUMNS + 1)
    assert isinstance(reverse, diffrax.RecursiveCheckpointAdjoint)
    assert reverse.checkpoints is None  # diffrax's choice from max_steps
    temp = lambda compiled: compiled.memory_analysis().temp_size_in_bytes
    assert temp(value_and_grad_default) == temp(_compiled_value_and_grad(100))


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_stagewise_step_matches_the_step_transposed_whole(dtype):
    """`RK4(stagewise_reverse=True)`: the same step, and the same reverse-mode derivatives
    of its end state and its slopes (the Hermite output's `k`) with respect to the
    state, the times and the system, as JAX's transpose of the whole step. The steps agree
    to a few units in the last place, not bitwise: the vector field is its own compiled
    program (`vector_field`'s `jax.jit`), and eagerly the sums around it are rounded in
    another order inside the custom rule (5 ulps apart in float32 at most seen)."""
    y0 = jax.tree.map(lambda x: x[0].astype(dtype), _states(1))

    def step(stagewise, t0, t1, y0, lengths):
        term = sm.MechanicsTerm(sm.chain_pendulum(jnp.ones(N, dtype), lengths, 9.81))
        solver = sm.RK4(stagewise_reverse=stagewise)
        y1, _, dense, _, _ = solver.step(term, t0, t1, y0, None, None, False)
        return y1, dense["k"]

    inputs = (jnp.array(0.1, dtype), jnp.array(0.15, dtype), y0, LENGTHS.astype(dtype))
    out, pull = jax.vjp(lambda *a: step(False, *a), *inputs)
    out_s, pull_s = jax.vjp(lambda *a: step(True, *a), *inputs)
    ulps = 16 * np.finfo(dtype).eps
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(out_s), strict=True):
        np.testing.assert_allclose(a, b, rtol=ulps, atol=ulps)
    keys = jax.random.split(jax.random.PRNGKey(2), len(jax.tree.leaves(out)))
    leaves, tree = jax.tree.flatten(out)
    cotangent = jax.tree.unflatten(
        tree, [jax.random.normal(k, x.shape, dtype) for k, x in zip(keys, leaves, strict=True)]
    )
    tol = 1e-13 if dtype == jnp.float64 else 1e-5
    grads = jax.tree.leaves(pull(cotangent)), jax.tree.leaves(pull_s(cotangent))
    for a, b in zip(*grads, strict=True):
        assert a.dtype == b.dtype == dtype
        np.testing.assert_allclose(a, b, rtol=tol, atol=tol)


def test_default_reverse_mode_is_stagewise_and_matches_the_old_path():
    """The default adjoint's reverse mode (here 4 scalars per trajectory of a batch)
    differentiates `RK4` stage by stage (`stagewise_reverse`, inside `Projected`): the
    gradient of the old path (`RK4()` under an explicit `RecursiveCheckpointAdjoint`) to
    rounding, and central differences; save times between the steps go through the
    Hermite output's slopes."""
    solver = GRADIENT_RUNS["fixed"]["solver"]
    inside = stagewise_reverse(solver)
    assert type(inside) is sm.Projected and inside.solver.stagewise_reverse
    assert not solver.solver.stagewise_reverse
    q, v = _states(2)
    saveat = diffrax.SaveAt(ts=jnp.array([0.105, 0.2, T1]))

    def loss(x, adjoint):
        chain = sm.chain_pendulum(x[:N], x[N:], 9.81)
        opts = dict(adjoint=adjoint, saveat=saveat, **GRADIENT_RUNS["fixed"])
        sol = sm.simulate_batch(chain, (q, v), T1, **opts)
        return jnp.sum(sol.ys[0] @ WEIGHTS) + jnp.sum(sol.ys[1] ** 2)

    x = jnp.concatenate([jnp.array([1.0, 1.5]), LENGTHS])
    new = eqx.filter_jit(jax.grad(lambda x: loss(x, None)))(x)
    old = eqx.filter_jit(jax.grad(lambda x: loss(x, diffrax.RecursiveCheckpointAdjoint())))(x)
    np.testing.assert_allclose(new, old, rtol=1e-12, atol=1e-12)
    fd = central_differences(eqx.filter_jit(lambda x: loss(x, None)), x)
    np.testing.assert_allclose(new, fd, rtol=1e-6, atol=1e-8)
    assert np.all(np.abs(new) > 1e-3)  # a gradient that could be wrong


@pytest.mark.parametrize("kind", ["tridiagonal", "dense"])
def test_symmetric_solves_differentiate_as_linear_solves(kind):
    """The fast path's solves (`symmetric_solve`: derivatives by another solve, not
    through the factorization's steps), forward and reverse mode, against
    `jnp.linalg.solve` on the same dense matrix (differentiated by JAX's own rule)."""
    n = 5
    d = jnp.linspace(3.0, 4.0, n)
    e = jnp.linspace(-1.0, 0.5, n - 1)
    b = jnp.linspace(-1.0, 2.0, 3 * n).reshape(n, 3)

    def dense(d, e):
        return jnp.diag(d) + jnp.diag(e, 1) + jnp.diag(e, -1)

    def ours(d, e, b):
        if kind == "tridiagonal":
            return tridiagonal_spd_solve(d, e, b)
        return spd_solve(dense(d, e), b)

    reference = lambda d, e, b: jnp.linalg.solve(dense(d, e), b)
    np.testing.assert_allclose(ours(d, e, b), reference(d, e, b), rtol=1e-13, atol=1e-14)
    for jac in (jax.jacfwd, jax.jacrev):
        got = jax.jit(jac(ours, argnums=(0, 1, 2)))(d, e, b)
        want = jax.jit(jac(reference, argnums=(0, 1, 2)))(d, e, b)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-13)
        assert np.abs(got[1]).max() > 1e-2  # a derivative that could be wrong


def test_dense_lu_is_lineax_lu_on_pytrees_and_transposes():
    """`DenseLU` (the Newton iterations' linear solver) against lineax's `LU` on an operator
    from a dict to a differently shaped dict, its transpose (used by implicit
    differentiation), and Newton's root's derivative through it against the closed form."""
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    A = jax.random.normal(keys[0], (5, 5)).at[0, 0].set(0.0)  # needs pivoting
    x_struct = {"a": jnp.zeros(2), "b": jnp.zeros(3)}
    to_out = lambda y: {"c": y[:4].reshape(2, 2), "d": y[4:]}
    matvec = lambda x: to_out(A @ jnp.concatenate([x["a"], x["b"]]))
    operator = lx.FunctionLinearOperator(matvec, jax.eval_shape(lambda: x_struct))
    rhs = to_out(jax.random.normal(keys[1], (5,)))
    for op, vector in ((operator, rhs), (operator.T, x_struct | {"a": jnp.ones(2)})):
        got = lx.linear_solve(op, vector, DenseLU()).value
        want = lx.linear_solve(op, vector, lx.LU()).value
        for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-13)
    # Root of x^3 + c x - 1 = 0 (c > 0): dx/dc = -x / (3 x^2 + c).
    newton = optx.Newton(rtol=1e-12, atol=1e-12, linear_solver=DenseLU())
    root = lambda c: optx.root_find(lambda x, c_: x**3 + c_ * x - 1.0, newton, jnp.ones(3), c).value
    c = jnp.array([0.5, 1.0, 2.0])
    x = root(c)
    np.testing.assert_allclose(x**3 + c * x, 1.0, rtol=1e-13)
    np.testing.assert_allclose(jnp.diag(jax.jacrev(root)(c)), -x / (3 * x**2 + c), rtol=1e-10)
    # The chord method carries the factorization through its loop.
    chord = optx.Chord(rtol=1e-12, atol=1e-12, linear_solver=DenseLU())
    f = lambda y, c_: y**3 + c_ * y - 1.0
    np.testing.assert_allclose(optx.root_find(f, chord, x + 0.01, c).value, x, rtol=1e-11)


@pytest.mark.parametrize("n", [1, 3, 7, DENSE_UNROLL_MAX + 2])
def test_dense_solve_pivots_and_differentiates_as_a_linear_solve(n):
    """The pivoted LU (unrolled up to DENSE_UNROLL_MAX, LAPACK's factors above) against
    `jnp.linalg.solve`, batched, on matrices that need pivoting (a
    zero leading entry), and its forward and reverse derivatives in `A` and `b`."""
    keys = jax.random.split(jax.random.PRNGKey(n), 2)
    A = jax.random.normal(keys[0], (16, n, n)) + 0.1 * jnp.eye(n)
    A = A.at[:, 0, 0].set(0.0) if n > 1 else A
    b = jax.random.normal(keys[1], (16, n))
    want = jnp.linalg.solve(A, b[..., None])[..., 0]
    np.testing.assert_allclose(jax.vmap(dense_solve)(A, b), want, rtol=1e-10, atol=1e-12)
    loss = lambda solve: lambda A_, b_: jnp.sum(jnp.sin(solve(A_, b_)))
    reference = lambda A_, b_: jnp.linalg.solve(A_, b_)
    for jac in (jax.jacfwd, jax.jacrev):
        got = jax.jit(jac(loss(dense_solve), argnums=(0, 1)))(A[0], b[0])
        expected = jax.jit(jac(loss(reference), argnums=(0, 1)))(A[0], b[0])
        for g, w in zip(got, expected, strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-9, atol=1e-11)
    assert not np.isfinite(np.asarray(dense_solve(jnp.zeros((n, n)), jnp.ones(n)))).any()
