"""`simulate`: composition with jit / vmap / grad, the four forms, float32, progress bar,
failure reporting (max_steps, NaN, Newton) with and without `throw`."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import max_rel_error, tree_allclose

import sphere_mech as sm


def double_pendulum(t, q, qdot, g):
    """Unit masses, lengths 1 and 0.8; gravity `g` is the `args`."""
    x1, x2 = q[0], q[0] + 0.8 * q[1]
    v1, v2 = qdot[0], qdot[0] + 0.8 * qdot[1]
    return 0.5 * (v1 @ v1 + v2 @ v2) - g * (x1[2] + x2[2])


SYSTEM = sm.Lagrangian(double_pendulum, quadratic_in_velocity=True)
G = jnp.asarray(9.81)
Q0 = sm.normalize(jnp.array([[1.0, 0.0, -1.0], [0.0, 1.0, -0.5]]))
V0 = sm.project(Q0, jnp.array([[0.0, 1.5, 0.0], [1.5, 0.0, 0.3]]))
T1 = 1.0
TS = jnp.linspace(0.0, T1, 5)
SAVEAT = diffrax.SaveAt(ts=TS)
MAX_STEPS_MESSAGE = "max_steps must be an integer from 1 to 2147483647 or None"


def run(y0, g=G, **kwargs):
    return sm.simulate(SYSTEM, y0, T1, args=g, saveat=SAVEAT, **kwargs)


@pytest.fixture(scope="module")
def eager():
    return run((Q0, V0))


def test_default_run(eager):
    q, v = eager.ys
    assert q.shape == v.shape == (5, 2, 3)
    assert eager.result == sm.RESULTS.successful
    assert float(sm.constraint_error(q)) < 1e-14
    energy = jax.jit(jax.vmap(SYSTEM.energy, (None, 0, 0, None)))(0.0, q, v, G)
    assert float(jnp.max(jnp.abs(energy - energy[0]))) < 1e-7


def test_jit(eager):
    ys = jax.jit(lambda y0, g: run(y0, g).ys)((Q0, V0), G)
    assert tree_allclose(ys, eager.ys, rtol=1e-12, atol=1e-12)


def test_vmap_over_initial_conditions(eager):
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    q_b, v_b = jax.vmap(lambda k: sm.random_state(k, 2))(keys)
    q_b, v_b = jnp.concatenate([Q0[None], q_b]), jnp.concatenate([V0[None], v_b])
    ys = jax.vmap(lambda q, v: run((q, v)).ys)(q_b, v_b)
    assert ys[0].shape == (3, 5, 2, 3)
    # Batched adaptive runs take the union of steps, so agree to the tolerance.
    assert max_rel_error(ys[0][0], eager.ys[0]) < 1e-7
    assert float(sm.constraint_error(ys[0])) < 1e-14


def test_vector_field_traced_once_per_system_and_shapes():
    """`L` runs (in Python) only when JAX traces the vector field: a solve traces it once,
    not once per Runge-Kutta stage and loop pass, and forward mode (`jax.jacfwd`) or
    reverse mode (`jax.grad`) transforms the traced equations instead of tracing them
    again (30, 30 and 30 traces of `L` each before `vector_field` cached them; 3, 0, 3
    now). The transformed runs are traced, not compiled (`jax.eval_shape`)."""
    traces = []

    def counted(t, q, qdot, g):
        traces.append(None)
        return double_pendulum(t, q, qdot, g)

    system, opts = sm.Lagrangian(counted), dict(solver=sm.Projected(sm.RK4()), dt0=0.05)
    final = lambda g, **kw: sm.simulate(system, (Q0, V0), 0.2, args=g, **opts, **kw).ys[0][-1]
    counts = [len(traces)]
    for run_ in (
        lambda: final(G),
        lambda: jax.eval_shape(jax.jacfwd(lambda g: final(g, adjoint=diffrax.ForwardMode())), G),
        lambda: jax.eval_shape(jax.grad(lambda g: final(g)[1, 2]), G),
    ):
        run_()
        counts.append(len(traces))
    per_run = np.diff(counts)
    assert per_run[0] >= 1 and np.all(per_run <= 6), per_run
    # the cache is keyed on what is static: a new function object is traced anew, and
    # Python floats (static, as in `system.rates`) give their own equations
    before = len(traces)
    jax.eval_shape(
        lambda: sm.simulate(sm.Lagrangian(lambda *a: counted(*a)), (Q0, V0), 0.2, args=G, **opts)
    )
    assert len(traces) > before
    low, high = final(1.0), final(9.81)
    assert float(jnp.max(jnp.abs(high - final(G)))) < 1e-12 < float(jnp.max(jnp.abs(low - high)))


def test_grad_wrt_args_and_initial_state():
    """Reverse mode through fixed steps of Projected(RK4) against central differences
    of the same discrete map (relative 1e-6), for `args` and along tangent directions
    of the initial state. One compilation (`value_and_grad` gives the values too)."""

    @eqx.filter_jit
    @jax.value_and_grad
    def loss(inputs):
        (q0, v0), g = inputs
        sol = sm.simulate(
            SYSTEM, (q0, v0), 0.5, args=g, solver=sm.Projected(sm.RK4()), dt0=0.01, max_steps=64
        )
        q, v = sol.ys
        return jnp.sum(q[-1, 1] * jnp.array([0.3, -1.0, 2.0])) + jnp.sum(v[-1] ** 2)

    _, ((gq, gv), gg) = loss(((Q0, V0), G))
    dq = sm.project(Q0, jnp.array([[0.0, 0.3, -0.2], [0.5, 0.0, 0.1]]))
    dv = sm.project(Q0, jnp.array([[0.2, 0.0, 0.0], [0.0, -0.1, 0.4]]))
    eps = 1e-6
    checks = [
        (gg, ((Q0, V0), G + eps), ((Q0, V0), G - eps)),
        (
            jnp.sum(gq * dq),
            ((sm.normalize(Q0 + eps * dq), V0), G),
            ((sm.normalize(Q0 - eps * dq), V0), G),
        ),
        (jnp.sum(gv * dv), ((Q0, V0 + eps * dv), G), ((Q0, V0 - eps * dv), G)),
    ]
    for derivative, plus, minus in checks:
        fd = (loss(plus)[0] - loss(minus)[0]) / (2 * eps)
        assert abs(float(derivative) - float(fd)) < 1e-6 * abs(float(fd)), (derivative, fd)


def test_four_forms_give_the_same_trajectory(eager):
    omega0 = sm.omega_from_qdot(Q0, V0)
    mu0 = SYSTEM.momentum(0.0, Q0, V0, G)
    pi0 = sm.pi_from_mu(Q0, mu0)
    forms = [
        (sm.angular(SYSTEM), omega0),
        (sm.legendre(SYSTEM), mu0),
        (sm.legendre(sm.angular(SYSTEM)), pi0),
    ]
    q_ref, qdot_ref = eager.ys
    # LieRK4 here: SE(3) moves each form's own v (as omega_i = q_i x v_i where not angular).
    for system, v0 in forms:
        sol = sm.simulate(
            system, (Q0, v0), T1, args=G, saveat=SAVEAT, solver=sm.LieRK4(), rtol=1e-10, atol=1e-12
        )
        q, v = sol.ys
        qdot = jax.jit(jax.vmap(system.velocity, (None, 0, 0, None)))(0.0, q, v, G)
        assert max_rel_error(q, q_ref) < 1e-7, type(system)
        assert max_rel_error(qdot, qdot_ref) < 1e-7, type(system)


def test_float32_with_progress_bar(eager, capfd):
    q0, v0 = Q0.astype(jnp.float32), V0.astype(jnp.float32)
    # float64 save times (numpy's default) are the state's float32 too; they promoted it
    saveat = diffrax.SaveAt(ts=np.asarray(TS, np.float64))
    sol = sm.simulate(SYSTEM, (q0, v0), T1, args=jnp.float32(9.81), saveat=saveat, progress=True)
    q, v = sol.ys
    assert q.dtype == v.dtype == sol.ts.dtype == jnp.float32
    assert float(sm.constraint_error(q)) < 1e-6
    # Default float32 tolerances are rtol=1e-5, atol=1e-6.
    assert max_rel_error(q, eager.ys[0]) < 1e-3
    assert "100.00%" in capfd.readouterr().err  # tqdm's bar reached the end


def singular(t, q, qdot, args):
    """A pendulum pulled down by a force that is NaN below z = -0.5 (sqrt)."""
    return 0.5 * jnp.sum(qdot**2) - 9.81 * q[0, 2] + jnp.sqrt(q[0, 2] + 0.5)


Y_SINGULAR = (jnp.array([[1.0, 0.0, 0.0]]), jnp.array([[0.0, 0.3, 0.0]]))


def _check_partial_trajectory(sol):
    """The saved states before the failure are finite (and on the spheres), the later
    ones are diffrax's `inf` padding."""
    q = np.asarray(sol.ys[0])
    reached = np.all(np.isfinite(q), axis=(1, 2))
    assert reached[0] and not reached[-1]
    assert np.all(reached[: reached.sum()])  # a prefix
    assert float(sm.constraint_error(q[reached])) < 1e-14
    # not NaN after a NaN state, nor their times (before: NaN states at finite times)
    assert np.all(np.isinf(q[~reached]))
    assert np.all(np.isinf(np.asarray(sol.ts)[~reached]))


