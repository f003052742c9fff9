"""Non-conservative and driven effects, as generalized forces derived from virtual work
(`delta W = sum_i f_i . delta q_i`)."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._geometry import project, vee
from .._linalg import tridiagonal_spd_solve
from .._misc import tree_add, tree_dtype
from .._spaces import chain_attitude, chain_parts, chain_state
from . import base
from .base import AbstractCommand, AbstractDrive, AbstractForce, ParameterError


def _at_parents(values, parents, support):
    """Each sphere's parent's row of `values` (`(n, ...)`), `support` (one row) for the
    spheres hanging from the support."""
    return jnp.concatenate([support.astype(values.dtype), values])[parents + 1]


def _joint_rates(q, qdot, scene):
    """Each joint's `omega_i - omega_p`, `(n, 3)` (`omega_i = q_i x qdot_i`; the support's
    `omega_p`: zero, or a `RigidBase`'s `vee(Rdot R^T) = R Omega`, whose spin is its own).
    `q`, `qdot`: the scene's state."""
    x = scene.spheres(q)
    omega = jnp.cross(x, scene.spheres(qdot))
    R, Rdot = chain_attitude(q), chain_attitude(qdot)
    support = jnp.zeros_like(omega[:1]) if R is None else vee(Rdot @ jnp.swapaxes(R, -1, -2))
    return omega - _at_parents(omega, scene.parents(), support)


def _with_free_spins(x, rel, parents, c):
    """The joints' relative angular velocities `r_i = rel_i + s_i q_i - s_p q_p` with the
    links' spins about themselves `s` as the joints' torques set them: a link (a point
    mass on a massless rod) has no inertia about its own axis, so its spin makes the axial
    torque on it vanish, the minimum over `s` of `R = 1/2 sum_i c_i |r_i|^2`. A chain
    turning rigidly with a `RigidBase` has every `r_i = 0`. The solve is tridiagonal (each
    sphere's parent is the one before it or the support), regularized by `eps max c` where
    undamped joints leave parallel links' spins free."""
    # dR/ds = K s + b: the joint of sphere k (own spin) and that of its child k + 1
    child = jnp.asarray(np.append(parents[1:] == np.arange(len(parents) - 1), False))
    c_child = jnp.where(child, jnp.roll(c, -1), 0.0)
    cos = jnp.sum(x * jnp.roll(x, -1, axis=0), axis=-1)
    b = c * jnp.sum(rel * x, -1) - c_child * jnp.sum(jnp.roll(rel, -1, axis=0) * x, -1)
    eps = jnp.finfo(rel.dtype).eps * jnp.max(c) + jnp.finfo(rel.dtype).tiny
    spin = tridiagonal_spd_solve(c + c_child + eps, (-c_child * cos)[:-1], -b)
    spin_x = spin[:, None] * x  # the support's own spin is in `rel` already
    return rel + spin_x - _at_parents(spin_x, parents, jnp.zeros_like(spin_x[:1]))


def _not_a_command(name: str, x) -> None:
    """Refuse a flight command where a torque or force is expected: it is what
    `GeometricControl` flies (called as a drive, it failed with a `TypeError`)."""
    if isinstance(x, AbstractCommand):
        message = f"{name} must be a vector or a drive, not a flight command"
        what = type(x).__name__
        raise ParameterError(name, f"{message}: fly {what}(...) with GeometricControl(command=...)")


def _drive(name: str, on_base: bool = False):
    """A drive field: a constant `(3,)` vector (`(m,)` on the `Base`) or a function."""

    def convert(x):
        _not_a_command(name, x)
        if callable(x):
            return x
        x = base.as_float(x, name)
        if not on_base:
            base.check_vector(name, x)
        elif jnp.ndim(x) != 1:
            what = f"an (m,) vector (one component per axis of the Base), got shape {jnp.shape(x)}"
            raise ParameterError(name, f"{name} must be {what}")
        return x

    return eqx.field(converter=convert)


