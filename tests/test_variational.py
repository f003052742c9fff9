"""The variational (RATTLE-type) integrator: order, reversibility, |q| = 1, energy,
symplecticity, gradients, forces, refusals."""

import functools
import importlib.util
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import fitted_order, fixed_steps, jaxpr_equations, last, max_rel_error, steps_taken

import sphere_mech as sm
from sphere_mech._anderson import Anderson
from sphere_mech._solvers.discrete_mechanics import substep


def general_L(t, q, qdot, args):
    """A double pendulum with configuration-dependent inertia, a quartic kinetic term
    (so the Legendre map needs Newton) and time-dependent gravity; `args = (g, c)`."""
    x1, x2 = q[0], q[0] + 0.8 * q[1]
    v1, v2 = qdot[0], qdot[0] + 0.8 * qdot[1]
    mass = 1.0 + 0.3 * q[0, 0] * q[1, 1]
    kinetic = 0.5 * mass * (v1 @ v1) + 0.5 * (v2 @ v2) + 0.05 * (v2 @ v2) ** 2
    g = args[0] * (1.0 + 0.1 * jnp.sin(2.0 * t))
    return kinetic - g * (x1[2] + x2[2])


def damping(t, q, qdot, args):
    return -args[1] * qdot


# One system for most tests (so they share compilations): conservative when c = 0.
GENERAL = sm.Lagrangian(general_L, forces=damping)
G = (jnp.asarray(9.81), jnp.asarray(0.0))
DAMPED = (jnp.asarray(9.81), jnp.asarray(0.5))
Y0 = (
    sm.normalize(jnp.array([[1.0, 0.0, -1.0], [0.0, 1.0, -1.0]])),
    sm.project(
        sm.normalize(jnp.array([[1.0, 0.0, -1.0], [0.0, 1.0, -1.0]])),
        jnp.array([[0.0, 1.5, 0.0], [1.5, 0.0, 0.3]]),
    ),
)
T1 = 1.0


@pytest.fixture(scope="module")
def reference():
    return last(sm.simulate(GENERAL, Y0, T1, args=G, rtol=1e-13, atol=1e-13).ys)


@pytest.mark.parametrize("order, dts", [(2, (0.04, 0.02, 0.01)), (4, (0.025, 0.0125, 0.00625))])
def test_order(reference, order, dts):
    """Time-dependent, non-quadratic L (Newton for the velocities too)."""
    errors = [
        max_rel_error(
            last(fixed_steps(GENERAL, sm.Variational(order), dt, Y0, args=G).ys)[0], reference[0]
        )
        for dt in dts
    ]
    assert abs(fitted_order(dts, errors) - order) < 0.3, errors
    assert errors[-1] < (1e-2 if order == 2 else 1e-6)


@pytest.mark.parametrize("order", [2, 4])
def test_time_reversible(order):
    """Forward over [0, 0.5] then back with -h returns the initial state to rounding
    (diffrax runs t1 < t0 in reversed time with wrapped terms)."""
    solver = sm.Variational(order)
    forward = last(fixed_steps(GENERAL, solver, 0.05, Y0, t1=0.5, args=G).ys)
    back = last(fixed_steps(GENERAL, solver, -0.05, forward, t0=0.5, t1=0.0, args=G).ys)
    assert max_rel_error(forward[0], Y0[0]) > 0.1  # it did move
    assert max_rel_error(back[0], Y0[0]) < 1e-12
    assert max_rel_error(back[1], Y0[1]) < 1e-12


@pytest.fixture(scope="module")
def long_runs():
    """2 * 10^4 steps (h = 0.05) of a double spherical pendulum: Variational vs
    Projected(RK4) at the same step."""
    chain = sm.chain_pendulum([1.0, 1.0], [1.0, 1.0])
    energy = jax.jit(jax.vmap(lambda q, v: chain.energy(0.0, q, v)))
    out = {}
    for name, solver in (("variational", sm.Variational()), ("rk4", sm.Projected(sm.RK4()))):
        sol = fixed_steps(chain, solver, 0.05, Y0, t1=1000.0, saveat=diffrax.SaveAt(steps=True))
        t, (q, v) = steps_taken(sol)
        error = np.asarray(energy(q, v) - chain.energy(0.0, *Y0))
        out[name] = (np.asarray(t), error, q)
    return out


