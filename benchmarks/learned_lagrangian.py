"""A Lagrangian learned on the spheres (`sm.learn`, `sm.LearnedLagrangian`) on the tasks of
Finzi, Wang and Wilson (NeurIPS 2020, "Simplifying Hamiltonian and Lagrangian Neural
Networks via Explicit Constraints"), regenerated from their equations:

- `magnet`: a spherical pendulum (mass 3, length 1, gravity 9.81) over two magnetic
  dipoles (moment 0.3 along +z, at radius 0.1 around the axis, 1.05 below the pivot); the
  bob is a dipole of moment `0.3 r / |r|^2`. Initial states in spherical angles of a frame
  turned 90 degrees about y: `phi = pi + 0.3 N`, `theta = pi/2 + 0.2 N`, `phidot = 0.05 N`,
  `thetadot = 0.4 N`. Observations every 0.05 s.
- `chain3`, `chain5`: planar chains of point masses (gravity 1), masses and lengths drawn
  uniformly in [0.6, 1.4] (seeded here: their draw depends on a global seed), in the
  vertical x-z plane of our frame. Initial states: joint angles and rates `N(0, 1)`, then
  bob positions `+ 0.2 N` and velocities `0.5 v + 0.4 N`, put back on the constraints (the
  links' directions renormalized, the relative velocities made tangent). Observations every
  0.1 s.

Training data: 800 trajectories of 10 s, one random chunk of 5 observations from each.
Test (their comparison notebook's protocol): 200 trajectories, each started at a random
0.25 s chunk start of a true trajectory and rolled out for 100 points (0 to 4.95 s, every
0.05 s); error `|zhat - z| / (|zhat| + |z|)` over the bobs' Cartesian positions and
velocities; per trajectory `exp(dt * trapz(log(err + 1e-8)) / 5)`; geometric mean over the
trajectories: `rollout_rel_err`. `chaos_floor`: the same metric for the true system started
`--floor-perturbation` (default 1e-5, relative, in `(q, qdot)`) off the true state, the
floor any model meets on a chaotic task (the size of that perturbation is our assumption:
on the magnet, 200 test trajectories, 1e-4 gives 4.43e-3, 1e-5 5.9e-4 and 1e-6 9.5e-5,
against their 4.45e-4).

The long horizon (`rollout_rel_err_long`, `chaos_floor_long`): the same metric, time
averaged over `LONG_POINTS` = 1000 observations every `Task.dt` (50 s on the magnet, 100 s
on the chains) from the same test starts, as their trainer's `test_rollouts` rolls out far
beyond the training chunks (its aggregate over trajectories is not in their code: ours is
the one above). `--evaluate` computes both metrics again for a saved `DIR/<system>.eqx`.
Measured (2026-12-04): the magnet's kernels 1.33e-2 (chaos floor 1.85e-2), the chains'
MLPs (`mlp/`) 1.06e-1 (7.12e-2, chain3) and 2.18e-1 (2.08e-1, chain5): over 1000
observations a 1e-5 perturbation of the true system grows as large as these models'
errors, so the long horizon measures chaos more than the model (0.72x, 1.5x and 1.05x
the floor). The chains' `linear` models stay below the floor: 3.86e-3 and 4.73e-2.

    python benchmarks/learned_lagrangian.py --system magnet --out DIR [--quick]

writes `DIR/<system>.json` and `DIR/<system>.eqx`, then prints the table of every task in
`DIR` and writes it with the training curves (`DIR/learned_lagrangian.{md,png}`, alone:
`--summary`); `load(path, system)` reads the model back as a library system (state
`(q, qdot)`: the links' unit vectors in the task's frame).

Models (`--model`, default `DEFAULT_MODEL`): `kernels` (the magnet's default):
`sm.LearnedLagrangian(1, depth=0, features=sm.SphereKernels())`, its potential the
linear term (gravity) plus a linear combination of 2041 kernels on the sphere, fitted by
`sm.fit_accelerations` (one least-squares solve on accelerations estimated from the
chunks) and then `--refine-steps` steps of `sm.refine`. `linear` (the chains' default;
`LINEAR`): a constant inertia and a potential linear in the links' unit vectors (a
uniform field, as gravity is; the model knows no more of the chain), both fitted by
`sm.fit_accelerations(..., inertia=True)` (`LINEAR_FIT`: 30 Levenberg-Marquardt steps
from the identity inertia, initial damping 1e-3). `mlp` (`MODEL`; the chains' default
before `linear`, its results in `benchmarks/results/learned_lagrangian/mlp/`):
`sm.LearnedLagrangian` with its linear term and a depth-3 silu MLP of width 128
(64 on the magnet, whose inputs are scaled by 8: the dipoles' potential varies over about
0.1 on the sphere), trained by `sm.learn`: Adam with warmup then cosine decay, gradient
clipping, L1 loss, minibatches of 100 chunks, `--substeps` fixed steps of `--solver`
(RK4, Tsit5 or Dopri8; default RK4) per observation in training.

The magnet with kernels (`--refine-steps 30 --substeps 4`,
`benchmarks/results/learned_lagrangian/magnet.json`): 3.22e-4 in 783 s wall (1445 s CPU,
load 1.5 to 1.7; `fit_accelerations` 14 s and 1.2e-3 alone), 32 times below CLNN and
below the chaos floor of a 1e-5 perturbation (5.9e-4); the objective -20.21 before
`refine`, -22.07 after 10 steps, -22.65 after 30. How it was found (scripts outside the
library, 2026-12-03): an oracle probe, the kernels fitted by least squares to the true
forces at the 4000 training states, scored 1.6e-4 with the five levels (a relative fit
residual of 1e-5) but 1.9e-2 without the finest (25600 centers at 1.02 within 15 degrees):
the levels must resolve the magnets' field. `refine` alone from the zero potential (4 RK4
steps per observation, damping 1e-2) reached the objective -19.29 in 15 steps (414 s) but
a rollout error of 4.75e-3: its force error far from the magnets (median 0.4 on test
states farther than 0.5) is what the acceleration estimates fix (there they are accurate
to 1e-6). From `fit_accelerations`, 10 `refine` steps (280 s) gave 7.85e-4; at 8 RK4 steps
per observation the first 3 steps lowered the objective as much as at 4, at twice the
time. The results of the MLP on the magnet moved to
`benchmarks/results/learned_lagrangian/mlp/` (and `refine/`, `budget/`); everything below
up to `--dtype` is about them.

Their chaos floor comes from `test_rollouts` in their trainer: a perturbation
`pert_eps * randn / |zt|`, `|zt|` the norm of the whole batch of true rollouts, added to
the Cartesian state without projecting it on the constraints, so its size depends on
their batch and horizon; ours is relative to each state and kept on the sphere, and
scales linearly with its size (1e-4 gives 4.4e-3, 1e-5 5.9e-4, 1e-6 9.5e-5 on the
magnet): their 4.45e-4 corresponds to about 7.5e-6.

The chains with `linear` (2026-12-04, AMD EPYC 2-core, load 1.0 to 1.4;
`benchmarks/results/learned_lagrangian/chain{3,5}.json`): chain3 7.41e-7 in 8 s wall (10
s CPU), chain5 1.19e-6 in 13 s (18 s CPU), 440 and 780 times below CLNN, `M / M_00`
recovered to 4 digits; the weighted mean square acceleration error falls from 1.82 to
1.45e-9 (chain3) and stops there, at the acceleration estimates' own error.

Results of the MLP (`benchmarks/results/learned_lagrangian/mlp/`, `--summary` writes the
table and the training curves): magnet (`--model mlp`) 2.59e-3
with a width-64 MLP after 28000 steps trained in
float32 at learning rate 1e-2 and 4 RK4 steps per observation (`--dtype float32 --steps
28000 --learning-rate 1e-2 --substeps 4`; CLNN 1.03e-2; 1779 s wall, 2563 s CPU, load
1.4 to 1.5), not learned to the goal (1e-3). At 2 steps per observation 36000 steps had
given 2.79e-3 (1342 s wall, 1959 s CPU, load 1.4 to 1.8); a second run of 45000 steps
(1439 s wall, 2076 s CPU, load 1.3 to 1.5, 32 ms a step after `learn`'s residuals
dropped an extra interpolated save per chunk) gave 3.01e-3, so at 2 steps per
observation and width 64 more steps no longer lower the error. Up to then its error fell
with the number of steps, so the step time decided: a width-64 step took 38 ms against
83 to 100 ms at width 128 (progress lines of three runs), and the width-128 model had
given 6.05e-3 after 16000 float32 steps (1571 s wall); in float64 (`--steps 14000`)
8.19e-3 (1566 s), 12000 steps 9.90e-3, 6000 1.29e-2. chain3 2.40e-4 and chain5 5.72e-4
after 6000 float64 steps (CLNN 3.26e-4 and 9.33e-4; 785 and 1079 s wall). On this shared
2-core CPU a run under heavy load (2 to 11) got as little as a fifth of a core; under
light load XLA uses both cores, so the CPU time exceeds the wall time.

What did not help on the magnet (from the width-128 14000-step float64 model, 8.19e-3):
full-batch L-BFGS (`optax.lbfgs`, mean-square loss, 200 iterations) lowered the training
mean square from 1.93e-4 to 1.13e-4 but raised the rollout error to 2.7e-2 (the mean
square follows the few chunks that pass the magnets; the metric, a geometric mean, the
typical ones); 1200 more Adam steps at 8 RK4 steps per observation instead of 2
(learning rate 1e-3) gave 1.20e-2. The integrator is not what limits the model: rolled
out at 2, 5 or 10 RK4 steps per 0.05 s it scores 9.2e-3, 8.2e-3, 8.0e-3, and on the
training chunks its median chunk error (mean `|r|`) is 1.35e-4 at 2, 4 and 8 steps per
observation, against 1.9e-7, 1.2e-8 and 7.7e-10 for the true system (whose mean over
chunks at 2 steps, 1.2e-2, comes from the chunks that pass the magnets). Random Fourier
features (the MLP also reading `sin(B q)`, `cos(B q)`, 64 rows of `B` drawn `N(0, 8^2)`,
fixed; width 128), trained from scratch in float32 at learning rate 1e-2: after 2500
steps 1.09e-2 against 1.70e-2 for the plain width-128 model (one run each), but each
step 1.5x as long, and 10000 steps (1589 s) gave 1.82e-2, worse than the plain model's
6.05e-3 after 16000. At an equal training budget of about 6 minutes (step counts from
each setting's step time, float32): width 64 with batches of 100, 11000 steps, gave
7.79e-3 at learning rate 1e-2, 9.25e-3 at 5e-3 and 1.01e-2 at 2e-2; width 32 with
batches of 50 (a step 9.3 ms against 32 ms), 38000 steps at 1e-2, 9.54e-3. Two priors
on the potential, width 64, 11000 steps at 1e-2: the task's mirror symmetry (the MLP
reading `(64 x^2, 64 y^2, 8 z)`, `LearnedLagrangian(features=...)`: the potential
symmetric under the reflections in the x-z and y-z planes exactly) gave 3.58e-3 (398 s,
about the plain model's step time), and 8 learnable softened sources (their inverse
distances `0.1 / sqrt(|q - c_k|^2 + e_k^2)` as 8 more MLP inputs and `sum_k a_k phi_k^3`
added, centers, softenings and amplitudes trained; a script outside the library) 5.56e-3
(477 s). But trained for the whole budget, 40000 steps (1343 s wall, 1923 s CPU, load
1.4 to 1.5), the mirror-symmetric model reached 3.48e-3, no better than the plain
model's 2.79e-3 to 3.01e-3: both stop at a minibatch loss of about 4e-4, so the
symmetry makes the start faster, not the end lower. The training integrator biases
what is learned near the magnets: the true system, simulated from each training chunk's
first state with `--substeps` RK4 steps per observation, scores an L1 loss (mean `|r|`
over the 800 chunks) of 1.2e-2 at 2 substeps, 1.5e-3 at 4 and 4.9e-4 at 8 (median chunk
1.9e-7, 1.2e-8, 7.7e-10; the mean comes from the few chunks that pass the magnets),
against the learned model's 4e-4 at 2: there the model fits the coarse steps' dynamics,
not the true potential. Trained at `--substeps 4` (28000 steps, 67 ms a step against
about 33 ms at 2), the plain model reached 2.59e-3 at a final loss of 2.5e-4, but in
1929 s wall (2774 s CPU, load 1.1 to 1.5), over the 30-minute budget; once `learn` ran
its steps in compiled blocks the same run (the same losses step for step) took 1779 s
wall, and the results hold it. Its errors by place (the acceleration of the learned
model against the true one at the 4000 training states): median 1.3e-3 (2e-4 of the
acceleration) farther than 0.5 from both magnets, 1.5e-2 (1.7e-3) at 0.15 to 0.2, 0.5
(1.2e-2) at 0.1 to 0.15 (57 states); the same on 800 held-out chunks, whose median
chunk error (mean `|r|`, integrated accurately) is 4.5e-5 against 3.5e-5 on the training
chunks: the model is not overfitted. Fine-tuning the 36000-step model for 3000 steps
(learning rate 3e-4, cosine decay) gave 2.63e-3 with the loss `mean(log(mean |r| +
1e-6))` over chunks (the metric's geometric mean: every chunk weighs alike) against 2.75e-3
with L1; 1000 steps at 8 RK4 steps per observation (constant 1e-4) 3.09e-3. Trained from scratch
with `--solver dopri8 --substeps 2` (the true system's loss: mean 8.6e-4, 99th percentile
1.4e-5, against 1.5e-3 and 1.1e-3 for RK4 at 4; 95 ms a step against 63), 17000 steps
planned: a solve failed between steps 2550 (loss 6.0e-3) and 3400, and the parameters
turned NaN (`learn` then applied such steps; it now skips them), so the run was stopped.
Rerun with the skipping (16500 steps, 1791 s wall, 2569 s CPU): 4.75e-3, worse than RK4's
2.59e-3; 84 of the 1650 recorded losses (every tenth step, from step 7360 on) were
non-finite, and the final finite loss 2.7e-4.

Where the magnet's error comes from (this 2-core CPU, scripts outside the library): the
true system plus the force error of the 2.59e-3 model (the gradient of `U / M_00` minus the
true one) only where the distance to the nearest magnet is above or below a threshold (a
smooth mask 0.02 wide) scores: the whole error 2.59e-3, half of it 1.38e-3 (the metric is
linear in the force error); only below 0.15 2.3e-4, only above 0.15 1.86e-3; below 0.3
1.77e-3, above 0.3 8.1e-4; above 0.5 2.4e-5. The error is made 0.15 to 0.5 from the
magnets, where the test trajectories spend their time (their closest pass: median 0.17),
not at the closest passes. The model class can do better there (an oracle probe: the true
accelerations are not in the task's data): a width-64 MLP regressed on the true
accelerations at the 4000 training states (relative squared error, full-batch
Adam, 20000 steps, 255 s) scores 3.21e-3 (shooting: 2.59e-3 in 30 minutes),
a width-128 one (30000 steps, 884 s) 1.33e-3. Accelerations can be estimated from the
data: the degree-9 polynomial through each chunk's 5 observed positions and velocities
(Hermite interpolation) gives them to a median relative error of 6e-7 at the middle
observation but 8e-4 at the 90th percentile (the fast passes near the magnets), and the
difference from the same estimate without the chunk's first or last observation
estimates that error (log correlation 0.97 to 0.99). Regression on those estimates,
weighted by `1 / (1 + (error / 1e-4)^2)`, learns the far field but not within 0.2 of the
magnets: 1.27e-2 (width 64, 30000 steps, 334 s). As a penalty beside the shooting loss
(0.1 times the weighted relative RMS acceleration error, added to the L1 loss in a copy
of `learn` with a penalty term; not in the library), 3000
fine-tuning steps of the 2.59e-3 model (learning rate 3e-4, cosine decay, batches of 100)
gave 2.41e-3 (with 1 instead of 0.1: 2.60e-3); trained from scratch with it (batches of
25, 31.5 ms a step, 44000 steps, 1384 s) 3.45e-3. In two stages at width 128
(regression on the estimates, 30000 steps, 1.30e-2; then 15000 steps of the shooting loss
with the penalty, batches of 25, learning rate 1e-3 with cosine decay, 73 ms a step; about
31 minutes in all) 6.59e-3: midway the minibatch loss rose from 2.3e-3 to 4.5e-2.

Gauss-Newton after Adam (`--refine-steps 40`: `sm.refine`, floor 1e-5, initial damping
5e-3, float32; `benchmarks/results/learned_lagrangian/refine/`): 1.21e-3 after the same
28000 Adam steps, in 3989 s wall (4799 s CPU, `top` showing half the machine's time
stolen by its host), twice the budget; that run's Adam part alone scored 2.07e-3 (1992
s), and its refine checkpoints after 5, 10, 15, 20, 25, 30 steps 1.97e-3, 1.86e-3,
1.61e-3, 1.29e-3, 1.24e-3, 1.24e-3. A script before `refine` existed (float64, weights
`1 / (rms + 1e-5)^2`, from the 2.59e-3 model) had lowered it to 1.73e-3 in 8 steps and
1.53e-3 in 10 (about 120 s a step: the float64 Gram matrix of 800 chunks' Jacobians took
about 5 times as long as in float32), and `refine` in float32 from there 1.17e-3 after
16 more.
Within the budget (`--steps 15000 --refine-steps 20 --refine-damping 1e-3`,
`benchmarks/results/learned_lagrangian/budget/`): 2.53e-3 in 1569 s wall (2222 s CPU;
`learn` 773 s, `refine` 796 s), no better than 28000 Adam steps (2.59e-3, 1779 s); its
Adam part alone 4.63e-3, after 9 refine steps 3.88e-3. 22000 Adam and 14 refine steps
(1662 s) gave 3.54e-3. Cheaper steps between refine's (a script: each full step's
Cholesky factor reused with the gradient at the new point, about 10 s for the gradient of
the 800 chunks and up to 3 trial lengths) failed: from the 15000-step Adam model, none of
4 such steps lowered the objective at length 1, 1/2 or 1/4. Adam at 2 RK4 steps per
observation (cheaper) and `refine` at 4 (`--steps 20000 --substeps 2 --refine-steps 18
--refine-substeps 4 --refine-damping 1e-3`; 21 ms an Adam step, 35 s a refine step) gave
3.44e-3 in 1206 s wall (2039 s CPU; `learn` 481 s), worse than at 4 throughout; 20000
Adam and 22 refine steps at 4 (1741 s wall, 2847 s CPU; `learn` 850 s) 2.67e-3. A
refine step's time is mostly the Gram matrix: `J^T J` of the 800 chunks' 19200 residual
rows and 8645 parameters in float32 took about 28 s (3.5 s per group of 100 chunks: a
random 2400 x 8600 matrix), the float64 Cholesky factorization 6.0 s per damping
tried; forming only the upper triangle in 4, 8 or 16 column blocks saved nothing (3.0 to
3.3 s a group against 3.2 s). Without the Gram matrix (a scratch script, 2026-12-02: the 800
chunks' weighted Jacobians stored, 664 MB in float32, each column scaled by its norm, and
the damped normal equations solved by 100 conjugate-gradient iterations: 6 to 8 s a
damping tried, with its evaluation), a step took 15 to 26 s after the first instead of 34
to 41 s, but lowered the objective less: from the 28000-step model (-18.54, 2.59e-3), 10
such steps reached -18.80 (2.53e-3) in 239 s, where `refine`'s first 6 steps reached
-18.86 in 251 s and its 10 steps -19.06 (2.33e-3) in 407 s. No faster per second, so
`refine` keeps its Cholesky step.

`--dtype float32` trains in float32 (evaluated and saved in float64): a width-128 magnet
step took 83 ms against 214 ms in float64 (100 chunks, same run conditions, this 2-core
CPU).
"""

