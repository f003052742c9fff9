"""`learn`: train a model system (an equinox Module, e.g. `LearnedLagrangian`) on many short
observed trajectory chunks by a first-order optimizer (optax), through the multiple-shooting
residuals of `shooting.py` (the ones `fit` minimizes), differentiated in reverse mode;
`refine`: Gauss-Newton steps on the same chunks from the model `learn` trained.

A sibling of `fit`, not an extension: `fit` solves a small least-squares problem by
Levenberg-Marquardt with each segment's Jacobian built in full (cheap for a few parameters,
and the uncertainties come from it), whereas learning has thousands of parameters, so it
needs gradients of a scalar loss, minibatches and an optimizer's state. `refine` is
Levenberg-Marquardt too, but for thousands of parameters: it sums the normal equations
over groups of chunks instead of holding the whole Jacobian (optimistix's factors it by QR
and again at each damping), and reweights the chunks. All three build the same
`Residuals`: each chunk is one record with one segment starting at its first observed
state"""

import math
import time
from collections.abc import Callable
from pathlib import Path

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
import optax
import tqdm
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, PyTree

from .._inertia import AbstractConstantInertiaLagrangian, check_spd_inertia
from .._misc import (
    all_finite,
    check_bool,
    check_integer,
    check_positive,
    float_dtype,
    tree_dtype,
)
from .._results import describe_failures
from .._solve import state_pair
from .._solvers.projected import Projected
from .._solvers.rk4 import RK4
from .._spaces import AbstractSpace, Spheres
from .._system import AbstractSystem
from .shooting import Residuals, check_data, own_options, split_segments


class LearnedLagrangian(AbstractConstantInertiaLagrangian):
    """A learnable Lagrangian on (S^2)^n, `L = 1/2 sum_jk M_jk qdot_j . qdot_k - U(q)`: a
    constant symmetric positive-definite inertia `M = C C^T` over the links (`C` lower
    triangular with a positive diagonal) and a potential
    `U(q) = sum_j g_j . q_j + MLP(input_scale * q)`: a linear term (uniform gravity, or any
    constant field, exactly; `g` starts at zero) plus an MLP of the `3n` coordinates of the
    unit vectors for the rest. It is a system like any other (`simulate`,
    `simulate_batch`, `legendre`, ...): the library derives its equations on the fast path
    of `AbstractConstantInertiaLagrangian`. Train it with `learn`.

    `L` and `c L` have the same motion, so `M` and `U` are learned up to one common factor:
    compare `U / M_00` or rollouts, not `M` alone.

    **Arguments:**
    - `n`: the number of unit vectors (links).
    - `key`: a `jax.random` key for the MLP's initial weights.
    - `width`, `depth`: the MLP's hidden width and number of hidden layers. With
      `depth=0` the potential is linear in the features (`width` unused) and starts at
      zero: with `features=SphereKernels(...)` a sum of kernels on the sphere, which
      `fit_accelerations` fits by one least-squares solve.
    - `inertia`: the initial `(n, n)` SPD inertia (default the identity).
    - `activation`: the MLP's activation, smooth (the equations differentiate `U` and
      training differentiates them again); default `jax.nn.softplus` (`jax.nn.silu`
      resolves sharp features better).
    - `input_scale`: the factor on the MLP's input: a potential that varies over a
      distance `d` on the sphere (a magnet close to the path) is learned far faster with
      `input_scale` about `1 / d` than with the default 1.
    - `features`: the MLP's input as a function of the `(n, 3)` unit vectors, a 1-D
      array (default their `3n` coordinates, `q.ravel()`); the MLP reads
      `input_scale * features(q)`. Invariants of a symmetry the system is known to have
      (e.g. `(x^2, y^2, z)` for reflections in the x-z and y-z planes) give a potential
      with that symmetry exactly. A static function: a module-level one, so that a saved
      model can be rebuilt with it.
    - `dtype`: the parameters' floating dtype (default JAX's default float): `learn`
      trains in this dtype.
    """

    inertia_factor: Array
    potential_linear: Array
    potential_net: eqx.nn.MLP
    input_scale: float = eqx.field(static=True)
    features: Callable[[Array], Array] = eqx.field(static=True)
    forces: None = None

    def __init__(
        self,
        n: int,
        *,
        key,
        width: int = 64,
        depth: int = 2,
        inertia=None,
        activation: Callable = jax.nn.softplus,
        input_scale: float = 1.0,
        features: Callable[[Array], Array] | None = None,
        dtype=None,
    ):
        dtype = float_dtype(dtype)
        for name, value, least in (("n", n, 1), ("width", width, 1), ("depth", depth, 0)):
            check_integer(value, name, least)
        M = np.eye(n) if inertia is None else np.asarray(inertia, dtype=float)
        if M.shape != (n, n):
            raise ValueError(f"inertia must have shape ({n}, {n}), got {M.shape}.")
        C = np.linalg.cholesky(check_spd_inertia(M))
        factor = np.tril(C, -1) + np.diag(np.log(np.diag(C)))
        check_positive(input_scale, "input_scale")
        self.inertia_factor = jnp.asarray(factor, dtype=dtype)
        self.potential_linear = jnp.zeros((n, 3), dtype)
        self.input_scale = float(input_scale)
        self.features = _coordinates if features is None else features
        size = jax.eval_shape(self.features, jax.ShapeDtypeStruct((n, 3), dtype)).shape
        if len(size) != 1:
            raise ValueError(f"features must return a 1-D array, got shape {size}.")
        net = eqx.nn.MLP(
            size[0], "scalar", width, depth, activation=activation, dtype=dtype, key=key
        )
        if depth == 0:  # linear in the features: start at zero (no symmetry to break)
            net = jtu.tree_map(lambda x: jnp.zeros_like(x) if eqx.is_inexact_array(x) else x, net)
        self.potential_net = net
        self.forces = None

    @property
    def space(self) -> AbstractSpace:
        """`Spheres(n)`, `n` the number of links of `inertia_factor`."""
        return Spheres(self.inertia_factor.shape[0])

    def inertia(self, args):
        F = self.inertia_factor
        C = jnp.tril(F, -1) + jnp.diag(jnp.exp(jnp.diag(F)))
        return C @ C.T

    def potential(self, t, q, args):
        q = jnp.asarray(q, self.inertia_factor.dtype)
        linear = jnp.sum(self.potential_linear * q)
        return linear + self.potential_net(self.input_scale * self.features(q))