def drift(t, error):
    """Energy change explained by a linear trend over the run, relative to the largest
    error: about 1 for a drift, small for a bounded oscillating error."""
    slope = np.polyfit(t, error, 1)[0]
    return abs(slope * (t[-1] - t[0])) / np.max(np.abs(error))


def test_energy_bounded_no_drift(long_runs):
    t, error, q = long_runs["variational"]
    assert len(t) == 20_000
    assert drift(t, error) < 0.1
    assert np.max(np.abs(error)) < 0.1 * 14.8  # E0 = -14.8: bounded, O(h^2)
    t_rk4, error_rk4, _ = long_runs["rk4"]
    assert drift(t_rk4, error_rk4) > 0.8  # RK4 at the same step drifts steadily


def test_unit_length_to_rounding(long_runs):
    _, _, q = long_runs["variational"]
    assert float(sm.constraint_error(q)) < 1e-14


def _flow_in_momenta(system, h, steps):
    """The map (q, mu) -> (q, mu) after `steps` steps, mu the momentum on T*(S^2)^n."""

    def flow(q, mu):
        t = jnp.asarray(0.0)
        qdot, _ = system.velocity_from_momentum(t, q, mu, G, guess=mu, tol=1e-12, max_steps=16)
        y = (q, qdot)
        for _ in range(steps):
            y, _, _ = substep(system, t, h, *y, system.rates(t, y, G), G, 1e-12, 16)
            t = t + h
        return y[0], system.momentum(t, y[0], y[1], G)

    return flow


def _tangent_vectors(q, mu):
    """A basis of the tangent space of T*(S^2)^n (as embedded in R^6n) at (q, mu)."""
    T = sm.tangent_basis(q)
    vectors = []
    for i in range(q.shape[0]):
        for b in range(2):
            dq = jnp.zeros_like(q).at[i].set(T[i, :, b])
            dmu = jnp.zeros_like(q).at[i].set(-jnp.dot(T[i, :, b], mu[i]) * q[i])
            vectors.append((dq, dmu))  # move q, keep q . mu = 0
            vectors.append((jnp.zeros_like(q), jnp.zeros_like(q).at[i].set(T[i, :, b])))
    return vectors


def _symplectic_form(u, w):
    return jnp.sum(u[0] * w[1]) - jnp.sum(u[1] * w[0])


def test_symplectic():
    """The pullback of sum dq ^ dmu is preserved (time-dependent, non-quadratic L).
    The flow's derivative along the 8 tangent vectors by central differences."""
    q, qdot = Y0
    mu = GENERAL.momentum(0.0, q, qdot, G)
    flow = jax.jit(jax.vmap(_flow_in_momenta(GENERAL, 0.15, 1)))
    vectors = _tangent_vectors(q, mu)
    eps = 1e-6
    points = [
        (q + sign * eps * dq, mu + sign * eps * dmu) for sign in (1.0, -1.0) for dq, dmu in vectors
    ]
    moved = flow(*jax.tree_util.tree_map(lambda *x: jnp.stack(x), *points))
    m = len(vectors)
    pushed = [tuple((x[i] - x[m + i]) / (2 * eps) for x in moved) for i in range(m)]
    before = np.array([[_symplectic_form(a, b) for b in vectors] for a in vectors])
    after = np.array([[_symplectic_form(a, b) for b in pushed] for a in pushed])
    assert np.max(np.abs(before)) > 0.5  # a nondegenerate form on the 8 vectors
    assert np.max(np.abs(after - before)) < 1e-7
    assert np.max(np.abs(np.asarray(moved[0][0]) - np.asarray(q))) > 0.1


def _steps(solver, system, y, args, h, n):
    """`n` steps of `solver` called directly, as diffrax calls it."""
    term = sm.MechanicsTerm(system)
    state = solver.init(term, 0.0, h, y, args)
    for i in range(n):
        y, _, _, state, _ = solver.step(term, i * h, (i + 1) * h, y, args, state, False)
    return y


