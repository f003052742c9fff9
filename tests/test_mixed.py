"""Mixed configuration spaces R^m x (S^2)^n: a point-mass base (a cart on a line, a point
in space) carrying a chain of point masses, against an independent reference (in
helpers.py): Cartesian coordinates with the link lengths imposed by Lagrange multipliers
(the index-1 DAE reduced to an ODE by solving for the multipliers), integrated by
scipy's DOP853 at tight tolerances."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import (
    T1,
    TIGHT,
    TS,
    G,
    MixedModel,
    assert_energy_balance,
    assert_forms_agree,
    cart_pendulum,
    fixed_steps,
    flying_chain,
    max_rel_error,
    mixed_angular,
    mixed_initial_state,
    random_forces,
    random_lagrangian,
    random_params,
    steps_taken,
)

import sphere_mech as sm
from sphere_mech._solvers.discrete_mechanics import substep

# The models (`MixedModel`: `cart_pendulum`, `flying_chain`) and their Cartesian reference
# live in helpers.py, shared with test_base_scenes.


@pytest.fixture(scope="module")
def tight_runs():
    """The forced cart pendulum and the unforced flying chain, at tight tolerances
    (each compiled once; the Lie-group tests run the forced flying chain and cart)."""
    out = {}
    for make, forced in ((cart_pendulum, True), (flying_chain, False)):
        model = make()
        y0 = mixed_initial_state(model, seed=int(forced))
        system = model.system(forced=forced)
        out[make.__name__] = (model, system, forced, y0, sm.simulate(system, y0, T1, **TIGHT))
    return out


@pytest.mark.parametrize("name", ["cart_pendulum", "flying_chain"])
def test_against_cartesian_reference(tight_runs, name):
    """Positions of the base and of every mass agree to 1e-8 over 2 s (the cart driven,
    the flying chain free)."""
    model, _, forced, (q0, v0), sol = tight_runs[name]
    q, v = sol.ys
    assert set(q) == {"base", "chain"} and q["chain"].shape == (len(TS), model.n, 3)
    x_ref, r_ref = model.reference(q0, v0, forced=forced)
    r = jax.jit(jax.vmap(model.positions))(q)
    assert np.max(np.abs(q["base"] - x_ref)) < 1e-8
    assert np.max(np.abs(r - r_ref)) < 1e-8
    assert sm.constraint_error(q["chain"]) < 1e-12


def test_energy_conserved_without_forces(tight_runs):
    model, system, _, (q0, v0), sol = tight_runs["flying_chain"]
    energy = jax.jit(jax.vmap(lambda q, v: system.energy(0.0, q, v)))(*sol.ys)
    assert np.ptp(energy) < 1e-9 * (1 + abs(float(energy[0])))
    # Independent energy: kinetic plus potential of the Cartesian positions.
    q, v = q0, v0
    r, rd = model.positions(q), model.positions(v)
    xb, vb = model.E @ q["base"], model.E @ v["base"]
    masses = model.masses
    T = 0.5 * model.M * vb @ vb + 0.5 * np.sum(masses * np.sum(rd**2, axis=-1))
    U = G * (model.M * xb[2] + masses @ r[:, 2])
    assert abs(float(system.energy(0.0, q, v)) - float(T + U)) < 1e-12 * (1 + abs(T + U))


def test_momentum_and_forces_per_factor():
    """The Euclidean momentum is dL/dxdot unprojected (the cart's: the total linear
    momentum along the line); the sphere momentum is projected; forces and power."""
    model = cart_pendulum()
    system = model.system(forced=True)
    q, v = mixed_initial_state(model, seed=2)
    mu = system.momentum(0.0, q, v)
    m, M, length = model.masses[0], model.M, model.lengths[0]
    expected = (M + m) * v["base"][0] + m * length * v["chain"][0, 0]
    assert abs(float(mu["base"][0]) - expected) < 1e-13 * (1 + abs(expected))
    assert abs(float(jnp.sum(mu["chain"] * q["chain"]))) < 1e-13
    t = 0.3
    f = system.generalized_force(t, q, v)
    assert float(system.power(t, q, v)) == pytest.approx(
        float(f["base"][0] * v["base"][0]), rel=1e-14
    )


def test_simulate_batch_matches_simulate():
    model = cart_pendulum()
    system = model.system(forced=True)
    states = [mixed_initial_state(model, seed=s) for s in range(3)]
    y0 = jax.tree.map(lambda *xs: jnp.stack(xs), *states)
    opts = dict(solver=sm.Projected(sm.RK4()), dt0=0.01)
    batch = sm.simulate_batch(system, y0, 0.5, **opts)
    for i, s in enumerate(states):
        one = sm.simulate(system, s, 0.5, **opts)
        for a, b in zip(jax.tree.leaves(one.ys), jax.tree.leaves(batch.ys), strict=True):
            np.testing.assert_allclose(b[i], a, rtol=0, atol=1e-13)


# ----------------------------------------------------------------------------------------
# The four forms agree on a random configuration-dependent, time-dependent Lagrangian
# with forces on R^3 x (S^2)^2: the random L and forces of test_forms (in helpers.py),
# read on the stacked rows (x, q_1, q_2).
# ----------------------------------------------------------------------------------------

N_CHAIN = 2
MIXED = {"base": sm.Euclidean(3), "chain": sm.Spheres(N_CHAIN)}
TOL = 1e-12


def pack(q):
    return jnp.concatenate([q["base"][None], q["chain"]])


def unpack(rows):
    return {"base": rows[0], "chain": rows[1:]}


def mixed_lagrangian(t, q, qdot, p):
    return random_lagrangian(t, pack(q), pack(qdot), p)


def mixed_forces(t, q, qdot, p):
    return unpack(random_forces(t, pack(q), pack(qdot), p))


MIXED_LAG = sm.Lagrangian(
    mixed_lagrangian, forces=mixed_forces, quadratic_in_velocity=True, space=MIXED
)
MIXED_FORMS = dict(
    lag=MIXED_LAG,
    ang=sm.angular(MIXED_LAG),
    ham=sm.legendre(MIXED_LAG),
    ang_ham=sm.legendre(sm.angular(MIXED_LAG)),
    ham_ang=sm.angular(sm.legendre(MIXED_LAG)),
    ham_newton=sm.legendre(MIXED_LAG, quadratic=False),
)


@pytest.mark.parametrize("seed,t", [(0, 0.3), (1, -1.2), (2, 1.7)])
def test_four_forms_agree_on_mixed_space(seed, t):
    q0, v0 = mixed_initial_state(
        MixedModel(1.0, [1.0] * N_CHAIN, [1.0] * N_CHAIN, np.eye(3), None), seed=seed
    )
    p = random_params(seed, N_CHAIN + 1)
    t = jnp.asarray(t, dtype=jnp.float64)
    ref, out = assert_forms_agree(MIXED_FORMS, t, q0, v0, p, TOL, angular=mixed_angular)
    dL_dt = float(ref["dL_dt"])
    assert abs(float(out["lag"]["power"])) > 1e-3 and abs(dL_dt) > 1e-3  # not vacuous
    assert_energy_balance(ref, out, TOL)  # dE/dt = power - dL/dt in every form
    # the Euclidean momentum is dL/dxdot, unprojected
    dL_dv = jax.grad(mixed_lagrangian, argnums=2)(t, q0, v0, p)
    assert max_rel_error(MIXED_LAG.momentum(t, q0, v0, p)["base"], dL_dv["base"]) < 1e-15


# ----------------------------------------------------------------------------------------
# Solvers: LieRK translates the base and rotates the spheres; Variational imposes
# multipliers on the spheres only.
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make,solver",
    [
        (cart_pendulum, sm.LieRK(sm.RK4(), action="SO3xR3")),
        (flying_chain, sm.LieRK(diffrax.Dopri8())),
    ],
)
def test_lie_group_solvers_against_reference(make, solver):
    """LieRK(RK4) with SO(3) x R^3 on the spheres and LieRK(Dopri8) (SE(3)): positions to 1e-8,
    |q_i| = 1 to rounding without any projection of q."""
    model = make()
    q0, v0 = mixed_initial_state(model)
    sol = sm.simulate(
        model.system(forced=True),
        (q0, v0),
        T1,
        solver=solver,
        rtol=1e-12,
        atol=1e-12,
        saveat=diffrax.SaveAt(steps=True),
    )
    keep = np.isfinite(np.asarray(sol.ts))  # the accepted steps
    q = jax.tree.map(lambda x: x[keep], sol.ys[0])
    ts = np.asarray(sol.ts)[keep]
    x_ref, r_ref = model.reference(q0, v0, forced=True, ts=np.concatenate([[0.0], ts]))
    assert np.max(np.abs(q["base"] - x_ref[1:])) < 1e-8
    assert np.max(np.abs(jax.jit(jax.vmap(model.positions))(q) - r_ref[1:])) < 1e-8
    assert sm.constraint_error(q["chain"]) < 1e-13


@pytest.mark.slow  # 30 s; bounded energy and reversibility stay in test_variational and
# test_rotations, the forced step's order 2 in test_variational_forced_converges_to_reference
def test_variational_energy_bounded_and_reversible():
    """The unforced cart pendulum: 2000 steps of h = 0.02 keep the energy error bounded
    and O(h^2) (no drift), |q| = 1 to rounding; stepping back returns the initial state.
    With the drive, the forced integrator converges to the reference at order 2."""
    model = cart_pendulum()
    system = model.system(forced=False)
    y0 = mixed_initial_state(model, seed=3)
    sol = fixed_steps(
        system, sm.Variational(), 0.02, y0, t1=40.0, saveat=diffrax.SaveAt(steps=True)
    )
    t, (q, v) = steps_taken(sol)
    assert len(t) == 2000
    energy = np.asarray(jax.jit(jax.vmap(lambda q, v: system.energy(0.0, q, v)))(q, v))
    error = energy - float(system.energy(0.0, *y0))
    t = np.asarray(t)
    assert np.max(np.abs(error)) < 1e-2 * abs(float(energy[0]))
    slope = np.polyfit(t, error, 1)[0]
    assert abs(slope * t[-1]) < 0.1 * np.max(np.abs(error))
    assert sm.constraint_error(q["chain"]) < 1e-14
    end = jax.tree.map(lambda x: x[int(0.5 / 0.02) - 1], sol.ys)  # t = 0.5
    back = fixed_steps(system, sm.Variational(), -0.02, end, t0=0.5, t1=0.0)
    for a, b in zip(jax.tree.leaves(back.ys), jax.tree.leaves(y0), strict=True):
        np.testing.assert_allclose(a[-1], b, rtol=0, atol=1e-12)


def test_variational_forced_converges_to_reference():
    model = cart_pendulum()
    y0 = mixed_initial_state(model, seed=4)
    x_ref, r_ref = model.reference(*y0, forced=True, ts=np.array([0.0, 0.5]))
    errors = []
    for h in (0.01, 0.005):
        q = fixed_steps(model.system(forced=True), sm.Variational(), h, y0, t1=0.5).ys[0]
        errors.append(np.max(np.abs(model.positions(jax.tree.map(lambda x: x[-1], q)) - r_ref[-1])))
    assert errors[1] < 1e-3
    assert 3.5 < errors[0] / errors[1] < 4.5  # order 2


def test_variational_symplectic_on_mixed_space():
    """The pullback of dx ^ dp_x + sum dq_i ^ dmu_i is preserved by a step."""
    model = cart_pendulum()
    system = model.system(forced=False)
    q, qdot = mixed_initial_state(model, seed=5)
    mu = system.momentum(0.0, q, qdot)

    def flow(q, mu):
        t = jnp.asarray(0.0)
        v, _ = system.velocity_from_momentum(t, q, mu, None, tol=1e-12, max_steps=16)
        y = (q, v)
        y, _, _ = substep(system, t, 0.1, *y, system.rates(t, y, None), None, 1e-12, 16)
        return y[0], system.momentum(t, y[0], y[1])

    zero = jax.tree.map(jnp.zeros_like, q)
    T = sm.tangent_basis(q["chain"][0])
    vectors = [({**zero, "base": jnp.ones(1)}, zero), (zero, {**zero, "base": jnp.ones(1)})]
    for b in range(2):
        dq = T[:, b][None]
        dmu = -jnp.dot(T[:, b], mu["chain"][0]) * q["chain"]
        vectors.append(({**zero, "chain": dq}, {**zero, "chain": dmu}))
        vectors.append((zero, {**zero, "chain": dq}))
    eps = 1e-6
    points = [
        jax.tree.map(lambda a, d, s=s: a + s * eps * d, (q, mu), u)
        for s in (1.0, -1.0)
        for u in vectors
    ]
    moved = jax.jit(jax.vmap(flow))(*jax.tree.map(lambda *x: jnp.stack(x), *points))
    m = len(vectors)
    pushed = [jax.tree.map(lambda x, i=i: (x[i] - x[m + i]) / (2 * eps), moved) for i in range(m)]

    def omega(u, w):
        return sum(
            jnp.sum(a * b)
            for a, b in zip(jax.tree.leaves(u[0]), jax.tree.leaves(w[1]), strict=True)
        ) - sum(
            jnp.sum(a * b)
            for a, b in zip(jax.tree.leaves(u[1]), jax.tree.leaves(w[0]), strict=True)
        )

    before = np.array([[omega(a, b) for b in vectors] for a in vectors])
    after = np.array([[omega(a, b) for b in pushed] for a in pushed])
    assert np.max(np.abs(before)) > 0.5
    assert np.max(np.abs(after - before)) < 1e-7


# ----------------------------------------------------------------------------------------
# Gradients through simulate on a mixed system, against finite differences.
# ----------------------------------------------------------------------------------------


def cart_lagrangian(t, q, qdot, args):
    M, m, length = args
    x, xd, p, pd = q["cart"][0], qdot["cart"][0], q["bob"][0], qdot["bob"][0]
    bob_v = jnp.array([xd, 0.0, 0.0]) + length * pd
    bob_z = length * p[2]
    return 0.5 * M * xd**2 + 0.5 * m * bob_v @ bob_v - m * G * bob_z + 0.0 * x


def test_gradient_through_simulate_matches_finite_differences():
    system = sm.Lagrangian(cart_lagrangian, space={"cart": sm.Euclidean(1), "bob": sm.Spheres(1)})
    q0 = {"cart": jnp.zeros(1), "bob": sm.normalize(jnp.array([[1.0, 0.0, -1.0]]))}
    v0 = {"cart": jnp.array([0.3]), "bob": jnp.zeros((1, 3))}

    def final_x(args):
        sol = sm.simulate(system, (q0, v0), 1.0, args=args, solver=sm.Projected(sm.RK4()), dt0=0.01)
        return sol.ys[0]["cart"][-1, 0]

    args = jnp.array([1.5, 0.7, 0.8])
    grad = jax.grad(final_x)(args)
    eps = 1e-6
    fd = [
        (final_x(args.at[i].add(eps)) - final_x(args.at[i].add(-eps))) / (2 * eps) for i in range(3)
    ]
    np.testing.assert_allclose(grad, np.array(fd), rtol=1e-6, atol=1e-9)
    assert np.min(np.abs(np.array(fd))) > 1e-3


# ----------------------------------------------------------------------------------------
# Events and fit on a mixed space, against the Cartesian reference.
# ----------------------------------------------------------------------------------------


def test_event_stops_at_cart_position(tight_runs):
    """The forced cart stops where it reaches the position it had at t = 0.5 (`q` a dict
    in the event function); at the event time the reference cart is there and the bob
    agrees with the reference."""
    model, system, forced, (q0, v0), sol = tight_runs["cart_pendulum"]
    target = float(sol.ys[0]["base"][5, 0])  # TS[5] = 1.0
    hit = lambda t, y, args, **kw: y[0]["base"][0] - target
    newton = optx.Newton(rtol=1e-13, atol=1e-13)
    out = sm.simulate(
        system,
        (q0, v0),
        T1,
        solver=TIGHT["solver"],
        rtol=1e-12,
        atol=1e-12,
        event=diffrax.Event(hit, root_finder=newton),
    )
    assert out.result == sm.RESULTS.event_occurred
    t_event = float(out.ts[-1])
    assert 0.0 < t_event <= 1.0 + 1e-9
    x_ref, r_ref = model.reference(q0, v0, forced=forced, ts=np.array([0.0, t_event]))
    assert abs(x_ref[-1, 0] - target) < 1e-8
    q_end = jax.tree.map(lambda x: x[-1], out.ys[0])
    assert abs(float(q_end["base"][0]) - target) < 1e-10
    assert np.max(np.abs(model.positions(q_end) - r_ref[-1])) < 1e-8


CART_LENGTH = 0.8
FIT_TS = np.linspace(0.0, 1.5, 16)


def cart_system(params):
    """The driven cart pendulum of `cart_pendulum()` with the cart mass `M` and the bob
    mass `m` as parameters (written out: the cart on the x axis, the bob at
    `x e_x + l q`)."""

    def lagrangian(t, q, qdot, args):
        u, ud = q["chain"][0], qdot["chain"][0]
        bob_v = qdot["base"][0] * jnp.array([1.0, 0.0, 0.0]) + CART_LENGTH * ud
        kinetic = 0.5 * params["M"] * qdot["base"][0] ** 2 + 0.5 * params["m"] * bob_v @ bob_v
        return kinetic - params["m"] * G * CART_LENGTH * u[2]

    forces = lambda t, q, qdot, args: {
        "base": 2.0 * jnp.sin(3.0 * t) * jnp.ones(1),
        "chain": jnp.zeros_like(q["chain"]),
    }
    return sm.Lagrangian(lagrangian, forces, space=cart_pendulum().space)


def observe_cart(system, t, q, v):
    """The cart's position and the bob's position."""
    bob = q["base"][0] * jnp.array([1.0, 0.0, 0.0]) + CART_LENGTH * q["chain"][0]
    return jnp.concatenate([q["base"], bob])


@pytest.fixture(scope="module")
def cart_data():
    """Noise-free observations of the cart pendulum (M = 1.5, m = 0.7) from the Cartesian
    reference."""
    model = cart_pendulum()
    y0 = mixed_initial_state(model, seed=3)
    x_ref, r_ref = model.reference(*y0, forced=True, ts=FIT_TS)
    return y0, np.concatenate([x_ref, r_ref[:, 0]], axis=1)


# single shooting is the same code as one segment of two (slow set: about 1 min)
@pytest.mark.parametrize("segments", [pytest.param(1, marks=pytest.mark.slow), 2])
def test_fit_recovers_masses_on_mixed_space(cart_data, segments):
    """`fit` recovers the cart and bob masses (started 30-40 % off) from the observed cart
    and bob positions, single and multiple shooting."""
    y0, obs = cart_data
    result = sm.fit(
        cart_system,
        {"M": 1.0, "m": 1.0},
        FIT_TS,
        obs,
        observe_cart,
        y0=y0,
        segments=segments,
        positive=True,
        simulate_options=dict(rtol=1e-10, atol=1e-10),
    )
    assert bool(result.converged)
    assert abs(float(result.params["M"]) / 1.5 - 1) < 1e-2
    assert abs(float(result.params["m"]) / 0.7 - 1) < 1e-2
    q, v = result.segment_states
    assert q["base"].shape == (segments, 1) and v["chain"].shape == (segments, 1, 3)
    # d = 1 + 2 tangent coordinates: 2d = 6 per junction and per fitted state
    assert result.dof == obs.size - 2
    assert result.jacobian.shape[1] == 2 + (segments - 1) * 6


# ----------------------------------------------------------------------------------------
# Bad input raises a clear error.
# ----------------------------------------------------------------------------------------


def test_bad_mixed_input_raises():
    model = cart_pendulum()
    system = model.system(forced=False)
    q0, v0 = mixed_initial_state(model)
    acc = lambda q, v: system.acceleration(0.0, q, v)
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"q\['chain'\] is not on the spheres"):
        acc({**q0, "chain": 1.1 * q0["chain"]}, v0)
    with pytest.raises(ValueError, match=r"^simulate: qdot\['chain'\] is not tangent"):
        sm.simulate(system, (q0, {**v0, "chain": v0["chain"] + 0.1 * q0["chain"]}), 0.1)
    with pytest.raises(ValueError, match=r"q must have the keys of the space.*missing \['base'\]"):
        acc({"chain": q0["chain"]}, v0)
    with pytest.raises(ValueError, match=r"q\['base'\] must have shape \(1,\) \(Euclidean\(1\)\)"):
        sm.simulate(system, ({**q0, "base": jnp.zeros(2)}, v0), 0.1)
    with pytest.raises(ValueError, match=r"q\['chain'\] must have shape \(1, 3\) \(Spheres\(1\)\)"):
        acc({**q0, "chain": sm.random_points(jax.random.PRNGKey(0), 2)}, v0)
    with pytest.raises(ValueError, match=r"q must be a dict with the keys of the space"):
        acc(q0["chain"], v0["chain"])
    with pytest.raises(ValueError, match="space must be a factor"):
        sm.Lagrangian(model.lagrangian, space={"base": 3})
    with pytest.raises(ValueError, match="space must be a factor"):
        sm.Hamiltonian(model.lagrangian, space=[sm.Euclidean(1)])
    with pytest.raises(ValueError, match=r"space must be a factor .*sphere_mech.Rotations\(k\)"):
        sm.Lagrangian(model.lagrangian, space="rot")
    with pytest.raises(ValueError, match="Euclidean\\(m\\): m must be a positive int"):
        sm.Euclidean(0)
    for factor in (sm.Spheres, sm.Euclidean, sm.Rotations):  # a bool is not a count
        with pytest.raises(ValueError, match=r"must be a positive int, got True"):
            factor(True)
    bad_forces = lambda t, q, v, args: {"base": jnp.zeros(1)}
    forced = sm.Lagrangian(model.lagrangian, bad_forces, space=model.space)
    with pytest.raises(ValueError, match=r"forces\(t, q, v, args\) must have the keys"):
        forced.acceleration(0.0, q0, v0)


def test_legendre_quadratic_must_be_a_bool():
    """`legendre(system, quadratic="no")` was accepted, read as true: one linear solve for a
    quartic `L`, a Hamiltonian off the energy by 6e-3. Now only True, False, None (NumPy
    bools too) pass; a wrong one is named when the Hamiltonian is built."""
    L = lambda t, q, v, args: (
        jnp.sum(v**2) + 0.1 * jnp.sum(jnp.sum(v**2, -1) ** 2) - jnp.sum(q[:, 2])
    )
    system = sm.Lagrangian(L)
    q, v = sm.random_state(jax.random.PRNGKey(5), 2, speed=0.8)
    mu = system.momentum(0.0, q, v)
    for flag in ("no", "False", 0, 1.0):
        with pytest.raises(
            ValueError, match=rf"^legendre: quadratic must be True or False, got {flag!r}\.$"
        ):
            sm.legendre(system, quadratic=flag)
    for flag in (None, False, np.False_):
        H = sm.legendre(system, quadratic=flag)
        assert abs(float(H.energy(0.0, q, mu) - system.energy(0.0, q, v))) < 1e-12


def test_factor_counts_may_be_numpy_integers():
    """`Spheres(np.int64(2))`, `Euclidean`, `Rotations` and `chain_space` refused NumPy
    integers (which `random_state` takes); they are stored as Python ints."""
    for factor, field in ((sm.Spheres, "n"), (sm.Euclidean, "m"), (sm.Rotations, "k")):
        built = factor(np.int64(2))
        assert type(getattr(built, field)) is int and built == factor(2)
        for bad in (0, 2.0, np.float64(2.0), "2"):
            with pytest.raises(
                ValueError, match=rf"\({field}\): {field} must be a positive int, got"
            ):
                factor(bad)
    assert sm.chain_space(np.int64(3), np.int32(2)) == sm.chain_space(3, 2)
    assert sm.chain_space(np.int64(3), 2, attitude=np.True_) == sm.chain_space(3, 2, True)