import argparse
import json
import os
import time
from pathlib import Path

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

jax.config.update("jax_enable_x64", True)

import sphere_mech as sm  # noqa: E402

CLNN = {"magnet": 1.03e-2, "chain3": 3.26e-4, "chain5": 9.33e-4}
"""Their published rollout errors of the constrained Lagrangian network."""
MODEL = {
    # the magnets' potential varies over about 0.1 on the sphere: inputs scaled, silu;
    # width 64: a step 2.2x to 2.6x faster than at 128, more steps in the 30 minutes
    "magnet": dict(width=64, depth=3, activation=jax.nn.silu, input_scale=8.0),
    "chain3": dict(width=128, depth=3, activation=jax.nn.silu),
    "chain5": dict(width=128, depth=3, activation=jax.nn.silu),
}
"""Each task's MLP `LearnedLagrangian` (`--model mlp`; gravity is its linear term, the MLP
learns the rest)."""
KERNELS = dict(depth=0, features=sm.SphereKernels())
"""`--model kernels`: the potential a linear combination of `sm.SphereKernels()` (2041
kernels, fine within 15 to 35 degrees of the bottom, where the pendulum hangs), fitted by
`sm.fit_accelerations` and then `sm.refine`."""


def no_features(q):
    """No features: `LearnedLagrangian`'s potential is its linear term (plus a constant)."""
    return jnp.zeros(1, q.dtype)


