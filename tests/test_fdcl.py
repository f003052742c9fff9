"""The FDCL quadrotor benchmark (benchmarks/fdcl_quadrotor.py) reproduces the circle run
of Gamagedara, Bisheban, Kaufman and Lee with their decoupled-yaw controller, against the
run they saved (benchmarks/data/fdcl_reference.npz, from their Data/Circle/decoupled.mat).

Tolerance on mean |e_x| (their 0.168595 m): 1e-6 m. Their run is MATLAB's ode45 at rtol =
atol = 1e-6; over the whole run their x is within 8.2e-7 m of ours at 1e-10 (measured by
the benchmark), so their mean |e_x| is within about 1e-6 m of the exact one, and ours here
(LieRK(Tsit5) at 1e-8, measured 2e-8 m from theirs) adds far less. A change of the
controller that matters is far larger: reading `Wc'` from the skew part instead of their
`vee`'s upper triangle moves mean |e_x| by 6e-4 m (checked below)."""

import importlib.util
import sys
from pathlib import Path

import diffrax
import numpy as np
import pytest

import sphere_mech as sm

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
OPTIONS = dict(solver=sm.LieRK(diffrax.Tsit5()), rtol=1e-8, atol=1e-8)


@pytest.fixture(scope="module")
def fdcl():
    sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(
        "fdcl_quadrotor", BENCHMARKS / "fdcl_quadrotor.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def circle(fdcl):
    return fdcl.run("circle", "decoupled", options=OPTIONS)


def test_circle_decoupled_reproduces_their_table(fdcl, circle):
    theirs = fdcl.reference("circle", "decoupled")
    ex, eR, thrust, converged = circle["table"]
    their_ex, their_eR, their_thrust, their_converged = theirs["table"]
    assert abs(their_ex - 0.1686) < 5e-5 and their_converged == 2.11  # the published table
    assert abs(ex - their_ex) < 1e-6
    assert abs(eR - their_eR) < 1e-6
    assert abs(thrust - their_thrust) < 1e-5
    assert converged == their_converged
    assert circle["x"].shape == (1001, 3) and circle["R"].shape == (1001, 3, 3)
    assert max(fdcl.distance(circle, theirs)) < 1e-5  # m, and Frobenius for R
    RtR = np.swapaxes(circle["R"], -1, -2) @ circle["R"]
    assert np.max(np.abs(RtR - np.eye(3))) < 1e-13


def test_their_b1c_formula_has_no_effect_and_the_tolerance_sees_a_change(fdcl, circle):
    """Their `b1c''` enters only the first column of `Rc^T Rc''`, which their `vee` never
    reads: the corrected formula gives the same run to the last bit; reading the skew part
    instead moves mean |e_x| by far more than the tolerance above."""
    corrected = fdcl.run("circle", "decoupled", corrected=True, options=OPTIONS)
    np.testing.assert_array_equal(corrected["x"], circle["x"])
    np.testing.assert_array_equal(corrected["R"], circle["R"])
    skew = fdcl.run("circle", "decoupled", skew_vee=True, options=OPTIONS)
    assert abs(skew["table"][0] - circle["table"][0]) > 1e-4
    both = fdcl.run("circle", "decoupled", corrected=True, skew_vee=True, options=OPTIONS)
    # S is skew: both reads agree, up to rounding amplified by the adaptive steps (rtol 1e-8)
    assert abs(both["table"][0] - circle["table"][0]) < 1e-7