@pytest.mark.parametrize(
    "case",
    ["max_steps", "nan", "newton"],
)
def test_failures_are_reported(case):
    ts = jnp.linspace(0.0, 2.0, 9)
    if case == "max_steps":
        kwargs = dict(system=SYSTEM, y0=(Q0, V0), args=G, max_steps=30)
        code, match = sm.RESULTS.max_steps_reached, "max_steps=30"
    elif case == "nan":
        kwargs = dict(system=sm.Lagrangian(singular), y0=Y_SINGULAR, solver=sm.RK4(), dt0=0.01)
        code, match = sm.RESULTS.nonfinite, "became NaN"
    else:
        chord = diffrax.VeryChord(rtol=1e-10, atol=1e-10)
        kwargs = dict(
            system=SYSTEM,
            y0=(Q0, V0),
            args=G,
            dt0=0.25,
            solver=sm.Projected(diffrax.ImplicitEuler(root_finder=chord)),
            stepsize_controller=diffrax.ConstantStepSize(),
        )
        code, match = None, "Newton iterations"
    sol = sm.simulate(t1=2.0, saveat=diffrax.SaveAt(ts=ts), throw=False, **kwargs)
    if code is None:
        assert sol.result in (
            sm.RESULTS.nonlinear_divergence,
            sm.RESULTS.nonlinear_max_steps_reached,
        )
    else:
        assert sol.result == code
    _check_partial_trajectory(sol)
    with pytest.raises(RuntimeError, match=match):
        sm.simulate(t1=2.0, saveat=diffrax.SaveAt(ts=ts), **kwargs)


