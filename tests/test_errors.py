"""Each bad input gives an error that names the problem: static problems raise
`ValueError` at trace time, value problems raise through `equinox.error_if` (also under
jit). Input within the documented tolerance is accepted."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sphere_mech as sm

NOT_UNIT = "q is not on the spheres"
SINGULAR = "reduced mass matrix .* is singular"
LEGENDRE = "the Legendre transform is not invertible at this state"


def L(t, q, qdot, args):
    return 0.5 * jnp.sum(qdot**2) - jnp.sum(q[:, 2])


def L_first_sphere_only(t, q, qdot, args):
    """No kinetic energy in the second sphere: a degenerate Lagrangian."""
    return 0.5 * jnp.sum(qdot[0] ** 2) - jnp.sum(q[:, 2])


SYSTEM = sm.Lagrangian(L)


@pytest.fixture(scope="module")
def state():
    return sm.random_state(jax.random.PRNGKey(0), 2)


def all_forms(system):
    return dict(
        qdot=lambda t, q, v: system.acceleration(t, q, v, None),
        omega=lambda t, q, v: sm.angular(system).angular_acceleration(t, q, v, None),
        mu=lambda t, q, v: sm.legendre(system).vector_field(t, q, v, None),
        pi=lambda t, q, v: sm.legendre(sm.angular(system)).vector_field(t, q, v, None),
    )


@pytest.mark.parametrize("name", ["qdot", "omega", "mu", "pi"])
def test_bad_shapes(name, state):
    q, v = state
    fn = all_forms(SYSTEM)[name]
    with pytest.raises(ValueError, match=r"q must have shape \(n, 3\).*got \(2, 2\)"):
        fn(0.0, q[:, :2], v[:, :2])
    with pytest.raises(ValueError, match=r"q must have shape \(n, 3\).*got \(6,\)"):
        fn(0.0, q.reshape(-1), v.reshape(-1))
    with pytest.raises(
        ValueError,
        match=rf"{name} must have the same shape as q, \(2, 3\), "
        r"got \(1, 3\)",
    ):
        fn(0.0, q, v[:1])
    with pytest.raises(ValueError, match="q must be a floating-point array"):
        fn(0.0, jnp.array([[0, 0, 1]]), jnp.zeros((1, 3)))
    # half precision ran simulate until max_steps (its rounding is above every tolerance)
    half = jnp.array([[0.0, 0.0, 1.0]], jnp.float16)
    with pytest.raises(ValueError, match="^q must be .* of float32 or float64, got float16.$"):
        fn(0.0, half, jnp.zeros_like(half))
    with pytest.raises(ValueError, match="^q must be .* of float32 or float64, got float16.$"):
        sm.simulate(sm.chain_pendulum([1.0], [1.0]), (-half, jnp.zeros_like(half)), 0.1)


@pytest.mark.parametrize("name", ["qdot", "omega", "mu", "pi"])
def test_not_on_the_spheres_or_not_tangent(name, state):
    q, v = state
    fn = all_forms(SYSTEM)[name]
    with pytest.raises(eqx.EquinoxRuntimeError, match=NOT_UNIT):
        fn(0.0, 1.01 * q, v)
    with pytest.raises(eqx.EquinoxRuntimeError, match=f"{name} is not tangent to the spheres"):
        fn(0.0, q, v + 0.01 * q)
    with pytest.raises(eqx.EquinoxRuntimeError, match="q contains NaN or infinite values"):
        fn(0.0, q.at[0, 0].set(jnp.nan), v)
    with pytest.raises(eqx.EquinoxRuntimeError, match=f"{name} contains NaN or infinite"):
        fn(0.0, q, v.at[1, 2].set(jnp.inf))


def test_within_tolerance_is_accepted(state):
    q, v = state
    tol = sm.unit_tolerance(jnp.float64)
    assert tol == 1e-6 and sm.unit_tolerance(jnp.float32) == 1e-4
    q_off = q * (1.0 + 0.5 * tol)
    v_off = v + 0.5 * tol * q
    SYSTEM.acceleration(0.0, q_off, v_off, None)
    # simulate accepts it and puts the initial state exactly on the tangent bundle
    sol = sm.simulate(SYSTEM, (q_off, v_off), 0.0)
    q0, v0 = sol.ys[0][0], sol.ys[1][0]
    assert float(sm.constraint_error(q0)) < 1e-15
    assert float(jnp.max(jnp.abs(jnp.sum(q0 * v0, -1)))) < 1e-15


def test_checks_work_under_jit(state):
    q, v = state
    with pytest.raises(eqx.EquinoxRuntimeError, match=NOT_UNIT):
        eqx.filter_jit(SYSTEM.acceleration)(0.0, 2.0 * q, v, None)


def test_non_scalar_lagrangian_or_hamiltonian(state):
    q, v = state
    bad = sm.Lagrangian(lambda t, q, qdot, args: qdot)
    with pytest.raises(
        ValueError,
        match=r"L\(t, q, v, args\) must return a scalar, got an "
        r"array of shape \(2, 3\)",
    ):
        bad.acceleration(0.0, q, v, None)
    with pytest.raises(ValueError, match="must return a scalar"):
        sm.legendre(bad).vector_field(0.0, q, v, None)
    with pytest.raises(ValueError, match=r"H\(t, q, p, args\) must return a scalar"):
        sm.Hamiltonian(lambda t, q, p, args: p).vector_field(0.0, q, v, None)


def test_bad_forces(state):
    q, v = state
    system = sm.Lagrangian(L, forces=lambda t, q, qdot, args: qdot[0])
    with pytest.raises(
        ValueError,
        match=r"forces\(t, q, v, args\) must return an array of "
        r"shape \(2, 3\)",
    ):
        system.acceleration(0.0, q, v, None)


@pytest.mark.parametrize("name", ["qdot", "omega"])
def test_degenerate_lagrangian_lagrangian_forms(name, state):
    q, v = state
    with pytest.raises(eqx.EquinoxRuntimeError, match=SINGULAR):
        all_forms(sm.Lagrangian(L_first_sphere_only))[name](0.0, q, v)


def test_singular_to_rounding_is_singular(state):
    """Mass matrices singular in exact arithmetic whose rounding leaves a pivot of about
    eps (kinetic energy along one direction of a sphere; a double pendulum whose first
    mass is missing; a cart with no mass): refused as degenerate. Before, the rank-1 case
    returned accelerations of 1e16 and the others O(1) rounding noise, silently."""
    q, v = state
    c = jnp.array([0.3, -0.5, 0.8])
    one_direction = lambda t, q, qdot, args: 0.5 * (qdot[0] @ c) ** 2 - q[0, 2]
    no_first_mass = lambda t, q, qdot, args: 0.5 * jnp.sum((qdot[0] + qdot[1]) ** 2) - q[1, 2]
    no_cart_mass = lambda t, q, qdot, args: 0.5 * jnp.sum((qdot["x"] + qdot["s"][0]) ** 2)
    cart = {"x": sm.Euclidean(3), "s": sm.Spheres(1)}
    cases = [
        (sm.Lagrangian(one_direction), q[:1], v[:1]),
        (sm.Lagrangian(no_first_mass), q, v),
        (
            sm.Lagrangian(no_cart_mass, space=cart),
            {"x": jnp.zeros(3), "s": q[:1]},
            {"x": jnp.ones(3), "s": v[:1]},
        ),
    ]
    for system, q_, v_ in cases:
        with pytest.raises(eqx.EquinoxRuntimeError, match=SINGULAR):
            system.acceleration(0.0, q_, v_, None)


@pytest.mark.parametrize("quadratic", [True, False])
def test_degenerate_lagrangian_hamiltonian_forms(quadratic, state):
    q, v = state
    H = sm.legendre(sm.Lagrangian(L_first_sphere_only), quadratic=quadratic)
    with pytest.raises(eqx.EquinoxRuntimeError, match=LEGENDRE):
        H.vector_field(0.0, q, v, None)
    if quadratic:  # in a run: a result code with throw=False, a message naming it
        sol = sm.simulate(H, (q, v), 1.0, throw=False)
        assert sol.result == sm.RESULTS.nonfinite_initial
        with pytest.raises(RuntimeError, match="Legendre transform that is not invertible"):
            sm.simulate(H, (q, v), 1.0)


def test_nan_hamiltonian(state):
    q, v = state
    H = sm.Hamiltonian(lambda t, q, p, args: jnp.sum(p**2) * jnp.log(-1.0))
    with pytest.raises(eqx.EquinoxRuntimeError, match="Hamilton's equations are not finite"):
        H.vector_field(0.0, q, v, None)


@pytest.mark.parametrize(
    "masses, lengths",
    [([1.0, 0.0], [1.0, 1.0]), ([0.0, 1.0], [1.0, 1.0]), ([1.0, 1.0], [1.0, 0.0])],
)
def test_degenerate_chain(masses, lengths, state):
    """Refused at construction (as a chain and as a constant-inertia system); built from
    traced values, singular at run time, with a message that says so."""
    q, v = state
    with pytest.raises(ValueError, match=r"(masses|lengths) must be > 0"):
        sm.chain_pendulum(jnp.array(masses), jnp.array(lengths))
    m, lengths = jnp.array(masses), jnp.array(lengths)
    M = jnp.outer(lengths, lengths) * jnp.cumsum(m[::-1])[::-1][jnp.maximum(*jnp.indices((2, 2)))]
    potential = lambda t, q, args: -9.81 * q[0, 2]
    with pytest.raises(ValueError, match="inertia must be a symmetric positive-definite"):
        sm.ConstantInertiaLagrangian(M, potential)
    # Built from traced values (not checked then), it is singular at run time.
    fast = lambda M: sm.ConstantInertiaLagrangian(M, potential).acceleration(0.0, q, v)
    with pytest.raises(eqx.EquinoxRuntimeError, match=SINGULAR):
        eqx.filter_jit(fast)(M)


def test_chain_constructor():
    with pytest.raises(ValueError, match="must be a scalar or 3 values, one per sphere"):
        sm.chain_pendulum(jnp.ones(2), jnp.ones(3))
    with pytest.raises(ValueError, match="g must be a scalar"):
        sm.chain_pendulum(jnp.ones(2), jnp.ones(2), g=jnp.ones(3))
    with pytest.raises(ValueError, match=r"force must be a \(3,\) vector"):
        sm.chain_pendulum(jnp.ones(2), jnp.ones(2), tip_force=jnp.ones(2))
    with pytest.raises(ValueError, match=r"inertia must be a square \(n, n\) matrix"):
        sm.ConstantInertiaLagrangian(jnp.ones((2, 3)), lambda t, q, args: 0.0)


def test_inertia_function(state):
    """An inertia function's matrix is traced: one of the wrong shape is refused at trace
    time, and a nonsymmetric one gives `Lagrangian(L)`'s accelerations for the same `L`
    (its symmetric part; before, the Cholesky solve read its lower half)."""
    q, v = state
    M = jnp.array([[2.0, 1.5], [-0.5, 1.0]])
    U = lambda t, q, args: 9.81 * jnp.sum(q[:, 2])
    T = lambda qdot: 0.5 * jnp.sum(M * (qdot @ qdot.T))
    general = sm.Lagrangian(lambda t, q, qdot, args: T(qdot) - U(t, q, args))
    fast = sm.ConstantInertiaLagrangian(lambda args: M, U)
    np.testing.assert_allclose(
        fast.acceleration(0.0, q, v), general.acceleration(0.0, q, v), rtol=1e-12, atol=1e-12
    )
    wrong = sm.ConstantInertiaLagrangian(lambda args: jnp.eye(3), U)
    message = r"must be a \(2, 2\) matrix, one row for each of the 2 points, got shape \(3, 3\)"
    with pytest.raises(ValueError, match=message):
        wrong.acceleration(0.0, q, v)


def test_errors_through_simulate(state):
    q, v = state
    with pytest.raises(ValueError, match=r"y0 must be a pair \(q0, v0\)"):
        sm.simulate(SYSTEM, q, 1.0)
    with pytest.raises(ValueError, match=r"qdot must have the same shape as q"):
        sm.simulate(SYSTEM, (q, v[:1]), 1.0)
    # Concrete initial states are checked before tracing: a ValueError whose message is
    # the problem itself (not equinox's "Above is the stack outside of JIT").
    with pytest.raises(ValueError, match=f"^simulate: {NOT_UNIT}"):
        sm.simulate(SYSTEM, (1.1 * q, v), 1.0)
    with pytest.raises(ValueError, match="^simulate: qdot is not tangent"):
        sm.simulate(SYSTEM, (q, v + 0.1 * q), 1.0)
    with pytest.raises(ValueError, match="^simulate: q contains NaN"):
        sm.simulate(SYSTEM, (q.at[0, 0].set(jnp.nan), v), 1.0)
    # Traced (inside jit), the same words from equinox's runtime check.
    with pytest.raises(eqx.EquinoxRuntimeError, match="q contains NaN"):
        eqx.filter_jit(sm.simulate)(SYSTEM, (q.at[0, 0].set(jnp.nan), v), 1.0)
    degenerate = sm.Lagrangian(L_first_sphere_only)
    with pytest.raises(RuntimeError, match="equations of motion are not finite at the initial"):
        sm.simulate(degenerate, (q, v), 1.0)
    sol = sm.simulate(degenerate, (q, v), 1.0, throw=False)  # a run-time failure: a code
    assert sol.result == sm.RESULTS.nonfinite_initial


def test_functions_and_inertia_checked_at_construction():
    """A system where L is expected, an L or H of the wrong arity, a negative inertia:
    refused when the system is built, naming the argument; partials and *args pass."""
    import functools

    hamiltonian = sm.Hamiltonian(lambda t, q, mu, args: 0.5 * jnp.sum(mu**2))
    with pytest.raises(
        ValueError,
        match=r"^L must be a function L\(t, q, qdot, args\), got "
        r"Hamiltonian\.$",
    ):
        sm.Lagrangian(hamiltonian)
    # the reverse: a bare function where a system is expected (angular: an AttributeError)
    L = lambda t, q, qdot, args: 0.5 * jnp.sum(qdot**2)
    with pytest.raises(TypeError, match=r"^angular\(\) takes a Lagrangian or Hamiltonian system"):
        sm.angular(L)
    with pytest.raises(TypeError, match=r"^legendre\(\) takes a Lagrangian system"):
        sm.legendre(L)
    with pytest.raises(
        ValueError,
        match=r"^L must be a function L\(t, q, qdot, args\) \(4 "
        r"arguments\), got one with signature \(t, q, qdot\)\.$",
    ):
        sm.Lagrangian(lambda t, q, qdot: 0.0)
    with pytest.raises(ValueError, match=r"^H must be a function H\(t, q, pi, args\)"):
        sm.AngularHamiltonian(lambda q, pi: 0.0)
    with pytest.raises(
        ValueError,
        match=r"^inertia must be a symmetric positive-definite "
        r"matrix \(got smallest eigenvalue -1",
    ):
        sm.ConstantInertiaLagrangian(-jnp.eye(2), lambda t, q, args: 0.0)
    with pytest.raises(ValueError, match=r"^potential must be a function U\(t, q, args\)"):
        sm.ConstantInertiaLagrangian(jnp.eye(2), lambda t, q: 0.0)
    # forces too (an array or a 3-argument function failed only inside the solve)
    L = lambda t, q, qdot, args: 0.5 * jnp.sum(qdot**2)
    message = r"^forces must be a function forces\(t, q, qdot, args\) -> \(n, 3\)"
    with pytest.raises(ValueError, match=message + r", got ArrayImpl\.$"):
        sm.Lagrangian(L, jnp.array([[0.0, 0.0, 1.0]]))
    with pytest.raises(ValueError, match=message + r" \(4 arguments\)"):
        sm.Lagrangian(L, lambda t, q, qdot: qdot)
    with pytest.raises(ValueError, match=r"^forces must be a function forces\(t, q, mu, args\)"):
        sm.Hamiltonian(lambda t, q, mu, args: 0.5 * jnp.sum(mu**2), forces=1.0)
    with pytest.raises(ValueError, match=message):
        sm.ConstantInertiaLagrangian(jnp.eye(2), lambda t, q, args: 0.0, "drag")
    # H's value is checked by energy too
    vector_H = sm.Hamiltonian(lambda t, q, mu, args: mu[0])
    with pytest.raises(ValueError, match=r"H\(t, q, p, args\) must return a scalar"):
        vector_H.energy(0.0, jnp.array([[0.0, 0.0, 1.0]]), jnp.zeros((1, 3)))
    sm.Lagrangian(functools.partial(lambda t, q, qdot, args, k: k, k=1.0))
    sm.Lagrangian(lambda *a: 0.0)
    # Traced inertia (e.g. under vmap) is left to the run-time checks.
    eqx.filter_vmap(lambda m: sm.ConstantInertiaLagrangian(m, lambda t, q, a: 0.0))(
        jnp.stack([jnp.eye(2), -jnp.eye(2)])
    )


def test_nan_parameter_is_named_not_the_mass_matrix(state):
    q, v = state
    system = sm.Lagrangian(lambda t, q, qdot, g: 0.5 * jnp.sum(qdot**2) - g * jnp.sum(q[:, 2]))
    with pytest.raises(
        eqx.EquinoxRuntimeError,
        match="args or the system's parameters contain NaN or infinite values",
    ):
        system.acceleration(0.0, q, v, jnp.asarray(jnp.nan))
    with pytest.raises(eqx.EquinoxRuntimeError, match="args or the system's parameters"):
        sm.Hamiltonian(lambda t, q, mu, g: g * jnp.sum(mu**2)).vector_field(0.0, q, v, jnp.inf)


def test_forward_mode_without_forward_adjoint_says_what_to_pass():
    """`jax.jacfwd` through `simulate` and `simulate_batch` with the default (reverse-mode)
    adjoint, or with a reverse-mode adjoint the user passed, names that adjoint and the fix,
    `adjoint=diffrax.ForwardMode()`, instead of JAX's bare "can't apply forward-mode
    autodiff (jvp) to a custom_vjp function"; with it, it works."""
    import diffrax

    system = sm.Lagrangian(lambda t, q, v, g: 0.5 * jnp.sum(v * v) - g * q[0, 2])
    q0, v0 = jnp.array([[1.0, 0.0, 0.0]]), jnp.array([[0.0, 1.0, 0.0]])

    def final(g, adjoint=None):
        return sm.simulate(system, (q0, v0), 0.2, args=g, adjoint=adjoint).ys[0][-1, 0, 0]

    def batch_final(g):
        y0 = (q0[None], v0[None])
        return sm.simulate_batch(system, y0, 0.2, args=g[None]).ys[0][0, -1, 0, 0]

    for f in (final, batch_final):
        with pytest.raises(
            TypeError,
            match=r"needs adjoint=diffrax\.ForwardMode\(\); the default adjoint is reverse mode",
        ):
            jax.jacfwd(f)(jnp.asarray(9.81))
    chosen = diffrax.RecursiveCheckpointAdjoint()  # a reverse-mode adjoint the user chose
    with pytest.raises(TypeError, match=r"; adjoint=RecursiveCheckpointAdjoint\(\) is reverse"):
        jax.jacfwd(lambda g: final(g, chosen))(jnp.asarray(9.81))
    forward = jax.jacfwd(lambda g: final(g, diffrax.ForwardMode()))(jnp.asarray(9.81))
    assert jnp.isfinite(forward)