def _check_drive(field: str, drive, scene, shape=(3,)) -> None:
    """Check an `AbstractDrive` in `field`, and its output's shape (errors: `field.<its field>`)."""
    if not isinstance(drive, AbstractDrive):
        return
    try:
        drive.check(scene)
    except ParameterError as e:
        e.field = f"{field}.{e.field}" if e.field else field
        raise
    spheres = jax.ShapeDtypeStruct((scene.n, 3), jnp.result_type(float))
    base = None if scene.base is None else jax.ShapeDtypeStruct((scene.base.m,), spheres.dtype)
    rigid = scene.rigid_body is not None
    state = chain_state(
        base, spheres, jax.ShapeDtypeStruct((1, 3, 3), spheres.dtype) if rigid else None
    )
    out = jax.eval_shape(drive, jax.ShapeDtypeStruct((), spheres.dtype), state, state, None)
    if out.shape != shape:
        message = f"{type(drive).__name__} returns shape {out.shape}, expected {shape}"
        raise ParameterError(field, f"{field}: {message}")


def _evaluate(drive, t, q, qdot, args, shape=(3,)):
    out = jnp.asarray(drive(t, q, qdot, args) if callable(drive) else drive, tree_dtype(q))
    if out.shape != shape:
        raise ValueError(
            f"a torque or force function must return shape {shape}, got shape {out.shape}."
        )
    return out


class JointDamping(AbstractForce):
    """Viscous damping in every joint (between a link and its parent, or the support: a
    `RigidBase`'s body, which takes the reaction).

    Rayleigh function `R = 1/2 sum_i c_i |r_i|^2`, `f = -dR/dqdot`, its power `-2R <= 0`.
    `r_i` is the link's angular velocity relative to its parent's (or the support's: zero,
    or a `RigidBase`'s body, which takes the reaction), `r_i = omega_i + s_i q_i - (omega_p
    + s_p q_p)` with `omega_i = q_i x qdot_i`. A link (a point mass on a massless rod) has
    no inertia about its own axis, so its spin `s_i` is what makes the axial torque on it
    vanish: `R` is minimized over the spins (a tridiagonal solve, O(n)). The joints'
    torques are then internal: on a `RigidBase` with no other effect the total angular
    momentum is conserved, and a chain turning rigidly with the body is not damped.

    **Arguments:**
    - `coefficient`: `c` (N m s, `>= 0`), a scalar or one value per sphere.
    """

    coefficient: jax.Array = eqx.field(converter=base.number("coefficient"))

    def __check_init__(self):
        base.check_sign("coefficient", self.coefficient, " (N m s)", strict=False)

    def check(self, scene):
        if jnp.ndim(self.coefficient):
            what = f"a scalar or {scene.n} values, one per sphere"
            base.check_shape("coefficient", self.coefficient, (scene.n,), what)

    def generalized_force(self, t, q, qdot, scene, args):
        # f = -dR/dqdot at the minimizing spins (the envelope theorem: dR/ds = 0 there),
        # not through their solve: the pullback of the relative rates applied to c r
        rel, pullback = jax.vjp(lambda v: _joint_rates(q, v, scene), qdot)
        parents = scene.parents()
        c = jnp.broadcast_to(self.coefficient, parents.shape).astype(rel.dtype)
        r = _with_free_spins(scene.spheres(q), rel, parents, c)
        return pullback(-c[:, None] * r)[0]