def test_gradient_matches_finite_differences():
    """Reverse mode through the Newton solves (implicit differentiation) of a step;
    gradients through `simulate` itself are covered with the other solvers."""

    def loss(g):
        q, v = _steps(sm.Variational(), GENERAL, Y0, (g, G[1]), 0.1, 1)
        return jnp.sum(q[1] * jnp.array([1.0, -2.0, 0.5])) + 0.1 * jnp.sum(v**2)

    grad = jax.jit(jax.grad(loss))(G[0])
    eps = 1e-5
    value = jax.jit(loss)
    fd = (value(G[0] + eps) - value(G[0] - eps)) / (2 * eps)
    assert abs(float(grad) - float(fd)) < 1e-6 * (1 + abs(float(fd)))
    assert abs(float(fd)) > 1e-3


def test_forced_lagrange_dalembert(reference):
    """Damping through `forces`: the forced (Lagrange-d'Alembert) step converges with
    order 2 to the solution of the forced equations."""
    damped_reference = last(sm.simulate(GENERAL, Y0, T1, args=DAMPED, rtol=1e-13, atol=1e-13).ys)
    assert max_rel_error(damped_reference[0], reference[0]) > 0.01  # damping matters
    dts = (0.04, 0.02, 0.01)
    errors = [
        max_rel_error(
            last(fixed_steps(GENERAL, sm.Variational(), dt, Y0, args=DAMPED).ys)[0],
            damped_reference[0],
        )
        for dt in dts
    ]
    assert abs(fitted_order(dts, errors) - 2) < 0.3, errors


def test_angular_lagrangian_same_step():
    """An AngularLagrangian (state (q, omega)) steps exactly like its form-1 original:
    L is only evaluated on the tangent bundle, where the two forms agree."""
    chain = sm.chain_pendulum([1.0, 2.0], [1.0, 0.5])
    q0, qdot0 = Y0
    step = jax.jit(lambda system, y0: _steps(sm.Variational(4), system, y0, None, 0.1, 1))
    form1 = step(chain, Y0)
    form2 = step(sm.angular(chain), (q0, sm.omega_from_qdot(q0, qdot0)))
    assert max_rel_error(form1[0], q0) > 0.01
    assert max_rel_error(form2[0], form1[0]) < 1e-12
    assert max_rel_error(sm.qdot_from_omega(*form2), form1[1]) < 1e-12


def test_newton_failure_is_reported():
    """A step far too large for Newton: reported through `result`, not thrown, and the
    trajectory stops at the last good state."""
    sol = fixed_steps(GENERAL, sm.Variational(), 0.9, Y0, t1=9.0, args=G, throw=False)
    assert sol.result != sm.RESULTS.successful
    assert np.all(np.isfinite(np.asarray(sol.ys[0])))
    # The last good state (here the initial one as the compiled solve retracts it: one
    # unit in the last place off the eager `normalize` on some CPUs), labelled by diffrax
    # with the failed step's end time (documented in `Variational`).
    assert float(sol.ts[-1]) == pytest.approx(0.9) and sol.stats["num_steps"] == 1
    np.testing.assert_allclose(sol.ys[0][-1], Y0[0], rtol=0, atol=2e-16)
    # Saved every 0.1: those inside the failed step are unreached (`inf`), as all after
    # it; before, its dense output made up a curve from the last good state back to it.
    saveat = diffrax.SaveAt(ts=jnp.linspace(0.0, 9.0, 91))
    options = dict(t1=9.0, args=G, throw=False, saveat=saveat)
    sol = fixed_steps(GENERAL, sm.Variational(), 0.9, Y0, **options)
    finite = np.all(np.isfinite(np.asarray(sol.ys[0])), axis=(1, 2))
    good = int(np.sum(finite))
    steps = int(sol.stats["num_steps"])  # the failed one last
    assert np.all(finite[:good]) and good == 9 * (steps - 1) + 1 and good < 91
    with pytest.raises(Exception, match="did not converge|onlinear solve"):
        fixed_steps(GENERAL, sm.Variational(), 0.9, Y0, t1=9.0, args=G)