def test_flags_must_be_bools(state):
    """A non-bool flag is refused, naming it: a string such as "no" is truthy, so
    `quadratic_in_velocity="no"` gave a wrong Legendre map, `progress="no"` a progress
    bar and `throw="no"` raised. simulate and simulate_batch check with the same words."""
    q, v = state
    flag = r"^quadratic_in_velocity must be True or False, got "
    with pytest.raises(ValueError, match=flag + r"'no'\.$"):
        sm.Lagrangian(L, quadratic_in_velocity="no")
    with pytest.raises(ValueError, match=flag + r"0\.0\.$"):
        sm.AngularLagrangian(L, quadratic_in_velocity=0.0)
    assert sm.Lagrangian(L, quadratic_in_velocity=np.bool_(True)).quadratic_in_velocity is True
    batch = (q[None], v[None])
    for name in ("progress", "throw"):
        message = rf"^{name} must be True or False, got 'no'\.$"
        with pytest.raises(ValueError, match=message):
            sm.simulate(SYSTEM, (q, v), 1.0, **{name: "no"})
        with pytest.raises(ValueError, match=message):
            sm.simulate_batch(SYSTEM, batch, 1.0, **{name: "no"})


def test_velocity_from_momentum_options(state):
    """The inverse Legendre map's options are checked: a negative `tol` returned a wrong
    velocity with a success code, a zero `max_steps` NaN, a `guess` of the wrong shape
    an einsum error."""
    q, v = state
    system = sm.Lagrangian(lambda t, q, qdot, a: L(t, q, qdot, a) + 0.1 * jnp.sum(qdot**4))
    chain = sm.ConstantInertiaLagrangian(jnp.eye(2), lambda t, q, args: jnp.sum(q[:, 2]))
    mu = system.momentum(0.0, q, v)
    bad = [
        (dict(tol=-1.0), r"^tol must be a finite number > 0, got -1\.0\.$"),
        (dict(tol=0.0), r"^tol must be a finite number > 0, got 0\.0\.$"),
        (dict(tol=float("nan")), r"^tol must be a finite number > 0, got nan\.$"),
        (dict(tol=1.0), r"^tol must be a finite number in \(0, 1\) \(relative\), got 1\.0\.$"),
        (dict(max_steps=0), r"^max_steps must be a positive integer, got 0\.$"),
        (dict(max_steps=-1), r"^max_steps must be a positive integer, got -1\.$"),
        (dict(quadratic="no"), r"^quadratic must be True or False, got 'no'\.$"),
        (
            dict(guess=jnp.ones(3)),
            r"^guess must have the shape of the momentum p \(the state's\), \(2, 3\), got \(3,\)",
        ),
    ]
    for s in (system, chain):
        for options, message in bad:
            with pytest.raises(ValueError, match=message):
                s.velocity_from_momentum(0.0, q, mu, **options)
    back, result = system.velocity_from_momentum(0.0, q, mu, guess=v, tol=1e-12, max_steps=8)
    assert float(jnp.max(jnp.abs(back - v))) < 1e-10
    assert sm.RESULTS.promote(result) == sm.RESULTS.successful  # as its docstring says