LINEAR = dict(depth=0, features=no_features)
"""`--model linear` (the chains' default): a constant inertia and a potential linear in the
links' unit vectors (a uniform field, such as gravity), both fitted by
`sm.fit_accelerations` with `LINEAR_FIT` (the inertia up to the common factor)."""
LINEAR_FIT = dict(steps=30, inertia=True)  # initial damping: the default with it, 1e-3
DEFAULT_MODEL = {"magnet": "kernels", "chain3": "linear", "chain5": "linear"}
SOLVERS = {"rk4": sm.RK4(), "tsit5": diffrax.Tsit5(), "dopri8": diffrax.Dopri8()}
"""`--solver`: the training solver, at fixed steps."""
TEST_DT, TEST_POINTS, CHUNK_STARTS = 0.05, 100, 20
LONG_POINTS = 1000
"""The long horizon: observations from each test start, every `Task.dt`."""


class Task(eqx.Module):
    """One task: the true system, the links' lengths and masses, the observation step."""

    name: str = eqx.field(static=True)
    system: sm.ConstantInertiaLagrangian
    lengths: np.ndarray
    dt: float

    @property
    def n(self) -> int:
        return len(self.lengths)


def _magnet_potential(t, q, args):
    mass, moment = 3.0, 0.3
    theta = np.linspace(0, 2 * np.pi, 3)[:-1]
    magnets = np.stack([0.1 * np.cos(theta), 0.1 * np.sin(theta), -1.05 * np.ones(2)], -1)
    r0 = q[0]
    m0 = moment * r0 / jnp.sum(r0**2)
    mi = moment * jnp.array([0.0, 0.0, 1.0])
    d = jnp.asarray(magnets) - r0
    d2 = jnp.sum(d * d, -1)
    dipole = (-3 * (d @ m0) * (d @ mi) - d2 * (m0 @ mi)) / (4 * np.pi * d2**2.5)
    return 9.81 * mass * r0[2] + jnp.sum(dipole)


