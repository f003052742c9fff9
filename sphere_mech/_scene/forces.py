"""Non-conservative and driven effects, as generalized forces derived from virtual work
(`delta W = sum_i f_i . delta q_i`)."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from .base import AbstractForce, as_float, check_scalar_param, check_vector


def _relative_omega(q, qdot, scene):
    """`omega_i - omega_parent(i)` for every joint (`omega_i = q_i x qdot_i`)."""
    omega = jnp.cross(q, qdot)
    padded = jnp.concatenate([jnp.zeros_like(omega[:1]), omega])
    return omega - padded[scene.parents() + 1]


def _drive(value, t, q, qdot, args, dtype):
    out = value(t, q, qdot, args) if callable(value) else value
    out = jnp.asarray(out, dtype=dtype)
    if out.shape != (3,):
        raise ValueError(f"a torque or force function must return a (3,) vector, got "
                         f"shape {out.shape}.")
    return out


class JointDamping(AbstractForce):
    """Viscous damping in every joint (between a link and its parent, or the support):
    Rayleigh function `R = c/2 sum_i |omega_i - omega_parent(i)|^2`, `f = -dR/dqdot`.
    Its power is `-2R <= 0`."""

    coefficient: jax.Array = eqx.field(converter=as_float)

    def __check_init__(self):
        if jnp.ndim(self.coefficient) > 1:
            raise ValueError("coefficient must be a scalar or one value per sphere.")

    def dissipation(self, q, qdot, scene):
        w = _relative_omega(q, qdot, scene)
        return 0.5 * jnp.sum(self.coefficient * jnp.sum(w * w, axis=-1))

    def force(self, t, q, qdot, scene, args):
        return -jax.grad(lambda v: self.dissipation(q, v, scene))(qdot)


class BaseTorque(AbstractForce):
    """A torque `tau` applied in the joint of link `link` (default 0: the base joint of
    the first link) by its parent (or the support) on it: `f_link = tau x q_link`, and
    `-tau x q_parent` on the parent.

    `torque`: a constant `(3,)` vector or a function `torque(t, q, qdot, args) -> (3,)`
    (a controller; an equinox Module such as `PDTorque` keeps its gains as leaves)."""

    torque: jax.Array | Callable
    link: int = eqx.field(default=0, static=True)

    def __check_init__(self):
        if not callable(self.torque):
            check_vector("torque", self.torque)

    def force(self, t, q, qdot, scene, args):
        tau = _drive(self.torque, t, q, qdot, args, q.dtype)
        link = self.link % q.shape[0]
        f = jnp.zeros_like(q).at[link].add(jnp.cross(tau, q[link]))
        parent = int(scene.parents()[link])
        if parent >= 0:
            f = f.at[parent].add(-jnp.cross(tau, q[parent]))
        return f


class PDTorque(eqx.Module):
    """A proportional-derivative controller for `BaseTorque`, steering link `link`
    toward the unit vector `target`: `tau = kp q_link x target - kd omega_link`.

    Its generalized force is `kp P target - kd qdot_link` (P the tangent projection)."""

    kp: jax.Array = eqx.field(converter=as_float)
    kd: jax.Array = eqx.field(converter=as_float)
    target: jax.Array = eqx.field(default=(0.0, 0.0, 1.0), converter=as_float)
    link: int = eqx.field(default=0, static=True)

    def __check_init__(self):
        check_scalar_param("kp", self.kp)
        check_scalar_param("kd", self.kd)
        check_vector("target", self.target)

    def __call__(self, t, q, qdot, args):
        x, v = q[self.link], qdot[self.link]
        return self.kp * jnp.cross(x, self.target) - self.kd * jnp.cross(x, v)


class TipForce(AbstractForce):
    """A force `d` on one mass (default the last one: the tip of a chain):
    `f = d/dq (d . x_point(q))` with `d` held fixed.

    `force`: a constant `(3,)` vector or a function `force(t, q, qdot, args) -> (3,)`."""

    force_value: jax.Array | Callable
    point: int = eqx.field(default=-1, static=True)

    def __init__(self, force, point: int = -1):
        self.force_value = force if callable(force) else as_float(force)
        self.point = int(point)

    def __check_init__(self):
        if not callable(self.force_value):
            check_vector("force", self.force_value)

    def force(self, t, q, qdot, scene, args):
        d = _drive(self.force_value, t, q, qdot, args, q.dtype)
        return jax.grad(lambda q_: jnp.dot(d, scene.positions(q_)[self.point]))(q)


class VibratingSupport(AbstractForce):
    """A prescribed motion of the support (every chain base and sphere centre),
    `s(t) = amplitude cos(angular_frequency t + phase) direction`; the Kapitza pendulum.

    The equations are written in the support frame, where each mass feels the inertial
    force `-m_i s''(t)`: `f = d/dq sum_i (-m_i s''(t)) . x_i(q)`. (Equivalently the
    time-dependent potential `sum_i m_i s''(t) . x_i`; kept as a force so that the
    energy `E` of the relative motion and the work-energy balance use `power`.)

    For a single pendulum of length `l` the inverted position is stable when
    `amplitude^2 angular_frequency^2 > 2 g l` (vertical vibration)."""

    amplitude: jax.Array = eqx.field(converter=as_float)
    angular_frequency: jax.Array = eqx.field(converter=as_float)
    direction: jax.Array = eqx.field(default=(0.0, 0.0, 1.0), converter=as_float)
    phase: jax.Array = eqx.field(default=0.0, converter=as_float)

    def __check_init__(self):
        for name in ("amplitude", "angular_frequency", "phase"):
            check_scalar_param(name, getattr(self, name))
        check_vector("direction", self.direction)

    def acceleration(self, t):
        """`s''(t)`, the acceleration of the support."""
        w = self.angular_frequency
        return -self.amplitude * w**2 * jnp.cos(w * t + self.phase) * self.direction

    def force(self, t, q, qdot, scene, args):
        a = self.acceleration(t).astype(q.dtype)
        m = scene.masses()
        return jax.grad(lambda q_: -jnp.sum(m * (scene.positions(q_) @ a)))(q)