def test_small_steps_converge_to_the_chords_rounding():
    """Steps so small that the chord `(q1 - q0) / h` rounds above `eps^0.75` relative (from
    rest, h = 1e-5, on the dense Newton path and the fast path; float32 at h = 1e-3): the
    solves accept that rounding floor and the steps agree with an adaptive reference to
    1e-12 (float64) and 1e-5 (float32). Before, Newton could not get below the floor and
    every such run failed."""
    rest = (Y0[0], jnp.zeros_like(Y0[1]))
    reference = lambda system, y0, t1, args: last(
        sm.simulate(system, y0, t1, args=args, rtol=1e-13, atol=1e-13).ys
    )
    chain = sm.chain_pendulum([1.0, 1.0], [1.0, 0.8])
    for system, args in ((GENERAL, G), (chain, None)):
        sol = fixed_steps(system, sm.Variational(), 1e-5, rest, t1=2e-4, args=args)
        assert max_rel_error(last(sol.ys)[0], reference(system, rest, 2e-4, args)[0]) < 1e-12
    f32 = jax.tree.map(lambda x: x.astype(jnp.float32), rest)
    sol = fixed_steps(chain, sm.Variational(), 1e-3, f32, t1=0.02)
    assert sol.ys[0].dtype == jnp.float32
    assert max_rel_error(last(sol.ys)[0], reference(chain, rest, 0.02, None)[0]) < 1e-5


def test_float32_small_steps_follow_float64():
    """The chord's value comes from the step's increment (`space.exp_step`), not from the
    difference `q1 - q0`, whose rounding `eps / h` fed the momenta at every step: 300
    float32 steps of 1e-3 on a moving chain end within 4.2e-6 of float64's velocities
    (max 2.7), against 2.3e-4 before (4.3e-4 with the suite's compiler options; LieRK4:
    1.5e-5)."""
    chain = sm.chain_pendulum([1.0, 0.5], [0.5, 0.4])
    q = sm.normalize(jnp.array([[0.3, 0.1, -1.0], [-0.2, 0.4, -1.0]]))
    y0 = (q, sm.project(q, jnp.array([[1.0, 0.5, 0.0], [-1.0, 0.3, 0.2]])))
    f32 = jax.tree.map(lambda x: x.astype(jnp.float32), y0)
    ends = [last(fixed_steps(chain, sm.Variational(), 1e-3, y, t1=0.3).ys) for y in (y0, f32)]
    assert ends[1][1].dtype == jnp.float32
    assert float(jnp.max(jnp.abs(ends[1][1] - ends[0][1]))) < 2e-5
    assert float(jnp.max(jnp.abs(ends[1][0] - ends[0][0]))) < 5e-6


def test_chord_iteration_solves_the_same_steps():
    """`root_finder="chord"` (the Jacobian at the predictor, factored once) solves the same
    damped discrete equations as Newton's method: the same states to 1e-12 over 20 steps.
    It contracts only while the predictor is close: at h = 0.1 Newton's method still
    converges and the chord iteration does not, which is reported, not thrown."""
    newton = last(fixed_steps(GENERAL, sm.Variational(), 0.05, Y0, args=DAMPED).ys)
    chord = sm.Variational(root_finder="chord")
    ys = last(fixed_steps(GENERAL, chord, 0.05, Y0, args=DAMPED).ys)
    assert max_rel_error(newton[0], Y0[0]) > 0.1
    assert max_rel_error(ys[0], newton[0]) < 1e-12
    assert max_rel_error(ys[1], newton[1]) < 1e-12
    coarse = dict(t1=2.0, args=G, throw=False)
    assert fixed_steps(GENERAL, sm.Variational(), 0.1, Y0, **coarse).result == sm.RESULTS.successful
    sol = fixed_steps(GENERAL, chord, 0.1, Y0, **coarse)
    assert sol.result != sm.RESULTS.successful
    assert np.all(np.isfinite(np.asarray(sol.ys[0])))