class BaseTorque(AbstractForce):
    """A torque in the joint of a link, applied by its parent (or the support).

    `f_link = tau x q_link`, and `-tau x q_parent` on the parent (on a `RigidBase`'s body,
    which carries the first joint: the body torque `-R^T P tau`, `P` the projection across
    the link, whose spin about itself is free). A point-mass link takes only the part of
    `tau` across it (its massless rod spins freely about itself), so between two links the
    torque is internal only where `tau` is across both (along `q_parent x q_link`, as a
    joint's motor on two rods); otherwise the total angular momentum changes by `P_link tau
    - P_parent tau`, as a torque from the support would.

    **Arguments:**
    - `torque`: `tau` (N m): a constant `(3,)` vector or a function
      `torque(t, q, qdot, args) -> (3,)` (a controller such as `PDTorque`).
    - `link`: the link's index (static; default 0: the base joint of the first link).
    """

    torque: jax.Array | Callable = _drive("torque")
    link: int = eqx.field(default=0, static=True)

    def check(self, scene):
        base.check_index(self, "link", self.link, scene.n)
        _check_drive("torque", self.torque, scene)

    def generalized_force(self, t, q, qdot, scene, args):
        tau, s = _evaluate(self.torque, t, q, qdot, args), scene.spheres(q)
        link = self.link % s.shape[0]
        f = jnp.zeros_like(s).at[link].add(jnp.cross(tau, s[link]))
        parent = int(scene.parents()[link])
        if parent >= 0:
            f = f.at[parent].add(-jnp.cross(tau, s[parent]))
        elif scene.rigid_body is not None:  # the body's reaction, to the part the link takes
            reaction = -chain_attitude(q)[0].T @ project(s[link], tau)
            return tree_add(scene.on_spheres(f), scene.on_base(q, jnp.zeros_like(tau), reaction))
        return scene.on_spheres(f)


class PDTorque(AbstractDrive):
    """A proportional-derivative controller for `BaseTorque`.

    Steers link `link` toward the unit vector `target`: `tau = kp q_link x target -
    kd omega_link`; its generalized force is `kp P target - kd qdot_link` (P the tangent
    projection).

    **Arguments:**
    - `kp`, `kd`: proportional and derivative gains (N m and N m s, `>= 0`).
    - `target`: the unit vector the link is steered toward.
    - `link`: the index of the link whose direction is measured (static).
    """

    kp: jax.Array = eqx.field(converter=base.number("kp"))
    kd: jax.Array = eqx.field(default=0.0, converter=base.number("kd"))
    target: jax.Array = eqx.field(default=(0.0, 0.0, 1.0), converter=base.number("target"))
    link: int = eqx.field(default=0, static=True)

    def __check_init__(self):
        base.check_sign("kp", self.kp, " (N m)", strict=False, scalar=True)
        base.check_sign("kd", self.kd, " (N m s)", strict=False, scalar=True)
        base.check_vector("target", self.target, unit=True)

    def check(self, scene):
        base.check_index(self, "link", self.link, scene.n)

    def __call__(self, t, q, qdot, args):
        x, v = chain_parts(q)[1][self.link], chain_parts(qdot)[1][self.link]
        return self.kp * jnp.cross(x, self.target) - self.kd * jnp.cross(x, v)


class TipForce(AbstractForce):
    """A force on one mass (default the last one: the tip of a chain).

    `f = d/dq (d . x_point(q))` with `d` held fixed (virtual work).

    **Arguments:**
    - `force`: `d` (N): a constant `(3,)` vector or a function
      `force(t, q, qdot, args) -> (3,)`.
    - `point`: the index of the mass it acts on (static; negative counts from the end).
    """

    force: jax.Array | Callable = _drive("force")
    point: int = eqx.field(default=-1, static=True)

    def check(self, scene):
        base.check_index(self, "point", self.point, scene.n)
        _check_drive("force", self.force, scene)

    def generalized_force(self, t, q, qdot, scene, args):
        d = _evaluate(self.force, t, q, qdot, args)
        return jax.grad(lambda q_: jnp.dot(d, scene.positions(q_)[self.point]))(q)