def test_velocity_from_momentum_codes(state):
    """`successful` on the general path and the constant-inertia fast path, `singular` for
    a degenerate `L`: diffrax's codes, which `sm.RESULTS.promote` turns into ours."""
    q, v = state
    chain = sm.ConstantInertiaLagrangian(jnp.eye(2), lambda t, q, args: jnp.sum(q[:, 2]))
    for system in (SYSTEM, chain):
        back, result = system.velocity_from_momentum(0.0, q, system.momentum(0.0, q, v))
        assert sm.RESULTS.promote(result) == sm.RESULTS.successful
        assert float(jnp.max(jnp.abs(back - v))) < 1e-10
    degenerate = sm.Lagrangian(L_first_sphere_only, quadratic_in_velocity=True)
    _, result = degenerate.velocity_from_momentum(0.0, q, v)
    assert sm.RESULTS.promote(result) == sm.RESULTS.singular


def test_float32_state_with_float64_forces():
    """A float32 state under x64 whose forces return float64 (a float64 constant, or a
    NumPy float64 time): the forces are called with the time in the state's dtype and
    cast to it, so simulate runs in float32 (it raised diffrax's dtype error),
    acceleration works (a jvp TypeError) and legendre's momentum rate stays float32."""
    U = lambda t, q, args: 9.81 * jnp.sum(q[:, 2])
    lift = jnp.array([0.0, 0.0, 1.0])  # float64 under x64
    force = lambda t, q, qdot, args: -0.2 * qdot + jnp.sin(t) * lift
    system = sm.Lagrangian(lambda t, q, qdot, args: 0.5 * jnp.sum(qdot**2) - U(t, q, args), force)
    q, v = sm.random_state(jax.random.PRNGKey(2), 1, dtype=jnp.float32)
    sol = sm.simulate(system, (q, v), 0.05)
    assert sol.ys[0].dtype == sol.ys[1].dtype == jnp.float32
    assert bool(jnp.all(jnp.isfinite(sol.ys[1])))
    for t in (np.float64(0.5), 0.5):
        assert system.acceleration(t, q, v).dtype == jnp.float32
    rates = sm.legendre(system).vector_field(np.float64(0.5), q, system.momentum(0.0, q, v))
    assert rates[0].dtype == rates[1].dtype == jnp.float32