def test_refuses_hamiltonian_and_bad_options():
    chain = sm.chain_pendulum([1.0, 1.0], [1.0, 1.0])
    q0, qdot0 = Y0
    mu0 = chain.momentum(0.0, q0, qdot0)
    with pytest.raises(ValueError, match="needs a Lagrangian system"):
        sm.simulate(sm.legendre(chain), (q0, mu0), 1.0, solver=sm.Variational(), dt0=0.1)
    with pytest.raises(ValueError, match="MechanicsTerm"):
        diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: y), sm.Variational(), 0.0, 1.0, 0.1, Y0, args=None
        )
    with pytest.raises(ValueError, match="order must be 2 or 4"):
        sm.Variational(3)
    with pytest.raises(ValueError, match="composition"):
        sm.Variational(4, composition="ruth")
    with pytest.raises(ValueError, match="root_finder must be 'chord' or 'newton', got 'bfgs'"):
        sm.Variational(root_finder="bfgs")
    # The Newton options (accepted before: a tolerance <= 0 or >= 1, 0 becoming the
    # default, a float or zero for the iterations, which optimistix refused when run).
    for tol, bound in ((-1.0, "> 0"), (0.0, "> 0"), (np.nan, "> 0"), (1e3, "< 1")):
        with pytest.raises(ValueError, match=f"Variational: root_find_tol must be .*{bound}"):
            sm.Variational(root_find_tol=tol)
    for steps in (2.5, 0, True):
        with pytest.raises(ValueError, match="root_find_max_steps must be a positive integer"):
            sm.Variational(root_find_max_steps=steps)
    assert sm.Variational(root_find_tol=np.float32(1e-6)).root_find_tol == pytest.approx(1e-6)