class VibratingSupport(AbstractForce):
    """A prescribed motion of the support (every chain base and sphere centre).

    `s(t) = amplitude cos(angular_frequency t + phase) direction`, felt in the support
    frame as the inertial force `-m_i s''(t)` on each mass, a `Base` included (a force,
    not a potential, so that the work-energy balance uses `power`). The Kapitza pendulum:
    a pendulum of length `l` is stable upright when
    `amplitude^2 angular_frequency^2 > 2 g l` (vertical vibration).

    **Arguments:**
    - `amplitude`, `angular_frequency`, `phase`: `a` (m), `w` (rad/s) and the phase (rad).
    - `direction`: the unit vector of the motion.
    """

    amplitude: jax.Array = eqx.field(converter=base.number("amplitude"))
    angular_frequency: jax.Array = eqx.field(converter=base.number("angular_frequency"))
    direction: jax.Array = eqx.field(default=(0.0, 0.0, 1.0), converter=base.number("direction"))
    phase: jax.Array = eqx.field(default=0.0, converter=base.number("phase"))

    def __check_init__(self):
        base.check_sign("amplitude", self.amplitude, " (m)", strict=False, scalar=True)
        base.check_sign(
            "angular_frequency", self.angular_frequency, " (rad/s)", strict=False, scalar=True
        )
        base.check_shape("phase", self.phase, (), "a scalar")
        base.check_vector("direction", self.direction, unit=True)

    def acceleration(self, t):
        """The acceleration of the support, `s''(t)`.

        **Arguments:**
        - `t`: time.

        **Returns:** a `(3,)` vector (m/s^2).
        """
        w = self.angular_frequency
        return -self.amplitude * w**2 * jnp.cos(w * t + self.phase) * self.direction

    def generalized_force(self, t, q, qdot, scene, args):
        a = self.acceleration(t).astype(tree_dtype(q))
        m = scene.point_masses()
        return jax.grad(lambda q_: -jnp.sum(m * (scene.points(q_) @ a)))(q)


def _per_axis(scene) -> str:
    """The words for "one value per axis of the scene's base", naming its class."""
    return f"one per axis of the {type(scene.base).__name__}"


def _base_vector(owner, name: str, x, scene) -> None:
    """`x` is a scalar or one value per axis of the scene's `Base`."""
    if jnp.ndim(x) and jnp.shape(x) != (m := scene.base.m,):
        what, got = f"a scalar or {m} values, {_per_axis(scene)}", jnp.shape(x)
        raise ParameterError(name, f"{type(owner).__name__}.{name} must be {what}, got shape {got}")


class BaseForce(AbstractForce):
    """A force on the `Base`, in its coordinates (one component per axis: the thrust of a
    drone, the push on a cart).

    Virtual work `f . delta x`: the base's part of the generalized force.

    **Arguments:**
    - `force`: `f` (N): a constant `(m,)` vector or a function
      `force(t, q, qdot, args) -> (m,)` of the scene's state (a controller such as
      `PDPosition`, or `Harmonic`).
    """

    force: jax.Array | Callable = _drive("force", on_base=True)

    def check(self, scene):
        if scene.base is None:
            raise ParameterError("", "BaseForce needs a Base in the scene")
        if not callable(self.force) and jnp.shape(self.force) != (scene.base.m,):
            what = f"{scene.base.m} components, {_per_axis(scene)}"
            raise ParameterError(
                "force", f"force must have {what}, got shape {jnp.shape(self.force)}"
            )
        _check_drive("force", self.force, scene, (scene.base.m,))

    def generalized_force(self, t, q, qdot, scene, args):
        return scene.on_base(q, _evaluate(self.force, t, q, qdot, args, (scene.base.m,)))


class BodyTorque(AbstractForce):
    """A torque on a `RigidBase`, in its body axes (the moment of its rotors, a reaction
    wheel's, a controller's).

    Virtual work `tau . eta` for `delta R = R hat(eta)`: the attitude's part of the
    generalized force.

    **Arguments:**
    - `torque`: `tau` (N m, body axes): a constant `(3,)` vector or a function
      `torque(t, q, qdot, args) -> (3,)` of the scene's state.
    """

    torque: jax.Array | Callable = _drive("torque")

    def check(self, scene):
        if scene.rigid_body is None:
            raise ParameterError("", "BodyTorque needs a RigidBase in the scene")
        _check_drive("torque", self.torque, scene)

    def generalized_force(self, t, q, qdot, scene, args):
        tau = _evaluate(self.torque, t, q, qdot, args)
        return scene.on_base(q, jnp.zeros((3,), tau.dtype), tau)


