"""Non-conservative and driven effects, as generalized forces derived from virtual work
(`delta W = sum_i f_i . delta q_i`)."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from . import base
from .base import AbstractDrive, AbstractForce


def _relative_omega(q, qdot, scene):
    """`omega_i - omega_parent(i)` for every joint (`omega_i = q_i x qdot_i`)."""
    omega = jnp.cross(q, qdot)
    padded = jnp.concatenate([jnp.zeros_like(omega[:1]), omega])
    return omega - padded[scene.parents() + 1]


def _drive_value(x):
    return x if callable(x) else base.as_float(x)


def _evaluate(drive, t, q, qdot, args):
    out = jnp.asarray(drive(t, q, qdot, args) if callable(drive) else drive, dtype=q.dtype)
    if out.shape != (3,):
        raise ValueError(f"a torque or force function must return a (3,) vector, got "
                         f"shape {out.shape}.")
    return out


class JointDamping(AbstractForce):
    """Viscous damping in every joint (between a link and its parent, or the support).

    Rayleigh function `R = c/2 sum_i |omega_i - omega_parent(i)|^2`, `f = -dR/dqdot`; its
    power is `-2R <= 0`.

    **Arguments:**
    - `coefficient`: `c` (N m s, `>= 0`), a scalar or one value per sphere.
    """

    coefficient: jax.Array = eqx.field(converter=base.as_float)

    def __check_init__(self):
        base.check_sign("coefficient", self.coefficient, " (N m s)", strict=False)

    def check(self, scene):
        if jnp.ndim(self.coefficient):
            base.check_shape("coefficient", self.coefficient, (scene.n,),
                        f"a scalar or {scene.n} values, one per sphere")

    def generalized_force(self, t, q, qdot, scene, args):
        def dissipation(v):
            w = _relative_omega(q, v, scene)
            return 0.5 * jnp.sum(self.coefficient * jnp.sum(w * w, axis=-1))

        return -jax.grad(dissipation)(qdot)


class BaseTorque(AbstractForce):
    """A torque in the joint of a link, applied by its parent (or the support).

    `f_link = tau x q_link`, and `-tau x q_parent` on the parent.

    **Arguments:**
    - `torque`: `tau` (N m): a constant `(3,)` vector or a function
      `torque(t, q, qdot, args) -> (3,)` (a controller such as `PDTorque`).
    - `link`: the link's index (static; default 0: the base joint of the first link).
    """

    torque: jax.Array | Callable = eqx.field(converter=_drive_value)
    link: int = eqx.field(default=0, static=True)

    def __check_init__(self):
        if not callable(self.torque):
            base.check_vector("torque", self.torque)

    def check(self, scene):
        base.check_index(self, "link", self.link, scene.n)
        if isinstance(self.torque, AbstractDrive):
            self.torque.check(scene)

    def generalized_force(self, t, q, qdot, scene, args):
        tau = _evaluate(self.torque, t, q, qdot, args)
        link = self.link % q.shape[0]
        f = jnp.zeros_like(q).at[link].add(jnp.cross(tau, q[link]))
        parent = int(scene.parents()[link])
        if parent >= 0:
            f = f.at[parent].add(-jnp.cross(tau, q[parent]))
        return f


class PDTorque(AbstractDrive):
    """A proportional-derivative controller for `BaseTorque`.

    Steers link `link` toward the unit vector `target`: `tau = kp q_link x target -
    kd omega_link`; its generalized force is `kp P target - kd qdot_link` (P the tangent
    projection).

    **Arguments:**
    - `kp`: proportional gain (N m, `>= 0`).
    - `kd`: derivative gain (N m s, `>= 0`).
    - `target`: the unit vector the link is steered toward.
    - `link`: the index of the link whose direction is measured (static).
    """

    kp: jax.Array = eqx.field(converter=base.as_float)
    kd: jax.Array = eqx.field(default=0.0, converter=base.as_float)
    target: jax.Array = eqx.field(default=(0.0, 0.0, 1.0), converter=base.as_float)
    link: int = eqx.field(default=0, static=True)

    def __check_init__(self):
        base.check_sign("kp", self.kp, " (N m)", strict=False, scalar=True)
        base.check_sign("kd", self.kd, " (N m s)", strict=False, scalar=True)
        base.check_vector("target", self.target, unit=True)

    def check(self, scene):
        base.check_index(self, "link", self.link, scene.n)

    def __call__(self, t, q, qdot, args):
        x, v = q[self.link], qdot[self.link]
        return self.kp * jnp.cross(x, self.target) - self.kd * jnp.cross(x, v)


class TipForce(AbstractForce):
    """A force on one mass (default the last one: the tip of a chain).

    `f = d/dq (d . x_point(q))` with `d` held fixed (virtual work).

    **Arguments:**
    - `force`: `d` (N): a constant `(3,)` vector or a function
      `force(t, q, qdot, args) -> (3,)`.
    - `point`: the index of the mass it acts on (static; negative counts from the end).
    """

    force: jax.Array | Callable = eqx.field(converter=_drive_value)
    point: int = eqx.field(default=-1, static=True)

    def __check_init__(self):
        if not callable(self.force):
            base.check_vector("force", self.force)

    def check(self, scene):
        base.check_index(self, "point", self.point, scene.n)

    def generalized_force(self, t, q, qdot, scene, args):
        d = _evaluate(self.force, t, q, qdot, args)
        return jax.grad(lambda q_: jnp.dot(d, scene.positions(q_)[self.point]))(q)


class VibratingSupport(AbstractForce):
    """A prescribed motion of the support (every chain base and sphere centre).

    `s(t) = amplitude cos(angular_frequency t + phase) direction`, felt in the support
    frame as the inertial force `-m_i s''(t)` on each mass (a force, not a potential, so
    that the work-energy balance uses `power`). The Kapitza pendulum: a pendulum of length
    `l` is stable upright when `amplitude^2 angular_frequency^2 > 2 g l` (vertical
    vibration).

    **Arguments:**
    - `amplitude`: `a` (m).
    - `angular_frequency`: `w` (rad/s).
    - `direction`: the unit vector of the motion.
    - `phase`: (rad).
    """

    amplitude: jax.Array = eqx.field(converter=base.as_float)
    angular_frequency: jax.Array = eqx.field(converter=base.as_float)
    direction: jax.Array = eqx.field(default=(0.0, 0.0, 1.0), converter=base.as_float)
    phase: jax.Array = eqx.field(default=0.0, converter=base.as_float)

    def __check_init__(self):
        base.check_sign("amplitude", self.amplitude, " (m)", strict=False, scalar=True)
        base.check_sign("angular_frequency", self.angular_frequency, " (rad/s)", strict=False,
                   scalar=True)
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
        a = self.acceleration(t).astype(q.dtype)
        m = scene.masses()
        return jax.grad(lambda q_: -jnp.sum(m * (scene.positions(q_) @ a)))(q)