def test_fixed_steps_turning_nan_after_the_last_save_time_are_reported():
    """Fixed steps accept a NaN step (no controller rejects it): a force that turns NaN
    at t = 0.5, after the last save time 0.2, is still `nonfinite`, with a dense-only
    `SaveAt` too, for `Projected(RK4())` and `LieRK4()`. Before, both were `successful`
    with NaN between the steps."""
    nan_force = lambda t, q, qdot, args: jnp.where(t > 0.5, jnp.nan, 0.0) * qdot
    system = sm.Lagrangian(double_pendulum, forces=nan_force, quadratic_in_velocity=True)
    fixed = dict(dt0=0.05, stepsize_controller=diffrax.ConstantStepSize(), args=G, throw=False)
    for solver in (sm.Projected(sm.RK4()), sm.LieRK4()):
        for saveat in (diffrax.SaveAt(ts=[0.1, 0.2]), diffrax.SaveAt(dense=True)):
            sol = sm.simulate(system, (Q0, V0), 1.0, solver=solver, saveat=saveat, **fixed)
            assert sol.result == sm.RESULTS.nonfinite
        assert np.all(np.isfinite(np.asarray(sol.evaluate(0.4)[0])))


def test_unreached_and_nan_save_times_are_inf_backwards_too():
    """Backwards in time, a NaN state's save times were `-inf` while the unreached ones
    (diffrax's, after `max_steps`) are `+inf`: both are `+inf`, as documented."""
    nan_force = lambda t, q, qdot, args: jnp.where(t < -0.25, jnp.nan, 0.0) * qdot
    system = sm.Lagrangian(double_pendulum, forces=nan_force, quadratic_in_velocity=True)
    saveat = diffrax.SaveAt(ts=[0.0, -0.1, -0.2, -0.3, -0.4])
    fixed = dict(dt0=-0.05, stepsize_controller=diffrax.ConstantStepSize(), args=G, throw=False)
    sol = sm.simulate(system, (Q0, V0), -0.5, solver=sm.Projected(sm.RK4()), saveat=saveat, **fixed)
    assert sol.result == sm.RESULTS.nonfinite
    np.testing.assert_array_equal(sol.ts, [0.0, -0.1, -0.2, np.inf, np.inf])
    short = sm.simulate(SYSTEM, (Q0, V0), -0.5, args=G, saveat=saveat, max_steps=2, throw=False)
    assert short.result == sm.RESULTS.max_steps_reached
    assert np.all(np.asarray(short.ts)[2:] == np.inf)