class PDPosition(AbstractDrive):
    """A proportional-derivative position controller for `BaseForce` (a drone holding a
    hover point, or flying a step to a new one).

    `f = kp (target(t) - x) - kd xdot + feedforward` in the base's coordinates, with
    `target(t) = target` before `step_time` and `target + step` from then on.

    **Arguments:**
    - `kp`, `kd`: proportional and derivative gains (N/m and N s/m, `>= 0`).
    - `target`: the set point (m): a scalar or one value per axis of the `Base`.
    - `feedforward`: a constant force added (N), e.g. the weight the drone carries: a
      scalar or one value per axis.
    - `step`: the change of set point at `step_time` (m): a scalar or one per axis.
    - `step_time`: when the set point changes (s).
    """

    kp: jax.Array = eqx.field(converter=base.number("kp"))
    kd: jax.Array = eqx.field(default=0.0, converter=base.number("kd"))
    target: jax.Array = eqx.field(default=0.0, converter=base.number("target"))
    feedforward: jax.Array = eqx.field(default=0.0, converter=base.number("feedforward"))
    step: jax.Array = eqx.field(default=0.0, converter=base.number("step"))
    step_time: jax.Array = eqx.field(default=0.0, converter=base.number("step_time"))

    def __check_init__(self):
        base.check_sign("kp", self.kp, " (N/m)", strict=False, scalar=True)
        base.check_sign("kd", self.kd, " (N s/m)", strict=False, scalar=True)
        base.check_shape("step_time", self.step_time, (), "a scalar")

    def check(self, scene):
        if scene.base is None:
            raise ParameterError("", "PDPosition needs a Base in the scene")
        for name in ("target", "feedforward", "step"):
            _base_vector(self, name, getattr(self, name), scene)

    def __call__(self, t, q, qdot, args):
        x, v = chain_parts(q)[0], chain_parts(qdot)[0]
        target = self.target + jnp.where(t >= self.step_time, self.step, 0.0)
        f = self.kp * (target - x) - self.kd * v + self.feedforward
        return jnp.broadcast_to(f, x.shape)


class Harmonic(AbstractDrive):
    """A force or torque varying harmonically in time, for `BaseForce`, `TipForce` or
    `BaseTorque`: `f(t) = offset + amplitude cos(angular_frequency t + phase)`.

    **Arguments:**
    - `amplitude`: a vector of the force's shape (`(m,)` on a base, `(3,)` otherwise).
    - `angular_frequency`, `phase`: scalars (rad/s, rad).
    - `offset`: a constant part, of the force's shape (or a scalar).
    """

    amplitude: jax.Array = eqx.field(converter=base.number("amplitude"))
    angular_frequency: jax.Array = eqx.field(converter=base.number("angular_frequency"))
    phase: jax.Array = eqx.field(default=0.0, converter=base.number("phase"))
    offset: jax.Array = eqx.field(default=0.0, converter=base.number("offset"))

    def __check_init__(self):
        base.check_sign(  # as VibratingSupport's
            "angular_frequency", self.angular_frequency, " (rad/s)", strict=False, scalar=True
        )
        base.check_shape("phase", self.phase, (), "a scalar")
        if jnp.ndim(self.amplitude) != 1:
            got = jnp.shape(self.amplitude)
            raise ParameterError("amplitude", f"amplitude must be a vector, got shape {got}")
        if jnp.ndim(self.offset) and jnp.shape(self.offset) != jnp.shape(self.amplitude):
            what = f"a scalar or of amplitude's shape {jnp.shape(self.amplitude)}"
            raise ParameterError("offset", f"offset must be {what}, got {jnp.shape(self.offset)}")

    def __call__(self, t, q, qdot, args):
        return self.offset + self.amplitude * jnp.cos(self.angular_frequency * t + self.phase)