@pytest.mark.slow
def test_long_time_energy_million_steps():
    """10^6 steps (dt = 0.01, 10^4 s) of a double spherical pendulum, as in
    benchmarks/long_time_energy.py: the envelope of the variational integrator's energy
    error has no trend, Projected(RK4)'s at the same step grows steadily."""
    path = Path(__file__).parents[1] / "benchmarks" / "long_time_energy.py"
    spec = importlib.util.spec_from_file_location("long_time_energy", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    t, error, constraint, result, _ = bench.run(sm.Variational(), 0.01, 1_000_000)
    assert result == sm.RESULTS.successful and len(t) == 1_000_000
    assert abs(bench.envelope_trend(t, error)[3]) < 0.3
    assert np.max(error) < 3e-3
    assert np.max(constraint) < 1e-15
    t, error, _, _, _ = bench.run(sm.Projected(sm.RK4()), 0.01, 1_000_000)
    assert bench.envelope_trend(t, error)[3] > 1.0


@pytest.mark.parametrize("composition", ["suzuki", "yoshida"])
def test_composition_conditions(composition):
    """Symmetric compositions of a symmetric order-2 step reach order 4 exactly when
    sum gamma = 1 and sum gamma^3 = 0 (Hairer, Lubich & Wanner, II.4); the Suzuki one
    is measured end to end in test_order."""
    gammas = np.array(sm.Variational(4, composition=composition).gammas)
    assert len(gammas) == (5 if composition == "suzuki" else 3)
    assert np.allclose(gammas, gammas[::-1], atol=0, rtol=1e-15)
    assert abs(np.sum(gammas) - 1) < 1e-14
    assert abs(np.sum(gammas**3)) < 1e-14
    assert sm.Variational().gammas == (1.0,)


# ---- the O(n) step of constant-inertia systems -------------------------------------------

STRUCTURED = {
    "chain": sm.chain_pendulum([1.0, 0.7, 1.3, 0.9], [1.0, 0.8, 0.6, 1.1]),
    # a chain and a free particle, springs, bending, damping (velocity-dependent forces)
    # and drives: every kind of effect the variational step supports
    "scene": sm.Scene(
        sm.Chain([1.0, 0.7, 1.3], [1.0, 0.8, 0.6]),
        sm.Particles(0.5, 0.7, [2.0, 0.0, 0.0]),
        sm.Gravity(9.81),
        sm.Spring(2, 3, 3.0, 0.5),
        sm.Bending(0.4),
        sm.JointDamping(0.3),
        sm.BaseTorque(jnp.array([0.2, -0.1, 0.3])),
        sm.TipForce(jnp.array([0.5, 0.0, -0.4])),
    ),
}


def _structured_state(n):
    q, v = sm.random_state(jax.random.PRNGKey(n), n, speed=1.0)
    q = sm.normalize(0.7 * q + jnp.array([0.0, 0.0, -1.0]))
    return q, sm.project(q, v)


@pytest.mark.parametrize("name", ["chain", "scene"])
def test_fast_path_agrees_with_dense_newton(name):
    """Constant-inertia systems solve each step by the O(n) iteration of the fast path;
    `fast_path=False` takes Newton's method with the dense Jacobian on the same
    equations: three steps of each agree to rounding."""
    system = STRUCTURED[name]
    y0 = _structured_state(system.n)
    term = sm.MechanicsTerm(system)

    @functools.partial(jax.jit, static_argnums=0)
    def run(solver, y):  # three steps of 0.05 (one compiled step in a scan)
        def step(y, t):
            rates = system.rates(t, y, None)
            return solver.step(term, t, t + 0.05, y, None, rates, False)[0], None

        return jax.lax.scan(step, y, 0.05 * jnp.arange(3.0))[0]

    fast = run(sm.Variational(), y0)
    dense = run(sm.Variational(fast_path=False), y0)
    assert max_rel_error(fast[0], y0[0]) > 0.01  # it moved
    assert max_rel_error(fast[0], dense[0]) < 1e-12
    assert max_rel_error(fast[1], dense[1]) < 1e-11


def test_fast_path_step_has_no_dense_solve():
    """The jaxpr of the O(n) step has no LU (LAPACK's, or the unrolled one's pivot search),
    Cholesky or triangular solve, where the dense Newton step of the same system has its
    LU; also past the size where dense solves call LAPACK."""
    lapack = {"lu", "cholesky", "triangular_solve", "lu_pivots_to_permutation"}
    dense_primitives = lapack | {"argmax"}

    def primitives(system, solver):
        n = system.n
        y0 = _structured_state(n)
        term = sm.MechanicsTerm(system)
        step = lambda y: solver.step(term, 0.0, 0.05, y, None, system.rates(0.0, y, None), False)[0]
        return {e.primitive.name for e in jaxpr_equations(jax.make_jaxpr(step)(y0).jaxpr)}

    scene = STRUCTURED["scene"]
    assert dense_primitives & primitives(scene, sm.Variational(fast_path=False))
    assert not dense_primitives & primitives(scene, sm.Variational())
    long_chain = sm.chain_pendulum(jnp.ones(20), jnp.ones(20))  # the unrolled-LAPACK limit
    assert not dense_primitives & primitives(long_chain, sm.Variational(4))


def test_anderson_converges_where_the_plain_iteration_diverges():
    """The acceleration of the O(n) iteration, on an affine map `y -> B y + c` with one
    eigenvalue of `B` above 1 (the plain iteration diverges): the fixed point
    `(I - B)^-1 c` to rounding, and its derivative in `c` by implicit differentiation."""
    rotation, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(4, 4)))
    B = jnp.asarray(rotation @ np.diag([1.5, 0.5, 0.2, -0.3]) @ rotation.T)
    c = jnp.array([1.0, -2.0, 0.5, 0.3])
    exact = jnp.linalg.solve(jnp.eye(4) - B, c)

    def solve(solver, c):
        sol = optx.fixed_point(
            lambda y, c: B @ y + c, solver, jnp.zeros(4), c, max_steps=40, throw=False
        )
        return sol.value, sol.result

    anderson = jax.jit(lambda c: solve(Anderson(rtol=1e-13, atol=1e-13), c))
    value, result = anderson(c)
    assert result == optx.RESULTS.successful
    assert max_rel_error(value, exact) < 1e-12
    plain = solve(optx.FixedPointIteration(rtol=1e-13, atol=1e-13), c)
    assert plain[1] != optx.RESULTS.successful
    jacobian = jax.jacfwd(lambda c: anderson(c)[0])(c)
    assert max_rel_error(jacobian, jnp.linalg.inv(jnp.eye(4) - B)) < 1e-10