def test_failure_inside_jit_raises():
    f = jax.jit(lambda y0: sm.simulate(SYSTEM, y0, 2.0, args=G, max_steps=30).ys)
    with pytest.raises(Exception, match="max_steps=30"):
        jax.block_until_ready(f((Q0, V0)))


def test_initial_state_checks():
    with pytest.raises(ValueError, match="pair"):
        sm.simulate(SYSTEM, Q0, T1, args=G)
    with pytest.raises(Exception, match="not on the spheres"):
        sm.simulate(SYSTEM, (2.0 * Q0, V0), T1, args=G)
    with pytest.raises(Exception, match="not tangent"):
        sm.simulate(SYSTEM, (Q0, V0 + Q0), T1, args=G)


@pytest.mark.parametrize(
    "options, message",
    [
        (dict(dt0=0.0), r"^dt0 must be a finite, nonzero step \(got 0\)$"),
        (
            dict(dt0=-0.01),
            r"^dt0 must have the sign of t1 - t0, the direction of integration "
            r"\(got -0.01 with t0 = 0, t1 = 1\)$",
        ),
        (dict(rtol=-1e-8), r"^rtol must be a finite number > 0 \(got -1e-08\)$"),
        (dict(atol=float("nan")), r"^atol must be a finite number > 0 \(got nan\)$"),
        (dict(max_steps=0), rf"^{MAX_STEPS_MESSAGE} \(got 0\)$"),
        (dict(max_steps=10**20), rf"^{MAX_STEPS_MESSAGE} \(got 100000000000000000000\)$"),
        (dict(t0=float("inf")), r"^t0 must be a finite time \(got inf\)$"),
        (dict(t0=jnp.zeros(2)), r"^t0 must be a scalar \(got shape \(2,\)\)$"),
        # before: a string or a bool was taken as a number (t0="0.5", dt0=True: a step of
        # 1), a string tolerance failed inside diffrax, and a huge integer overflowed
        (dict(t0="0.5"), r"^t0 must be a real number \(got '0.5'\)$"),
        (dict(dt0=True), r"^dt0 must be a real number \(got True\)$"),
        (dict(rtol="1e-6"), r"^rtol must be a real number \(got '1e-6'\)$"),
        (dict(t0=-(10**400)), r"^t0 must be a finite time \(got -inf\)$"),
        # before: AttributeErrors from inside diffrax ('str' object has no attribute 'wrap')
        (
            dict(stepsize_controller="pid"),
            r"^stepsize_controller must be a diffrax step-size controller, .* \(got 'pid'\)$",
        ),
        (dict(saveat=[0.0, 0.5]), r"^saveat must be a diffrax.SaveAt, .* \(got \[0.0, 0.5\]\)$"),
        (dict(adjoint="forward"), r"^adjoint must be a diffrax adjoint, .* \(got 'forward'\)$"),
        (dict(event=print), r"^event must be a diffrax.Event, e.g. diffrax.Event\(cond_fn\)"),
        (dict(solver=42), r"^solver must be a diffrax solver instance.*\(got 42\)$"),
        (
            dict(solver="Tsit6"),
            r"^solver must be a diffrax solver or a solver spelled as in "
            r"Python: .*got 'Tsit6'$",
        ),
        (dict(solver=sm.LieRK), r"^solver must be a diffrax solver instance"),
        # save times: diffrax checked order and range only while running, and a NaN not at
        # all (it saved inf)
        (dict(saveat=diffrax.SaveAt(ts=jnp.array([jnp.nan]))), r"^saveat.ts must be finite"),
        (
            dict(saveat=diffrax.SaveAt(ts=jnp.array([0.5, 1.5]))),
            r"^saveat.ts must lie between t0 = 0 and t1 = 1 \(got 0.5 to 1.5\)$",
        ),
        (dict(saveat=diffrax.SaveAt(ts=jnp.array([0.5, 0.2]))), r"^saveat.ts must be increasing"),
        # before: raveled by the check, then an error from inside diffrax
        (
            dict(saveat=diffrax.SaveAt(ts=jnp.array([[0.1, 0.2]]))),
            r"^saveat.ts must be a 1-D array of times \(got shape \(1, 2\)\)$",
        ),
        # malformed events: before, an AttributeError, a TypeError (unexpected keyword
        # argument 'terms') and a 'float' object is not callable from inside diffrax
        (
            dict(event=diffrax.Event(lambda t, y, args, **kw: t, root_finder="newton")),
            r"^event.root_finder must be an optimistix root finder or None, .*got 'newton'",
        ),
        (
            dict(event=diffrax.Event(lambda t, y, args: t)),
            r"^event.cond_fn must be a function cond_fn\(t, y, args, \*\*kwargs\) .*\(3 arguments "
            r"and the keywords terms, solver, .*got one with signature \(t, y, args\)\.$",
        ),
        (dict(event=diffrax.Event(3.0)), r"^event.cond_fn must be a function .*, got float\.$"),
    ],
)
def test_option_values_are_checked_before_tracing(options, message):
    """The same check (and words) as scene files: a ValueError naming the option and its
    value, before anything is traced, for simulate and simulate_batch alike."""
    with pytest.raises(ValueError, match=message):
        sm.simulate(SYSTEM, (Q0, V0), T1, args=G, **options)
    with pytest.raises(ValueError, match=message):
        sm.simulate_batch(SYSTEM, (Q0[None], V0[None]), T1, args=G, batch_args=False, **options)


