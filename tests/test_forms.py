"""The four forms of the equations of motion agree on random configuration-dependent,
time-dependent Lagrangians with random forces (hypothesis); terms that vanish on the
tangent bundle change nothing; energy balances the power of the forces in every form.

One family of Lagrangians (helpers.random_lagrangian), with every coefficient passed
through `args`, serves all the tests: each set of systems below compiles once. The
cross-check itself (helpers.assert_forms_agree) serves test_mixed too."""

import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import pytest
from helpers import (
    assert_energy_balance,
    assert_forms_agree,
    evaluate_forms,
    max_rel_error,
    random_forces,
    random_lagrangian,
    random_params,
)
from hypothesis import given, settings

import sphere_mech as sm

SETTINGS = settings(max_examples=8, deadline=None, derandomize=True)
TOL = 1e-12
SEEDS = st.integers(0, 2**31 - 1)
TIMES = st.floats(-2.0, 2.0)


LAG = sm.Lagrangian(random_lagrangian, forces=random_forces, quadratic_in_velocity=True)
LINEAR = dict(  # Legendre transform by one linear solve: valid for quadratic L only
    lag=LAG,
    ang=sm.angular(LAG),
    ham=sm.legendre(LAG),
    ang_ham=sm.legendre(sm.angular(LAG)),
    ham_ang=sm.angular(sm.legendre(LAG)),
)
NEWTON = dict(  # Legendre transform by Newton's method: any L
    lag=LAG,
    ang=sm.angular(LAG),
    ham=sm.legendre(LAG, quadratic=False),
    ang_ham=sm.legendre(sm.angular(LAG), quadratic=False),
)


def state(seed, n, speed=1.0):
    return sm.random_state(jax.random.PRNGKey(seed % 2**32), n, speed=speed)


N_LINEAR, N_NEWTON = 2, 3  # spheres: one compilation per set of systems and n


def as_time(t):
    return jnp.asarray(t, dtype=jnp.float64)  # one dtype and weak type: no recompilation


@SETTINGS
@given(seed=SEEDS, t=TIMES, augment=st.booleans())
def test_four_forms_agree_quadratic(seed, t, augment):
    q, qdot = state(seed, N_LINEAR)
    p = random_params(seed, N_LINEAR, augment=augment)
    assert_forms_agree(LINEAR, as_time(t), q, qdot, p, TOL)


@SETTINGS
@given(seed=SEEDS, t=TIMES, kind=st.sampled_from(["quadratic", "quartic", "relativistic"]))
def test_four_forms_agree_newton(seed, t, kind):
    """Newton's Legendre map, on quadratic and on genuinely non-quadratic Lagrangians."""
    speed = 0.3 if kind == "relativistic" else 1.0  # keeps |qdot_i| < c
    q, qdot = state(seed, N_NEWTON, speed=speed)
    p = random_params(
        seed, N_NEWTON, quartic=kind == "quartic", relativistic=kind == "relativistic"
    )
    assert_forms_agree(NEWTON, as_time(t), q, qdot, p, TOL)


def test_linear_legendre_is_wrong_for_non_quadratic_L():
    """The linear-solve Legendre map is exact only for quadratic L: on the quartic L it
    differs, so the Newton comparison is not vacuous."""
    q, qdot = state(1, N_LINEAR, speed=1.5)
    p = random_params(1, N_LINEAR, quartic=1.0)
    ref, out = evaluate_forms(LINEAR, as_time(0.3), q, qdot, p)
    assert max_rel_error(out["ham"]["rates"][0], qdot) > 1e-3


@SETTINGS
@given(seed=SEEDS, t=TIMES)
def test_terms_vanishing_on_tangent_bundle_change_nothing(seed, t):
    q, qdot = state(seed, N_NEWTON)
    t = as_time(t)
    p, p_aug = (random_params(seed, N_NEWTON, quartic=1.0, augment=a) for a in (0.0, 1.0))
    # the added terms do change L's derivatives (off the tangent directions)
    dL, dL_aug = (jax.grad(random_lagrangian, argnums=2)(t, q, qdot, p_) for p_ in (p, p_aug))
    assert max_rel_error(dL_aug, dL) > 1e-3
    plain, augmented = (evaluate_forms(NEWTON, t, q, qdot, p_) for p_ in (p, p_aug))
    leaves = jax.tree.leaves(plain)
    for a, b in zip(jax.tree.leaves(augmented), leaves, strict=True):
        assert max_rel_error(a, b) < TOL


@SETTINGS
@given(seed=SEEDS, t=TIMES)
def test_energy_balance_forced_time_dependent(seed, t):
    """dE/dt = sum_i f_i . qdot_i - dL/dt along the vector field of every form."""
    q, qdot = state(seed, N_LINEAR)
    ref, out = evaluate_forms(LINEAR, as_time(t), q, qdot, random_params(seed, N_LINEAR))
    assert abs(float(ref["dL_dt"])) > 1e-3
    assert abs(float(out["lag"]["power_method"] - out["lag"]["power"])) < 1e-13
    for o in out.values():
        assert abs(float(o["power"])) > 1e-3
    assert_energy_balance(ref, out, TOL)


@pytest.mark.parametrize("kind", ["quadratic", "quartic"])
def test_energy_conserved_unforced_time_independent(kind):
    q, qdot = state(7, N_NEWTON)
    p = random_params(7, N_NEWTON, quartic=kind == "quartic", time=False, forced=False)
    ref, out = evaluate_forms(NEWTON, as_time(0.7), q, qdot, p)
    assert float(ref["dL_dt"]) == 0.0
    for name, o in out.items():
        assert float(o["power"]) == 0.0
        assert abs(float(o["dE"])) < TOL * (1 + abs(float(o["energy"]))), name