def test_function_where_a_system_is_expected(state):
    """A bare L (or a system's class) passed as the system: a TypeError saying what to wrap
    it in, from simulate, simulate_batch and MechanicsTerm (an AttributeError from deep
    inside, or for MechanicsTerm only inside diffeqsolve)."""
    q, v = state
    bare = lambda t, q, qdot, args: 0.5 * jnp.sum(qdot**2)
    wrap = r"takes a mechanical system, an instance such as sm\.Lagrangian\(L\), "
    wrap += r"sm\.Hamiltonian\(H\) or a Scene \(wrap a bare function L or H in one\), got "
    with pytest.raises(TypeError, match=rf"^simulate {wrap}function\.$"):
        sm.simulate(bare, (q, v), 1.0)
    with pytest.raises(TypeError, match=rf"^simulate {wrap}the class Lagrangian\.$"):
        sm.simulate(sm.Lagrangian, (q, v), 1.0)
    with pytest.raises(TypeError, match=rf"^simulate_batch {wrap}function\.$"):
        sm.simulate_batch(bare, (q[None], v[None]), 1.0)
    with pytest.raises(TypeError, match=rf"^MechanicsTerm {wrap}function\.$"):
        sm.MechanicsTerm(bare)


def test_lists_at_the_state_functions(state):
    """`energy`, `momentum` and `velocity` read nested lists as arrays too, in every form
    (`energy` and `momentum` raised an AttributeError from inside `jax.grad`)."""
    q, v = state
    systems = dict(
        qdot=SYSTEM,
        omega=sm.angular(SYSTEM),
        mu=sm.legendre(SYSTEM),
        pi=sm.legendre(sm.angular(SYSTEM)),
    )
    for name, system in systems.items():
        y = (q, system.from_linear(q, v))
        methods = [system.energy, system.velocity]
        methods += [system.momentum] if name in ("qdot", "omega") else []
        for method in methods:
            expected = method(0.0, *y)
            got = method(0.0, *(x.tolist() for x in y))
            assert isinstance(got, jax.Array), (name, method.__name__)
            assert float(jnp.max(jnp.abs(got - expected))) < 1e-12, (name, method.__name__)


def test_time_and_lists_at_the_vector_fields(state):
    """The vector-field entry points read nested lists as arrays, as simulate does (they
    raised "Cannot determine dtype"), and refuse a time that is not a real scalar (a
    string "2" was read as 2.0, True as 1.0)."""
    q, v = state
    for name, fn in all_forms(SYSTEM).items():
        expected = fn(0.0, q, v)
        got = fn(0.0, q.tolist(), v.tolist())
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expected), strict=True):
            assert float(jnp.max(jnp.abs(a - b))) < 1e-12, name
        for t, shown in (("2", "'2'"), (True, "True"), (None, "None")):
            with pytest.raises(ValueError, match=rf"^t must be a real scalar time, got {shown}\.$"):
                fn(t, q, v)
        with pytest.raises(ValueError, match=r"^t must be a real scalar time, got Array"):
            fn(jnp.zeros(2), q, v)