def test_fixed_steps_that_do_not_divide_the_interval():
    """As `simulate`'s docstring says (it said 0.3, 0.3, 0.3, 0.1): the first step is
    `dt0`, the others end at `t0 + k (t1 - t0) / N`, `N = ceil((t1 - t0) / dt0)`."""
    steps = diffrax.SaveAt(steps=True)
    sol = sm.simulate(
        SYSTEM, (Q0, V0), T1, args=G, solver=sm.Projected(sm.RK4()), dt0=0.3, saveat=steps
    )
    np.testing.assert_allclose(sol.ts[:5], [0.3, 0.5, 0.75, 1.0, np.inf], rtol=1e-15)


def test_numpy_integer_max_steps(eager):
    """`max_steps` as a NumPy integer (before: equinox's TracerBoolConversionError, the
    value made static as an array): the same run as with a Python int."""
    sol = run((Q0, V0), max_steps=np.int64(100_000))
    assert tree_allclose(sol.ys, eager.ys, rtol=0.0, atol=0.0)


def test_solver_by_name_or_class(eager):
    """A name (as in scene files) or a solver class resolves to an instance; a class
    inside Projected is refused naming `solver`."""
    ref = run((Q0, V0), solver=sm.Projected(diffrax.Tsit5()), dt0=0.01)
    for solver in ("Projected(Tsit5)", "Tsit5", diffrax.Tsit5):
        sol = run((Q0, V0), solver=solver, dt0=0.01)
        unprojected = solver != "Projected(Tsit5)"
        assert tree_allclose(sol.ys, ref.ys, rtol=0.0, atol=1e-5 if unprojected else 0.0)
    with pytest.raises(
        ValueError,
        match=r"^Projected\(solver\): solver must be a diffrax "
        r"solver instance, e.g. diffrax.Tsit5\(\) \(got the class Tsit5\)$",
    ):
        sm.Projected(diffrax.Tsit5)


def test_lists_and_backward_integration(eager):
    """y0 as nested Python lists; t1 < t0 integrates backwards (and back again)."""
    lists = (np.asarray(Q0).tolist(), np.asarray(V0).tolist())
    sol = run(lists)
    assert tree_allclose(sol.ys, eager.ys, rtol=0.0, atol=0.0)
    end = (sol.ys[0][-1], sol.ys[1][-1])
    back = sm.simulate(SYSTEM, end, 0.0, t0=T1, args=G, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(back.ys[0][-1], Q0, atol=1e-6)
    assert float(back.ts[-1]) == 0.0