def _chain(n, seed=0):
    rng = np.random.default_rng(seed + n)
    masses, lengths = 0.6 + 0.8 * rng.random(n), 0.6 + 0.8 * rng.random(n)
    tail = np.cumsum(masses[::-1])[::-1]  # sum_{k >= j} m_k
    M = np.outer(lengths, lengths) * tail[np.maximum.outer(np.arange(n), np.arange(n))]
    weights = jnp.asarray(lengths * tail)
    potential = lambda t, q, args: jnp.sum(weights * q[:, 2])  # gravity 1
    return sm.ConstantInertiaLagrangian(jnp.asarray(M), potential), lengths


def task(name: str) -> Task:
    """The task `magnet`, `chain3` or `chain5`."""
    if name == "magnet":
        return Task(
            name,
            sm.ConstantInertiaLagrangian(3.0 * jnp.eye(1), _magnet_potential),
            np.ones(1),
            0.05,
        )
    if name in ("chain3", "chain5"):
        system, lengths = _chain(int(name[-1]))
        return Task(name, system, lengths, 0.1)
    raise ValueError(f"unknown system {name!r}: magnet, chain3 or chain5.")


def initial_states(tk: Task, num: int, rng: np.random.Generator):
    """`num` initial states `(q, qdot)` from the task's distribution."""
    if tk.name == "magnet":
        phi, theta = (
            np.pi + 0.3 * rng.standard_normal(num),
            np.pi / 2 + 0.2 * rng.standard_normal(num),
        )
        rates = np.stack([0.05 * rng.standard_normal(num), 0.4 * rng.standard_normal(num)], -1)

        def point(angles):
            p, th = angles
            return jnp.stack([-jnp.cos(th), jnp.sin(p) * jnp.sin(th), jnp.cos(p) * jnp.sin(th)])

        angles = jnp.stack([phi, theta], -1)
        q, v = jax.vmap(lambda a, r: jax.jvp(point, (a,), (r,)))(angles, jnp.asarray(rates))
        return q[:, None], v[:, None]
    n, lengths = tk.n, tk.lengths
    angle, rate = rng.standard_normal((num, n)), rng.standard_normal((num, n))
    links = np.stack([np.sin(angle), np.zeros_like(angle), -np.cos(angle)], -1)
    rates = rate[..., None] * np.stack([np.cos(angle), np.zeros_like(angle), np.sin(angle)], -1)
    x = np.cumsum(lengths[:, None] * links, 1)
    v = np.cumsum(lengths[:, None] * rates, 1)
    plane = np.array([1.0, 0.0, 1.0])
    x = x + 0.2 * rng.standard_normal(x.shape) * plane
    v = 0.5 * v + 0.4 * rng.standard_normal(v.shape) * plane
    d = np.diff(x, axis=1, prepend=0.0)
    q = d / np.linalg.norm(d, axis=-1, keepdims=True)
    w = np.diff(v, axis=1, prepend=0.0) / lengths[:, None]
    qdot = w - np.sum(w * q, -1, keepdims=True) * q
    return jnp.asarray(q), jnp.asarray(qdot)