def _coordinates(q):
    """The default features: the unit vectors' `3n` coordinates."""
    return jnp.reshape(q, (-1,))


def _fibonacci(count: int) -> np.ndarray:
    """`count` nearly evenly spread unit vectors (the Fibonacci lattice), `(count, 3)`."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    r = np.sqrt(1 - z**2)
    angle = np.pi * (1 + 5**0.5) * i
    return np.stack([r * np.cos(angle), r * np.sin(angle), z], -1)


MAGNET_LEVELS = (
    (100, 1.3, 180.0),
    (400, 1.15, 180.0),
    (1600, 1.075, 70.0),
    (6400, 1.04, 35.0),
    (25600, 1.02, 15.0),
)


class SphereKernels(eqx.Module):
    """Features for `LearnedLagrangian(features=...)`: kernels on the unit sphere, each
    `((rho - 1) / |x - rho u|)^power` of a link's vector `x`, for centers `u` on the unit
    sphere and a radius `rho > 1` (a source just outside the sphere: the kernel is 1 at
    the point of the sphere nearest it and falls off over a distance of about `rho - 1`).
    With `LearnedLagrangian(n, depth=0, features=SphereKernels(...))` the potential is a
    linear combination of them (plus the linear term), which `fit_accelerations` fits by
    one linear least-squares solve; the sum of kernels of each link is the potential of
    sources near the sphere, so it resolves fields that vary over short distances (a
    magnet close to the path) where the kernels are fine.

    **Arguments:**
    - `levels`: `((count, rho, cap), ...)`: for each level the centers are the points of
      a Fibonacci lattice of `count` points on the whole sphere that lie within `cap`
      degrees of `axis`, at radius `rho`. Default (`MAGNET_LEVELS`): five levels from
      100 points at 1.3 (all around) to 25600 at 1.02 within 15 degrees, 2041 kernels:
      fine near `axis`, coarse elsewhere.
    - `axis`: the direction around which the fine levels lie (default `(0, 0, -1)`, where
      a pendulum hangs).
    - `power`: the kernels' power (default 3, the falloff of a dipole's field).

    `__call__(q)` maps `(n, 3)` vectors to the `n K` kernels (`K` per link, the same
    centers for every link); `q` need not be of unit length (an integrator's stages are
    not), the distances being the true ones. All fields are static: the centers are
    recomputed when traced."""

    levels: tuple = eqx.field(static=True, default=MAGNET_LEVELS)
    axis: tuple = eqx.field(static=True, default=(0.0, 0.0, -1.0))
    power: float = eqx.field(static=True, default=3.0)

    def __check_init__(self):
        for level in self.levels:
            if len(level) != 3:
                raise ValueError(f"SphereKernels: each level is (count, rho, cap), got {level}.")
            count, rho, cap = level
            check_integer(count, "SphereKernels: a level's count")
            if not (np.isfinite(rho) and rho > 1):
                raise ValueError(f"SphereKernels: a level's rho must be > 1, got {rho}.")
            check_positive(cap, "SphereKernels: a level's cap")
        if np.shape(self.axis) != (3,) or not np.linalg.norm(self.axis) > 0:
            raise ValueError(f"SphereKernels: axis must be a nonzero 3-vector, got {self.axis}.")
        check_positive(self.power, "SphereKernels: power")

    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """The kernels' sources, level by level.

        **Returns:** `(units, radii)`: the centers `(K, 3)` (unit vectors) and their radii
        `(K,)`."""
        axis = np.asarray(self.axis, float) / np.linalg.norm(self.axis)
        units, radii = [], []
        for count, rho, cap in self.levels:
            u = _fibonacci(count)
            u = u[u @ axis >= np.cos(np.radians(cap)) - 1e-12]
            units.append(u)
            radii.append(np.full(len(u), float(rho)))
        return np.concatenate(units), np.concatenate(radii)

    def __call__(self, q):
        units, radii = self.centers()
        q = jnp.asarray(q)
        u, rho = jnp.asarray(units, q.dtype), jnp.asarray(radii, q.dtype)

        def link(x):  # one link's kernels; |x - rho u|^2 exact off the sphere too
            d2 = x @ x + rho**2 - 2 * rho * (u @ x)
            return (rho - 1) ** self.power / d2 ** (self.power / 2)

        # link by link (a `(n, 3) @ (3, K)` product made a refine step 2.6x as long)
        return jnp.concatenate([link(x) for x in q])


class LearnResult(eqx.Module):
    """What `learn` returns (and `refine` and `fit_accelerations`, whose docstrings say
    what their `losses` and `skipped` count).

    **Attributes:**
    - `model`: the trained model (same structure as the model given).
    - `losses`: `(steps,)`, the minibatch loss at each step (before its update).
    - `skipped`: the number of steps skipped because their loss, gradient or updated
      parameters were not finite.
    - `wall_time`: seconds spent training (compilation included).
    """

    model: PyTree
    losses: np.ndarray
    skipped: int
    wall_time: float


def _state_vector(system, t, q, v):
    """One observation: the state `(q, v)` raveled (any space's structure)."""
    return jnp.concatenate([ravel_pytree(q)[0], ravel_pytree(v)[0]])


# the most optimizer steps in one compiled block
_MAX_BLOCK = 100


def _identity(model):
    return model


def _bar(show, total, name):
    """`learn`'s and `refine`'s progress bar over `total` steps (tqdm; does nothing unless
    `show`)."""
    return tqdm.tqdm(total=total, desc=name, unit="step", disable=not show)


def _report(bar, name, done, total, moved, loss, start, print_every):
    """`learn`'s and `refine`'s progress after step `done` of `total`: a line (step, loss,
    seconds) every `print_every` steps and after the last, and `bar` moved by `moved` steps
    with the loss; `loss` is read from the device only for these."""
    line = bool(print_every) and (done % print_every == 0 or done == total)
    if line or not bar.disable:
        loss = float(loss)
        if line:
            elapsed = time.perf_counter() - start
            print(f"{name}: step {done}/{total}  loss {loss:.4e}  {elapsed:.1f} s")
        bar.set_postfix_str(f"loss {loss:.3e}", refresh=False)
        bar.update(moved)


def _check_options(name, checkpoint, every: dict, counts: dict):
    """`learn`'s and `refine`'s own checks, before any work (`ValueError`): `counts`
    positive integers, `every` (`print_every`, ...) `None` or positive integers, and
    `checkpoint` a file path in a folder that exists (else a run would fail at its first
    write, after training). The file `eqx.tree_serialise_leaves` writes: `checkpoint`, with
    `.eqx` appended if it has no suffix."""
    every = {key: value for key, value in every.items() if value is not None}
    for key, value in (counts | every).items():
        check_integer(value, f"{name}: {key}")
    if checkpoint is None:
        return
    given = Path(checkpoint)
    path = given if given.suffix else given.with_suffix(".eqx")
    for folder in {given, path}:
        if folder.is_dir():
            raise ValueError(f"{name}: checkpoint {str(folder)!r} is a folder, not a file path.")
    if not path.parent.is_dir():
        raise ValueError(f"{name}: checkpoint {str(path)!r} is in a folder that does not exist.")


def _default_sim(ts, simulate_options, name):
    """`simulate`'s options: `Projected(RK4())` unless a solver is given, `dt0` the
    observations' first spacing unless given, reverse-mode adjoint.
    `RecursiveCheckpointAdjoint()` given explicitly differentiates an `RK4()` step whole,
    not stage by stage as the default adjoint does: with an MLP in the vector field the
    stage-by-stage pass costs 1.3x (magnet) to 1.8x (chain3) as much
    (`benchmarks/gradients.py --learned`). `max_steps` stays `simulate`'s (its
    `sqrt(2 max_steps)` checkpoints hold every step of a chunk): bounded
    by a chunk's 8 steps (the tasks of `benchmarks/learned_lagrangian.py`, 2 RK4 steps per
    observation, 100 chunks) the loop recomputed steps from 4 checkpoints, and a training
    step took 1.3x (chain3) to 1.4x (magnet) as long."""
    sim = own_options(simulate_options, name, ts)
    sim.setdefault("solver", Projected(RK4()))
    if "dt0" not in sim:
        ts = np.asarray(ts)
        sim["dt0"] = float(np.min(ts[:, 1] - ts[:, 0]))
    sim["adjoint"] = diffrax.RecursiveCheckpointAdjoint()
    return sim


def _observed_chunks(model, ts, states, name, least):
    """The checks of `learn`'s, `refine`'s and `fit_accelerations`' data, before any work
    (`ValueError`): `model` a system, `states` a pair `(q, v)` with leading axes `(B, T)`,
    `T >= least`, of the model's shapes, `ts` `(T,)` or `(B, T)`, and `check_data`'s.
    Returns `ts`, the states in the model's floating dtype, the observations raveled
    `(B, T, d)`, and that dtype."""
    if not isinstance(model, AbstractSystem):
        raise ValueError(f"model must be a sphere_mech system, got {type(model).__name__}.")
    dtype = tree_dtype(eqx.filter(model, eqx.is_inexact_array))
    states = state_pair(states, "(B, T, n, 3)", "states", "(q, v)")
    q, v = jtu.tree_map(lambda x: jnp.asarray(x, dtype), states)
    leading = {x.shape[:2] for x in jtu.tree_leaves((q, v))}
    if len(leading) != 1 or len(next(iter(leading))) != 2:
        raise ValueError(
            "states must be (q, v) with the same leading axes (B, T) on every array, got "
            f"shapes {jtu.tree_map(jnp.shape, (q, v))}."
        )
    if len(axes := model.state_space.batch_shape(q)) != 2:
        raise ValueError(
            "states must have two leading axes (B, T), B chunks of T observations, before "
            f"the shape of one state; q's shapes {jtu.tree_map(jnp.shape, q)} have "
            f"{len(axes)} ({axes}); for one chunk, add a leading axis of 1."
        )
    model.state_space.check_shapes(*jtu.tree_map(lambda x: x[0, 0], (q, v)), model.state_name)
    num_chunks, num_times = next(iter(leading))
    ts = jnp.asarray(ts)
    if ts.shape not in ((num_times,), (num_chunks, num_times)) or num_times < least:
        raise ValueError(
            f"ts must have shape (T,) or (B, T) with T >= {least} matching states' (B, T) = "
            f"{(num_chunks, num_times)}, got {ts.shape}."
        )
    y0 = jtu.tree_map(lambda x: x[:, 0], (q, v))
    observed = jax.vmap(jax.vmap(lambda q_, v_: _state_vector(None, None, q_, v_)))(q, v)
    check_data(model, ts, y0, observed, name, "chunk")
    return ts, (q, v), observed, dtype


class _Chunks(eqx.Module):
    """`learn`'s and `refine`'s shooting problem: each observed chunk one record with one
    segment, simulated from its first observed state."""

    residuals: Residuals
    unknowns: tuple[PyTree, PyTree]  # the model's floating-point leaves, and the rest
    times: tuple[Array, Array, Array]  # the segments' `(ts, t0, t1)`
    obs: Array
    mask: Array
    y0: PyTree
    shared: bool = eqx.field(static=True)
    num: int = eqx.field(static=True)

    @classmethod
    def build(cls, model, ts, states, simulate_options, jac, name):
        ts, (q, v), observed, dtype = _observed_chunks(model, ts, states, name, 2)
        num_chunks, num_times = observed.shape[:2]
        shared = ts.ndim == 1
        y0 = jtu.tree_map(lambda x: x[:, 0], (q, v))
        ts = jnp.broadcast_to(ts.astype(dtype), (num_chunks, num_times))
        seg_ts, obs, t0, t1, mask = split_segments(ts, observed, 1)
        # one segment per chunk: with `ts` shared, the first chunk's times are every chunk's
        times = (seg_ts[0, 0], t0[0, 0], t1[0, 0]) if shared else (seg_ts, t0, t1)
        u0, static = eqx.partition(model, eqx.is_inexact_array)
        residuals = Residuals(
            _identity,
            model.state_space,
            _state_vector,
            (False,) * len(jtu.tree_leaves(u0)),
            static,
            False,
            jnp.ones(()),
            _default_sim(ts, simulate_options, name),
            jtu.tree_map(jnp.result_type, (u0, None)),
            jac,
        )
        return cls(residuals, (u0, static), times, obs, mask, y0, shared, num_chunks)

    def pick(self, index):
        """The residuals' data `(segment data, y0)` of the chunks `index`."""
        pick = lambda tree: jtu.tree_map(lambda x: x[index], tree)
        ts, t0, t1 = self.times if self.shared else pick(self.times)
        obs, mask, y0 = pick((self.obs, self.mask, self.y0))
        return (ts, obs, t0, t1, mask), y0


def learn(
    model: AbstractSystem,
    ts,
    states,
    *,
    steps: int = 1000,
    batch_size: int = 64,
    optimizer: optax.GradientTransformation | None = None,
    learning_rate: float = 1e-3,
    loss: Callable[[Array], Array] | None = None,
    simulate_options: dict | None = None,
    seed: int = 0,
    checkpoint=None,
    checkpoint_every: int | None = None,
    print_every: int | None = None,
    progress: bool = False,
) -> LearnResult:
    """Train the floating-point parameters of a model system on observed trajectory chunks:
    minimizes (by default) the mean over minibatches of chunks of
    `|(q, v)_sim(t_j) - (q, v)_obs(t_j)|^2`,
    each chunk simulated from its first observed state (multiple shooting: short chunks keep
    the loss smooth however chaotic the system), with an optax optimizer.

    **Arguments:**
    - `model`: a sphere_mech system that is an equinox Module with the parameters as its
      floating-point array leaves, e.g. `LearnedLagrangian` (or any system: its other
      leaves are kept).
    - `ts`: observation times `(T,)` shared by every chunk, or `(B, T)`, each chunk's own
      (slower: the solver's time stepping is then batched too).
    - `states`: the observed chunks `(q, v)`, each of shape `(B, T, n, 3)` (the system's
      state variable `v`; dicts of such arrays on a mixed space); `(q, v)[:, 0]` starts
      each chunk. Cast to the model's floating dtype (float32 or float64). Checked before
      any solve (`ValueError`): the first states as `simulate_batch` checks initial
      states, every observation finite.
    - `steps`: optimizer steps, each on one minibatch.
    - `batch_size`: chunks per minibatch (at most the number of chunks: a larger value
      means all of them), drawn without replacement each epoch.
    - `seed`: the seed of the minibatches' order (NumPy's `default_rng`; an integer
      >= 0).
    - `optimizer`: an optax `GradientTransformation`; default `optax.adam(learning_rate)`.
    - `learning_rate`: the default optimizer's step size (finite, > 0).
    - `loss`: `loss(r) -> scalar` of a minibatch's residuals `r`, `(batch, 1, T, d)` (the
      raveled `(q, v)` simulated minus observed, zero at each chunk's start); default
      `jnp.mean(r**2)` (e.g. `lambda r: jnp.mean(jnp.abs(r))` is less swayed by a few
      chunks with fast motion).
    - `simulate_options`: keyword arguments for `simulate` (`solver`, `dt0`,
      `max_steps`, ...); default solver `Projected(RK4())` (fixed steps), default `dt0`
      the smallest spacing of the chunks' first two observations. The adjoint is
      `diffrax.RecursiveCheckpointAdjoint()`.
    - `checkpoint`: a file path in an existing folder (checked before training; `.eqx`
      appended if it has no suffix, as `eqx.tree_serialise_leaves` does): the model is
      written there at the end; read it back with `eqx.tree_deserialise_leaves(path,
      like)`, `like` a model of the same structure and dtype.
    - `checkpoint_every`: also write it every so many steps.
    - `print_every`: print a progress line (step, loss, seconds) every so many steps and
      after the last.
    - `progress`: show a tqdm progress bar of the steps (with the last loss), moved at
      the end of each block.

    A step whose loss, gradient or updated parameters are not finite (a chunk's solve
    failed: e.g. a model that blows up under the training solver's fixed steps; or the
    optimizer divided by zero) is skipped, the model and the optimizer's state kept as
    they were; `LearnResult.skipped` counts them.

    The steps run in blocks, each one compiled `jax.lax.scan` of up to 100 steps (their
    length the greatest common divisor of `steps`, `print_every`, `checkpoint_every` and
    100), so that a progress line or checkpoint falls at the end of a block.

    **Returns:** a `LearnResult` (the trained model, the losses, the skipped steps, the
    wall time).
    """
    start = time.perf_counter()
    every = dict(print_every=print_every, checkpoint_every=checkpoint_every)
    _check_options("learn", checkpoint, every, dict(steps=steps, batch_size=batch_size))
    check_integer(seed, "learn: seed", 0)
    if optimizer is None:
        check_positive(learning_rate, "learn: learning_rate")
    elif not isinstance(optimizer, optax.GradientTransformation):
        kind = type(optimizer).__name__
        raise TypeError(f"learn: optimizer must be an optax GradientTransformation, got {kind}.")
    chunks = _Chunks.build(model, ts, states, simulate_options, "grad", "learn")
    residuals, num_chunks, (u0, static) = chunks.residuals, chunks.num, chunks.unknowns
    optimizer = optax.adam(learning_rate) if optimizer is None else optimizer
    batch_size = min(batch_size, num_chunks)

    loss = (lambda r: jnp.mean(r**2)) if loss is None else loss
    r = jax.ShapeDtypeStruct((batch_size,) + chunks.obs.shape[1:], chunks.obs.dtype)
    out = jax.eval_shape(loss, r)
    if not (isinstance(out, jax.ShapeDtypeStruct) and out.shape == ()):
        raise ValueError(f"learn: loss(r) must return a scalar (r: {r.shape}), got {out}.")

    def loss_fn(u, batch):
        return loss(residuals((u, None), batch)[0])

    def step(carry, index):
        u, opt_state = carry
        loss, grad = jax.value_and_grad(loss_fn)(u, chunks.pick(index))
        updates, new_state = optimizer.update(grad, opt_state, u)
        new_u = optax.apply_updates(u, updates)
        # a step whose loss, gradient or new parameters are not finite is skipped (a solve
        # failed, or the optimizer divided by zero)
        finite = all_finite((loss, grad, new_u))
        keep = lambda new, old: jnp.where(finite, new, old)
        carry = jtu.tree_map(keep, (new_u, new_state), carry)
        return carry, (loss, finite)

    @eqx.filter_jit
    def run_block(u, opt_state, indices):
        return jax.lax.scan(step, (u, opt_state), indices)

    def save(u):
        if checkpoint is not None:
            eqx.tree_serialise_leaves(checkpoint, eqx.combine(u, static))

    # the minibatches' order, drawn on the host: each epoch a permutation, the remainder
    # of one that does not fill a minibatch dropped
    rng = np.random.default_rng(seed)
    per_epoch = num_chunks // batch_size
    epochs = -(-steps // per_epoch)
    order = np.concatenate(
        [rng.permutation(num_chunks)[: per_epoch * batch_size] for _ in range(epochs)]
    )
    order = order[: steps * batch_size].reshape(steps, batch_size)
    # one dispatch per block (the docstring says how long)
    block = math.gcd(steps, print_every or steps, checkpoint_every or steps, _MAX_BLOCK)
    u, opt_state, outputs = u0, optimizer.init(u0), []
    with _bar(progress, steps, "learn") as bar:
        for end in range(block, steps + 1, block):
            (u, opt_state), (block_losses, finite) = run_block(
                u, opt_state, order[end - block : end]
            )
            outputs.append((block_losses, finite))
            _report(bar, "learn", end, steps, block, block_losses[-1], start, print_every)
            if checkpoint_every and end % checkpoint_every == 0:
                save(u)
    save(u)
    losses, finite = (np.concatenate(x) for x in zip(*jax.device_get(outputs), strict=True))
    skipped = int(np.sum(~finite))
    return LearnResult(eqx.combine(u, static), losses, skipped, time.perf_counter() - start)


def refine(
    model: AbstractSystem,
    ts,
    states,
    *,
    steps: int = 10,
    floor: float | None = None,
    damping: float = 1e-2,
    group_size: int = 100,
    simulate_options: dict | None = None,
    checkpoint=None,
    print_every: int | None = None,
    progress: bool = False,
) -> LearnResult:
    """Refine a model trained by `learn` on the same chunks by Gauss-Newton steps
    (Levenberg-Marquardt with Marquardt's scaling): each step builds every chunk's
    Jacobian in the parameters (`jax.jacrev`: a chunk has far fewer residuals than a
    model has parameters), the normal equations `(J^T W J + damping diag(J^T W J)) dp =
    -J^T W r` summed over groups of chunks, and solves them by Cholesky. A step that does
    not lower the objective is retried with 10 times the damping; an accepted one divides
    it by 3. A first-order optimizer stalls on a small network well before its least
    squares does (docs/fitting.md has the figures of the magnet task).

    **Arguments:**
    - `model`, `ts`, `states`, `simulate_options`: as for `learn` (the chunks' first
      observations start them).
    - `steps`: Gauss-Newton steps (each one Jacobian of every chunk, and one Cholesky
      factorization and one simulation of every chunk per damping tried).
    - `floor`: `None` (default): least squares, `sum_c |r_c|^2` over chunks `c`. A
      positive number: `sum_c log(rms_c^2 + floor^2)`, `rms_c` chunk `c`'s root mean
      square residual, minimized by iteratively reweighted least squares (weights
      `1 / (rms_c^2 + floor^2)` from each step's start, a majorizer, so an accepted step
      lowers it): every chunk above the floor weighs alike, as in a geometric mean over
      trajectories, instead of the few fast ones dominating.
    - `damping`: the initial Marquardt damping.
    - `group_size`: chunks whose Jacobians are held at once (memory: `group_size` times
      the residuals of a chunk times the parameters). The normal equations themselves
      are a `P x P` matrix in JAX's default float, `P` the model's parameters, and a step
      holds about three of them: 8 P^2 bytes each in float64, so the magnet task's 8645
      parameters (0.6 GB) took 1.8 GB more than `learn` alone, and a width-128 MLP on
      three links (34451 parameters, 9.5 GB) would need about 28 GB.
    - `checkpoint`, `print_every`, `progress`: as for `learn`, `checkpoint` written and the
      bar moved after each step.

    **Returns:** a `LearnResult`: `losses` the objective (the mean over chunks of
    `rms_c^2`, or of `log(rms_c^2 + floor^2)`) at the start and after each accepted step;
    `skipped` the number of rejected trial steps. It stops early when 8 dampings in a row
    fail to lower the objective (with a line saying so if `print_every`). A chunk whose
    simulation from the given model is not finite is a `ValueError`. The Jacobians and
    the Gram matrix are computed in the model's dtype, their sums and the factorization
    in JAX's default float.
    """
    start = time.perf_counter()
    counts = dict(steps=steps, group_size=group_size)
    _check_options("refine", checkpoint, dict(print_every=print_every), counts)
    if floor is not None:
        check_positive(floor, "refine: floor")
    check_positive(damping, "refine: damping")
    chunks = _Chunks.build(model, ts, states, simulate_options, "bwd", "refine")
    problem, (u0, static) = chunks.residuals, chunks.unknowns
    p0, unravel = ravel_pytree(u0)
    wide = jnp.promote_types(p0.dtype, jax.dtypes.canonicalize_dtype(jnp.float64))
    # the chunks in groups; the last one padded with chunk 0 at weight zero
    groups, real = _groups(chunks.num, group_size)

    def chunk_residuals(p, index):
        # `(chunks, rows)`; a chunk's first observation is its start: its residual is zero
        return problem((unravel(p), None), chunks.pick(index))[0][:, 0, 1:].reshape(len(index), -1)

    @jax.jit
    def evaluate(p, weights):
        """The objective at `p`; its weighted least squares with `weights`; the weights
        that `p` gives and its weighted least squares with them; each chunk's mean square
        residual."""
        r = chunk_residuals(p, np.arange(chunks.num))
        ms = jnp.mean(r**2, -1)
        if floor is None:
            loss, own = jnp.mean(ms), jnp.ones_like(ms)
        else:
            loss, own = jnp.mean(jnp.log(ms + floor**2)), 1 / (ms + floor**2)
        squares = jnp.sum(r**2, -1).astype(wide)
        own = own.astype(wide)
        return loss, jnp.sum(weights * squares), own, jnp.sum(own * squares), ms

    def one_chunk(p, data):
        def rows(p_):
            r = problem.segment(unravel(p_), *data)[0][1:].reshape(-1)
            return r, r

        return jax.jacrev(rows, has_aux=True)(p)

    @jax.jit
    def normal_equations(p, weights):
        def add(sums, group):
            index, keep = group
            (seg_data, y0) = chunks.pick(index)
            states = problem.states(None, y0)
            J, r = problem.over_segments(lambda s, *d: one_chunk(p, (s, *d)), states, seg_data)
            w = jnp.sqrt(jnp.where(keep, weights[index], 0.0)).astype(p.dtype)
            Jw = (w[:, None, None, None] * J).reshape(-1, p.size)
            rw = (w[:, None, None] * r).reshape(-1)
            return jtu.tree_map(
                jnp.add, sums, ((Jw.T @ Jw).astype(wide), (Jw.T @ rw).astype(wide))
            ), None

        zeros = (jnp.zeros((p.size, p.size), wide), jnp.zeros(p.size, wide))
        return jax.lax.scan(add, zeros, (groups, real))[0]

    rebuild = lambda p: eqx.combine(unravel(p), static)
    save = (
        None if checkpoint is None else lambda p: eqx.tree_serialise_leaves(checkpoint, rebuild(p))
    )
    loss, _, weights, current, ms = evaluate(p0, jnp.ones(chunks.num, wide))
    bad = np.flatnonzero(~np.isfinite(np.asarray(ms)))
    if bad.size:
        where = describe_failures(bad, chunks.num, "chunks have non-finite residuals", "chunk")
        raise ValueError(
            f"refine:{where} the model's simulation from its first observed state is not "
            "finite (its solve failed), so its residuals cannot be minimized: drop those "
            "chunks or train the model further with `learn` (which skips such steps)."
        )
    first = (loss, weights, current)
    solve = (normal_equations, evaluate, steps, damping)
    return _marquardt("refine", p0, first, solve, (start, print_every, progress), save, rebuild)


def _groups(num: int, size: int):
    """`num` items in groups of `size` (at most `num`) for a `lax.scan`: `(groups, real)`,
    the items' indices `(G, size)`, the last group padded with item 0, and which are real."""
    size = min(size, num)
    padded = -(-num // size) * size
    return (np.arange(padded) % num).reshape(-1, size), (np.arange(padded) < num).reshape(-1, size)


@jax.jit
def _damped_step(p, A, g, lam):
    """`p` plus the solution of `(A + lam diag(A)) dp = -g` (Cholesky), with a floor
    added to the diagonal: 1e-12 times its largest entry in float64, and in a coarser
    dtype that times `(eps / eps_float64)^(3/4)` (3.5e-6 in float32). It keeps the matrix
    positive definite, and holds still a parameter the data barely see, whose `diag(A)`
    and `g` are then rounding noise of `p`'s dtype. With 1e-12 in float32 too, a float32
    model's `fit_accelerations(..., inertia=True)` moved such a parameter by 550 (its
    column `1e-11` against `159`: at the identity inertia the accelerations do not depend
    on the second link's inertia) and the fit diverged (`M / M_00` off by 1e3)."""
    d = jnp.diag(A)
    coarser = float(jnp.finfo(p.dtype).eps / jnp.finfo(jnp.float64).eps) ** 0.75
    A = A + jnp.diag(lam * d + 1e-12 * coarser * jnp.max(d))
    dp = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(A), -g)
    return p + dp.astype(p.dtype)


def _marquardt(name, p, first, solve, report, save, rebuild) -> LearnResult:
    """`refine`'s and `fit_accelerations`' Levenberg-Marquardt loop from `p`, `first` its
    `(loss, weights, weighted least squares)`, `solve` `(normal_equations, evaluate,
    steps, damping)`: each step solves the damped normal equations
    `normal_equations(p, weights) -> (J^T W J, J^T W r)`; a trial that does not lower the
    weighted least squares (`evaluate(trial, weights)`, as `refine`'s) is retried with
    10 times the damping, an accepted one divides it by 3; 8 failures in a row stop it.
    `save(p)` (unless `None`) after each step and at the end. Returns the `LearnResult`
    of the model `rebuild(p)`: the losses (the first and each accepted step's), the
    rejected trials, the time since `report`'s start."""
    normal_equations, evaluate, steps, lam = solve
    start, print_every, progress = report
    save = save or (lambda p: None)
    (loss, weights, current), skipped = first, 0
    losses = [float(loss)]
    with _bar(progress, steps, name) as bar:
        for k in range(steps):
            A, g = normal_equations(p, weights)
            for _ in range(8):
                trial = _damped_step(p, A, g, lam)
                out = evaluate(trial, weights)
                if bool(jnp.isfinite(out[1])) and out[1] < current:
                    p, lam, (loss, _, weights, current, _) = trial, lam / 3, out
                    break
                skipped, lam = skipped + 1, 10 * lam
            else:  # no damping lowered it: at a minimum, as far as the steps resolve
                if print_every:
                    print(
                        f"{name}: stopped after step {k}/{steps}: 8 dampings in a row did "
                        f"not lower the objective (loss {float(loss):.4e})"
                    )
                break
            losses.append(float(loss))
            _report(bar, name, k + 1, steps, 1, loss, start, print_every)
            save(p)
    save(p)
    return LearnResult(rebuild(p), np.asarray(losses), skipped, time.perf_counter() - start)


def _second_derivatives(t, x, xdot, at):
    """The second derivatives at times `at` of the polynomial of degree `2T - 1` through
    the `T` values `x` `(T, d)` and first derivatives `xdot` at times `t` (Hermite
    interpolation; in time scaled to `[-1, 1]` for conditioning)."""
    center, half = (t[0] + t[-1]) / 2, (t[-1] - t[0]) / 2
    tau, s = (t - center) / half, (at - center) / half
    power = jnp.arange(2 * len(t))
    values = tau[:, None] ** power
    slopes = power * tau[:, None] ** jnp.maximum(power - 1, 0)
    coef = jnp.linalg.solve(jnp.concatenate([values, slopes]), jnp.concatenate([x, half * xdot]))
    curvature = power * (power - 1) * s[:, None] ** jnp.maximum(power - 2, 0)
    return curvature @ coef / half**2


def estimate_accelerations(ts, states, *, tolerance: float = 2e-5):
    """Accelerations of observed chunks `(q, qdot)` at their interior observations, from
    the polynomial of degree `2T - 1` through each chunk's `T` positions and velocities
    (Hermite interpolation), with weights from an estimate of their error.

    **Arguments:**
    - `ts`: observation times `(T,)` shared by the chunks, or `(B, T)`; `T >= 3`.
    - `states`: `(q, qdot)`, each `(B, T, ...)` (positions and their time derivatives).
    - `tolerance`: the error, relative to the root mean square acceleration over the
      data, at which an estimate's weight is halved.

    **Returns:** `(accelerations, weights)`: `(B, T - 2, ...)` `qddot` at observations 1 to
    `T - 2`, and `(B, T - 2)` weights `1 / (1 + (e / (tolerance a_rms))^2)`, `e` the
    larger change of the estimate when the chunk's first or its last observation is left
    out (on the magnet task of `benchmarks/learned_lagrangian.py` its log correlates with
    the log of the true error at 0.97 to 0.99: the fast passes near the magnets have
    large errors and small weights)."""
    check_positive(tolerance, "estimate_accelerations: tolerance")
    if any(isinstance(x, dict) for x in states):
        raise ValueError(
            "estimate_accelerations: states must be arrays (q, qdot); a mixed space's "
            "dicts of arrays are not supported."
        )
    q, qdot = (jnp.asarray(x) for x in states)
    if q.shape != qdot.shape or q.ndim < 2 or q.shape[1] < 3:
        raise ValueError(
            "estimate_accelerations: states must be (q, qdot) of the same shape (B, T, ...) "
            f"with T >= 3 observations, got shapes {q.shape} and {qdot.shape}."
        )
    num, T = q.shape[:2]
    ts = jnp.broadcast_to(jnp.asarray(ts, q.dtype), (num, T))
    flat = lambda x: x.reshape(num, T, -1)

    def one(t, x, xdot):
        estimates = [
            _second_derivatives(t[keep], x[keep], xdot[keep], t[1:-1])
            for keep in (slice(None), slice(1, None), slice(None, -1))
        ]
        change = jnp.maximum(*(jnp.linalg.norm(e - estimates[0], axis=-1) for e in estimates[1:]))
        return estimates[0], change

    acc, change = jax.vmap(one)(ts, flat(q), flat(qdot))
    scale = tolerance * jnp.sqrt(jnp.mean(jnp.sum(acc**2, -1)))
    return acc.reshape((num, T - 2) + q.shape[2:]), 1 / (1 + (change / scale) ** 2)


def fit_accelerations(
    model: AbstractSystem,
    ts,
    states,
    *,
    steps: int = 1,
    ridge: float | None = None,
    tolerance: float = 2e-5,
    inertia: bool = False,
    group_size: int = 1000,
    print_every: int | None = None,
    progress: bool = False,
) -> LearnResult:
    """Fit a model's potential to accelerations estimated from observed chunks: minimizes
    `sum_j w_j |qddot_model(q_j, qdot_j) - a_j|^2` over the chunks' interior observations
    `j`, with `a_j` and `w_j` from `estimate_accelerations` (no solve of the model), by
    Levenberg-Marquardt steps whose Marquardt damping starts at `ridge`. For a potential
    linear in its parameters (`LearnedLagrangian(n, depth=0, features=...)`) the
    accelerations are linear in them, and one step is the ridge-regularized least-squares
    solution: a start for `refine`, which then fits the trajectories themselves. On the
    magnet task of `benchmarks/learned_lagrangian.py` (`SphereKernels()`: 2045 fitted)
    one step took 12 to 20 s and scored a rollout error of 1.2e-3, 30 `refine` steps after
    it 3.2e-4 (docs/fitting.md).

    **Arguments:**
    - `model`: a sphere_mech system with state `(q, qdot)` (form 1) that is an equinox
      Module with its parameters as floating-point leaves; of a `LearnedLagrangian` the
      inertia is held (it and the potential are learned up to a common factor: holding
      the inertia fixes it), every other floating leaf is fitted.
    - `ts`, `states`: the observed chunks, as for `learn` (`T >= 3` observations).
    - `steps`: Levenberg-Marquardt steps (one suffices for a linear potential).
    - `ridge`: the initial Marquardt damping `ridge diag(J^T W J)` (a ridge in the scaled
      parameters, pulling toward the model's parameters: zero for a new linear one).
      Default 1e-10, and 1e-3 with `inertia`: from 1e-10 the first, nearly undamped step
      of the nonlinear fit overshot, and 8 larger dampings in a row then failed to
      lower the error (a 3-link chain stopped after one step at a quarter of its start).
    - `tolerance`: `estimate_accelerations`' tolerance.
    - `inertia`: also fit a `LearnedLagrangian`'s inertia, all of it but the first
      diagonal entry of its Cholesky factor (the common factor). The accelerations are
      then nonlinear in the parameters: take several `steps` (the chains of
      `benchmarks/learned_lagrangian.py` converged in 12 and 13 of 30; the 2-link chain of
      `tests/test_learn.py` in 14 accepted steps in float64 and 8 in float32, to
      `M / M_00` within 2e-8 and 9e-7).
    - `group_size`: observations whose Jacobians are held at once.
    - `print_every`, `progress`: as for `refine`.

    **Returns:** a `LearnResult`, `losses` the weighted mean square acceleration error at
    the start and after each accepted step, `skipped` the rejected trials."""
    start = time.perf_counter()
    _check_options(
        "fit_accelerations",
        None,
        dict(print_every=print_every),
        dict(steps=steps, group_size=group_size),
    )
    check_bool(inertia, "fit_accelerations: inertia")
    ridge = (1e-3 if inertia else 1e-10) if ridge is None else ridge
    check_positive(ridge, "fit_accelerations: ridge")
    if inertia and not isinstance(model, LearnedLagrangian):
        raise ValueError(
            "fit_accelerations: inertia=True fits a LearnedLagrangian's inertia, got "
            f"{type(model).__name__} (all of its floating leaves are fitted anyway)."
        )
    if isinstance(model, AbstractSystem) and model.state_name != "qdot":
        raise ValueError(
            "fit_accelerations: model must be a system with state (q, qdot) (form 1), got "
            f"{type(model).__name__} with state (q, {model.state_name})."
        )
    ts, (q, qdot), _, dtype = _observed_chunks(model, ts, states, "fit_accelerations", 3)
    acc, weights = estimate_accelerations(ts, (q, qdot), tolerance=tolerance)
    inner = lambda x: x[:, 1:-1].reshape((-1,) + x.shape[2:])
    ts = jnp.broadcast_to(ts.astype(dtype), q.shape[:2])
    data = (
        inner(ts),
        inner(q),
        inner(qdot),
        acc.reshape((-1,) + acc.shape[2:]),
        weights.reshape(-1),
    )
    num = data[0].shape[0]
    free = jtu.tree_map(eqx.is_inexact_array, model)
    if isinstance(model, LearnedLagrangian) and not inertia:
        free = eqx.tree_at(lambda m: m.inertia_factor, free, False)
    u0, static = eqx.partition(model, free)
    p0, unravel = ravel_pytree(u0)
    held = None  # the index in p of a parameter held within a fitted leaf
    if inertia:
        ones = jtu.tree_map(jnp.ones_like, u0)
        ones = eqx.tree_at(lambda m: m.inertia_factor, ones, replace_fn=lambda F: F.at[0, 0].set(0))
        held = int(np.argmin(ravel_pytree(ones)[0]))
    wide = jnp.promote_types(p0.dtype, jax.dtypes.canonicalize_dtype(jnp.float64))
    groups, real = _groups(num, group_size)

    def residual(p, t, q_, qdot_, a, w):
        system = eqx.combine(unravel(p), static)
        qddot = system.rates(t, (q_, qdot_), None)[1]
        return jnp.sqrt(w) * jnp.reshape(qddot - a, (-1,)).astype(p.dtype)

    # the data are arguments, not constants of the programs (XLA would fold them)
    @jax.jit
    def evaluate_at(p, data):
        r = jax.vmap(residual, (None, 0, 0, 0, 0, 0))(p, *data)
        squares = jnp.sum(r**2).astype(wide)
        return squares / num, squares

    @jax.jit
    def normal_equations_at(p, data):
        def add(sums, group):
            index, keep = group
            t, q_, qdot_, a, w = (x[index] for x in data)
            rows = lambda *args: (residual(*args),) * 2
            jac = jax.vmap(jax.jacrev(rows, has_aux=True), (None, 0, 0, 0, 0, 0))
            J, r = jac(p, t, q_, qdot_, a, w * keep)
            J, r = J.reshape(-1, p.size), r.reshape(-1)
            sums = jtu.tree_map(jnp.add, sums, ((J.T @ J).astype(wide), (J.T @ r).astype(wide)))
            return sums, None

        zeros = (jnp.zeros((p.size, p.size), wide), jnp.zeros(p.size, wide))
        A, g = jax.lax.scan(add, zeros, (groups, real))[0]
        if held is None:
            return A, g
        A = A.at[held].set(0).at[:, held].set(0).at[held, held].set(1)
        return A, g.at[held].set(0)  # the held parameter's step is zero

    def evaluate(p, weights):  # as `refine`'s, the weights fixed
        loss, squares = evaluate_at(p, data)
        return loss, squares, weights, squares, None

    normal_equations = lambda p, weights: normal_equations_at(p, data)
    loss, squares, *_ = evaluate(p0, None)
    solve = (normal_equations, evaluate, steps, ridge)
    report = (start, print_every, progress)
    rebuild = lambda p: eqx.combine(unravel(p), static)
    return _marquardt("fit_accelerations", p0, (loss, None, squares), solve, report, None, rebuild)