def true_trajectories(tk: Task, y0, ts):
    """The true `(q, qdot)` at `ts`, `(B, T, n, 3)`."""
    opts = dict(rtol=1e-10, atol=1e-12, saveat=diffrax.SaveAt(ts=jnp.asarray(ts)))
    return sm.simulate_batch(tk.system, y0, ts[-1], **opts).ys


def training_chunks(tk: Task, num=800, chunk=5, duration=10.0, seed=0):
    """`num` chunks of `chunk` observations, one at random from each of `num` trajectories."""
    rng = np.random.default_rng(seed)
    ts = np.arange(0.0, duration, tk.dt)
    q, v = true_trajectories(tk, initial_states(tk, num, rng), ts)
    start = chunk * rng.integers(0, len(ts) // chunk, num)
    index = start[:, None] + np.arange(chunk)
    take = lambda x: x[np.arange(num)[:, None], index]
    return ts[:chunk], (take(q), take(v))


def test_set(tk: Task, num=200, seed=1):
    """`num` true test trajectories of `TEST_POINTS` points, from random 0.25 s chunk starts."""
    rng = np.random.default_rng(seed)
    ts = np.arange(CHUNK_STARTS * 5 + TEST_POINTS) * TEST_DT
    q, v = true_trajectories(tk, initial_states(tk, num, rng), ts)
    start = 5 * rng.integers(0, CHUNK_STARTS, num)
    index = start[:, None] + np.arange(TEST_POINTS)
    take = lambda x: x[np.arange(num)[:, None], index]
    return ts[:TEST_POINTS], (take(q), take(v))


def cartesian(tk: Task, q, qdot):
    """The bobs' positions and velocities, raveled, from `(..., n, 3)` links."""
    w = jnp.asarray(tk.lengths)[:, None]
    x, xdot = jnp.cumsum(w * q, -2), jnp.cumsum(w * qdot, -2)
    return jnp.concatenate(
        [x.reshape(x.shape[:-2] + (-1,)), xdot.reshape(x.shape[:-2] + (-1,))], -1
    )


def long_test_set(tk: Task, truth, points=LONG_POINTS):
    """The true trajectories of `points` observations (every `tk.dt`) from the test set's
    starts: the horizon of their trainer's `test_rollouts`."""
    ts = np.arange(points) * tk.dt
    return ts, true_trajectories(tk, (truth[0][:, 0], truth[1][:, 0]), ts)


def rollout_rel_err(tk: Task, system, ts, truth, perturb=0.0, seed=2):
    """Their metric of `system` rolled out from the starts of `truth` (observed at the
    evenly spaced `ts`): the geometric mean over trajectories of the time-averaged log
    relative error, `exp(dt * trapz(log(err + 1e-8)) / (len(ts) dt))` (5 s on the test set)."""
    q, v = truth
    y0 = (q[:, 0], v[:, 0])
    if perturb:
        key1, key2 = jax.random.split(jax.random.PRNGKey(seed))
        dq = perturb * jax.random.normal(key1, y0[0].shape)
        q0 = sm.normalize(y0[0] + dq)
        v0 = y0[1] + perturb * jnp.linalg.norm(y0[1]) * jax.random.normal(key2, y0[1].shape)
        y0 = (q0, v0 - jnp.sum(v0 * q0, -1, keepdims=True) * q0)
    opts = dict(
        solver=sm.Projected(sm.RK4()), dt0=TEST_DT / 5, saveat=diffrax.SaveAt(ts=jnp.asarray(ts))
    )
    qh, vh = sm.simulate_batch(system, y0, ts[-1], throw=False, **opts).ys
    z, zh = cartesian(tk, q, v), cartesian(tk, qh, vh)
    err = jnp.linalg.norm(zh - z, axis=-1) / (
        jnp.linalg.norm(zh, axis=-1) + jnp.linalg.norm(z, axis=-1)
    )
    err = jnp.where(jnp.isfinite(err), err, 1.0)
    # exp(dt trapz(log(err + 1e-8)) / (len(ts) dt)): dt cancels
    per = jnp.exp(jnp.trapezoid(jnp.log(err + 1e-8), axis=-1) / len(ts))
    return float(jnp.exp(jnp.mean(jnp.log(per))))


def l1(r):
    """The training loss: the mean `|r|`, robust to the few chunks that pass the magnets."""
    return jnp.mean(jnp.abs(r))


def training_options(tk: Task, solver, substeps: int) -> dict:
    """`simulate`'s options in training: `substeps` fixed steps of `Projected(solver)` per
    observation interval."""
    return dict(
        solver=sm.Projected(solver),
        dt0=tk.dt / substeps,
        stepsize_controller=diffrax.ConstantStepSize(),
    )


def model_options(name: str, kind: str | None = None) -> dict:
    """`LearnedLagrangian`'s options of task `name` for the model `kind` (`"mlp"`,
    `"kernels"` or `"linear"`; default the task's `DEFAULT_MODEL`)."""
    return dict(kernels=KERNELS, linear=LINEAR).get(kind or DEFAULT_MODEL[name], MODEL[name])


def new_model(tk: Task, key=None, dtype="float64", kind=None):
    key = jax.random.PRNGKey(0) if key is None else key
    return sm.LearnedLagrangian(tk.n, key=key, dtype=dtype, **model_options(tk.name, kind))


def as_float64(model):
    """`model` with its floating-point leaves in float64 (evaluation and the saved file)."""
    cast = lambda x: x.astype(jnp.float64) if eqx.is_inexact_array(x) else x
    return jax.tree.map(cast, model)


def load(path, system: str, dtype="float64", kind=None):
    """The model trained on `system`, read from `path`, as a sphere_mech system. The final
    file is float64; the checkpoints written during a run (`--dtype float32`) are in the
    training dtype: pass it as `dtype`. `kind`: the `--model` it was trained with (default
    the task's `DEFAULT_MODEL`)."""
    like = new_model(task(system), dtype=dtype, kind=kind)
    return eqx.tree_deserialise_leaves(path, like)


def evaluate(tk: Task, model, test_ts, truth, perturbation: float) -> dict:
    """`rollout_rel_err` of `model` and the chaos floor on the test set (5 s) and over
    `LONG_POINTS` observations from the same starts."""
    long_ts, long_truth = long_test_set(tk, truth)
    floor = dict(perturb=perturbation)
    return {
        "rollout_rel_err": rollout_rel_err(tk, model, test_ts, truth),
        "chaos_floor": rollout_rel_err(tk, tk.system, test_ts, truth, **floor),
        "floor_perturbation": perturbation,
        "long_points": LONG_POINTS,
        "rollout_rel_err_long": rollout_rel_err(tk, model, long_ts, long_truth),
        "chaos_floor_long": rollout_rel_err(tk, tk.system, long_ts, long_truth, **floor),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--system", choices=["magnet", "chain3", "chain5"], help="required unless --summary"
    )
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--quick", action="store_true", help="small data, few steps")
    parser.add_argument(
        "--model",
        choices=["mlp", "kernels", "linear"],
        default=None,
        help="the model: an MLP potential trained by sm.learn, sm.SphereKernels fitted "
        "by sm.fit_accelerations, or a linear potential fitted with the inertia by "
        "sm.fit_accelerations (default: kernels on the magnet, linear on the chains)",
    )
    parser.add_argument("--steps", type=int, default=None, help="sm.learn's steps (mlp)")
    parser.add_argument("--batch-size", type=int, default=100)
    parser.add_argument("--learning-rate", type=float, default=3e-3)
    parser.add_argument("--warmup", type=int, default=100, help="steps of linear warmup")
    parser.add_argument(
        "--substeps", type=int, default=2, help="solver steps per observation interval in training"
    )
    parser.add_argument(
        "--solver",
        choices=sorted(SOLVERS),
        default="rk4",
        help="the training solver (fixed steps, wrapped in sm.Projected)",
    )
    parser.add_argument(
        "--refine-steps",
        type=int,
        default=0,
        help="Gauss-Newton steps (sm.refine) after the optimizer's, in the training dtype "
        "(the chains' width-128 models need about 28 GB: see sm.refine)",
    )
    parser.add_argument(
        "--refine-floor",
        type=float,
        default=1e-5,
        help="sm.refine's floor: minimize the mean over chunks of log(rms^2 + floor^2)",
    )
    parser.add_argument("--refine-damping", type=float, default=5e-3)
    parser.add_argument(
        "--refine-substeps",
        type=int,
        default=None,
        help="solver steps per observation interval in sm.refine (default: --substeps)",
    )
    parser.add_argument("--floor-perturbation", type=float, default=1e-5)
    parser.add_argument(
        "--dtype",
        choices=["float32", "float64"],
        default="float64",
        help="training dtype (the model is evaluated and saved in float64)",
    )
    parser.add_argument(
        "--summary", action="store_true", help="only write DIR/learned_lagrangian.{md,png}"
    )
    parser.add_argument(
        "--evaluate",
        action="store_true",
        help="no training: evaluate DIR/<system>.eqx again and update DIR/<system>.json",
    )
    args = parser.parse_args(argv)
    if args.summary:
        return summary(args.out)
    if args.system is None:
        parser.error("--system is required (unless --summary)")
    tk = task(args.system)
    num_train, num_test = (80, 20) if args.quick else (800, 200)
    test_ts, truth = test_set(tk, num_test)
    if args.evaluate:
        path = args.out / f"{args.system}.json"
        report = json.loads(path.read_text())
        kind = report.get("model_kind")  # absent from older files: the default model
        model = load(args.out / f"{args.system}.eqx", args.system, kind=kind)
        report.update(evaluate(tk, model, test_ts, truth, report["floor_perturbation"]))
        path.write_text(json.dumps(report, indent=2))
        summary(args.out)
        return report
    kind = args.model or DEFAULT_MODEL[args.system]
    fitted = kind in ("kernels", "linear")  # by sm.fit_accelerations, not sm.learn
    steps = 0 if fitted else args.steps or (50 if args.quick else 5000)
    ts, chunks = training_chunks(tk, num_train)
    args.out.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    sim = training_options(tk, SOLVERS[args.solver], args.substeps)
    start, cpu_start = time.perf_counter(), time.process_time()
    model = new_model(tk, dtype=args.dtype, kind=kind)
    if fitted:
        options = LINEAR_FIT if kind == "linear" else {}
        result = sm.fit_accelerations(model, ts, chunks, print_every=1, **options)
    else:
        schedule = optax.warmup_cosine_decay_schedule(
            0.0, args.learning_rate, min(args.warmup, steps // 2), steps
        )
        optimizer = optax.chain(optax.clip_by_global_norm(1.0), optax.adam(schedule))
        result = sm.learn(
            model,
            ts,
            chunks,
            steps=steps,
            batch_size=args.batch_size,
            optimizer=optimizer,
            loss=l1,
            simulate_options=sim,
            checkpoint=args.out / f"{args.system}.eqx",
            checkpoint_every=max(steps // 10, 1),
            print_every=max(steps // 20, 1),
        )
    learn_time = time.perf_counter() - start
    last = result.losses[-max(steps // 20, 1) :]  # the last twentieth, skipped steps left out
    refined = None
    refine_substeps = args.substeps if args.refine_substeps is None else args.refine_substeps
    if args.refine_steps:
        refined = sm.refine(
            result.model,
            ts,
            chunks,
            steps=args.refine_steps,
            floor=args.refine_floor,
            damping=args.refine_damping,
            simulate_options=training_options(tk, SOLVERS[args.solver], refine_substeps),
            checkpoint=args.out / f"{args.system}.eqx",
            print_every=1,
        )
    train_time, train_cpu = time.perf_counter() - start, time.process_time() - cpu_start
    model = as_float64((refined or result).model)
    eqx.tree_serialise_leaves(args.out / f"{args.system}.eqx", model)
    report = {
        "system": args.system,
        **evaluate(tk, model, test_ts, truth, args.floor_perturbation),
        "clnn_rollout_rel_err": CLNN[args.system],
        "train_time_s": train_time,
        "train_cpu_time_s": train_cpu,
        "learn_time_s": learn_time,
        "steps": steps,
        "refine_steps": args.refine_steps,
        "refine_floor": args.refine_floor,
        "refine_damping": args.refine_damping,
        "refine_substeps": refine_substeps,
        "refine_losses": [] if refined is None else [float(x) for x in refined.losses],
        "refine_rejected": 0 if refined is None else refined.skipped,
        "train_chunks": num_train,
        "test_trajectories": num_test,
        "final_loss": float(np.mean(last[np.isfinite(last)])) if steps else None,
        "skipped_steps": result.skipped,
        "quick": args.quick,
        "device": str(jax.devices()[0]),
        "load_average_1min_before_after": [load_before[0], os.getloadavg()[0]],
        "model_kind": kind,
        "model": {
            k: getattr(v, "__name__", repr(v) if isinstance(v, eqx.Module) else v)
            for k, v in model_options(args.system, kind).items()
        },
        "learning_rate": args.learning_rate,
        "batch_size": args.batch_size,
        "substeps": args.substeps,
        "solver": args.solver,
        "dtype": args.dtype,
        "losses_every_10": [] if fitted else [float(x) for x in result.losses[::10]],
        "fit_accelerations_losses": [float(x) for x in result.losses] if fitted else [],
    }
    (args.out / f"{args.system}.json").write_text(json.dumps(report, indent=2))
    summary(args.out)
    return report


def summary(out: Path):
    """`out/learned_lagrangian.md` (table beside CLNN, printed) and `.png` (training
    curves) from the `<system>.json` files in `out`; a training run ends with it."""
    # here, not at the top: notebook 09 loads this module without benchmarks/ on the path
    from _harness import publish, pyplot, save_figure

    reports = [
        json.loads((out / f"{s}.json").read_text()) for s in CLNN if (out / f"{s}.json").exists()
    ]
    lines = [
        "Learned Lagrangian (`sm.learn`, `sm.LearnedLagrangian`; trained in the dtype of "
        "its row, evaluated in float64) on the tasks of "
        "Finzi et al. (NeurIPS 2020), their rollout metric (200 test trajectories, 5 s). "
        "Written by `python benchmarks/learned_lagrangian.py --system S --out DIR`, "
        "then `--summary`.",
        "",
        f"The long horizon: the same metric over {LONG_POINTS} observations (every 0.05 s on "
        "the magnet, 0.1 s on the chains) from the same test starts, as their trainer's "
        "`test_rollouts` rolls out (`--evaluate`).",
        "",
        "| system | rollout_rel_err | CLNN | chaos floor (perturbation) | long horizon: "
        "model / chaos floor | steps | dtype | "
        "train wall time (s) | train CPU time (s) | load (1 min) before / after | model |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    steps = lambda r: (
        ("fit_accelerations" if r.get("model_kind") in ("kernels", "linear") else f"{r['steps']}")
        + (f" + {r['refine_steps']} refine" if r.get("refine_steps") else "")
    )
    long = lambda r: (
        f"{r['rollout_rel_err_long']:.2e} / {r['chaos_floor_long']:.2e}"
        if "rollout_rel_err_long" in r
        else "not measured"
    )
    for r in reports:
        load = r.get("load_average_1min_before_after", [float("nan")] * 2)
        lines.append(
            f"| {r['system']} | {r['rollout_rel_err']:.2e} | {r['clnn_rollout_rel_err']:.2e} | "
            f"{r['chaos_floor']:.2e} ({r['floor_perturbation']:g}) | {long(r)} | {steps(r)} | "
            f"{r.get('dtype', 'float64')} | "
            f"{r['train_time_s']:.0f} | {r.get('train_cpu_time_s', float('nan')):.0f} | "
            f"{load[0]:.1f} / {load[1]:.1f} | {r.get('model', '')} |"
        )
    publish("\n".join(lines) + "\n", "learned_lagrangian.md", out)
    fig, (ax, ax2) = pyplot().subplots(1, 2, figsize=(10, 4))
    for r in reports:
        losses = np.asarray(r.get("losses_every_10", []))
        if losses.size:
            ax.semilogy(10 * np.arange(len(losses)), losses, label=r["system"])
        if r.get("refine_losses"):
            ax2.plot(
                r["refine_losses"],
                "o-",
                ms=3,
                label=f"{r['system']} ({r.get('model_kind', 'mlp')})",
            )
    ax.set(xlabel="step", ylabel="minibatch loss (mean |residual|)", title="sm.learn (MLP)")
    ax2.set(xlabel="Gauss-Newton step", ylabel="mean log(rms^2 + floor^2)", title="sm.refine")
    for a in (ax, ax2):
        if a.lines:
            a.legend()
    save_figure(fig, "learned_lagrangian.png", out)


if __name__ == "__main__":
    main()
