"""Rotorcraft: four rotors on a `RigidBase` and the geometric tracking controller on SE(3)
of Lee, Leok and McClamroch (2010) that drives them, with the commands it tracks."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._geometry import hat, vee
from .._linalg import dense_solve
from .._spaces import chain_attitude, chain_parts
from . import base
from .base import AbstractCommand, AbstractDrive, AbstractForce, ParameterError
from .forces import _check_drive, _evaluate, _not_a_command
from .kinetic import check_rigid_inertia, inertia_matrix

E3 = (0.0, 0.0, 1.0)


def mixing_matrix(arm: jax.Array, torque_coefficient: jax.Array) -> jax.Array:
    """The mixing of four rotors in the `+` layout: rotor `i` at `d (cos, sin)((i - 1) pi/2)`
    in the body's `e1 e2` plane pushing along `+e3` with the yaw reaction `+-c f_i` (`+`
    for rotors 1 and 3): `M1 = d (f2 - f4)`, `M2 = d (f3 - f1)`, `M3 = c (f1 - f2 + f3 -
    f4)`.

    **Arguments:**
    - `arm`: `d` (m).
    - `torque_coefficient`: `c` (m).

    **Returns:** `A`, `(4, 4)`, with `(f, M1, M2, M3) = A (f_1, ..., f_4)`."""
    d, c, zero, one = arm, torque_coefficient, jnp.zeros_like(arm), jnp.ones_like(arm)
    return jnp.stack(
        [
            jnp.stack([one, one, one, one]),
            jnp.stack([zero, d, zero, -d]),
            jnp.stack([-d, zero, d, zero]),
            jnp.stack([c, -c, c, -c]),
        ]
    )


class Rotors(AbstractForce):
    """Four rotors on the scene's `RigidBase` in the `+` layout (`mixing_matrix`): the
    commanded total thrust `f` and body moments `M` are allocated to the four rotors (with
    the flight controller's model of the rotors, by default the rotors themselves), each
    thrust saturated to `[min_thrust, max_thrust]`, and the rotors' own mixing gives what
    the body feels: the thrust `f R e3` at its centre of mass (`e3` the body axis, up) and
    the moment `M`.

    **Arguments:**
    - `command`: `(f, M1, M2, M3)` (N, N m): a constant `(4,)` vector or a function
      `command(t, q, qdot, args) -> (4,)` of the scene's state, such as
      `GeometricControl` (a flight command, such as `Hover`, is refused: it is what
      `GeometricControl` flies).
    - `arm`: the distance `d` of each rotor from the centre of mass (m, `> 0`).
    - `torque_coefficient`: `c`, the yaw moment per unit thrust (m, `> 0`).
    - `min_thrust`, `max_thrust`: each rotor's bounds (N; default 0 and no upper bound;
      `None`: unbounded, as in the controller's published analysis).
    - `model_arm`, `model_torque_coefficient`: the rotors as the allocation knows them
      (default: `arm` and `torque_coefficient`, an exact allocation); a different value
      is a model error, such as one a fit recovers.
    """

    command: jax.Array | Callable
    arm: jax.Array
    torque_coefficient: jax.Array
    min_thrust: jax.Array | None
    max_thrust: jax.Array | None
    model_arm: jax.Array | None
    model_torque_coefficient: jax.Array | None

    def __init__(
        self,
        command,
        arm,
        torque_coefficient,
        min_thrust=0.0,
        max_thrust=None,
        model_arm=None,
        model_torque_coefficient=None,
    ):
        _not_a_command("command", command)
        if not callable(command):
            command = base.as_float(command, "command")
            base.check_shape("command", command, (4,), "a (4,) vector (f, M1, M2, M3)")
            base.check_magnitude("command", command)
        self.command = command
        self.arm = base.as_float(arm, "arm")
        self.torque_coefficient = base.as_float(torque_coefficient, "torque_coefficient")
        optional = dict(
            min_thrust=min_thrust,
            max_thrust=max_thrust,
            model_arm=model_arm,
            model_torque_coefficient=model_torque_coefficient,
        )
        self.min_thrust, self.max_thrust, self.model_arm, self.model_torque_coefficient = (
            None if x is None else base.as_float(x, name) for name, x in optional.items()
        )

    def __check_init__(self):
        base.check_sign("arm", self.arm, " (m)", scalar=True)
        base.check_sign("torque_coefficient", self.torque_coefficient, " (m)", scalar=True)
        for name, x in (
            ("model_arm", self.model_arm),
            ("model_torque_coefficient", self.model_torque_coefficient),
        ):
            if x is not None:
                base.check_sign(name, x, " (m)", scalar=True)
        for name in ("min_thrust", "max_thrust"):
            if getattr(self, name) is not None:
                base.check_shape(name, getattr(self, name), (), "a scalar")
                base.check_magnitude(name, getattr(self, name))
        low, high = self.min_thrust, self.max_thrust
        if low is not None and high is not None and base._concrete(high) and not high > low:
            message = f"max_thrust must be > min_thrust ({float(low):g} N)"
            raise ParameterError("max_thrust", f"{message}, got {float(high):g}")

    def check(self, scene):
        if scene.rigid_body is None:
            raise ParameterError("", "Rotors needs a RigidBase in the scene")
        _check_drive("command", self.command, scene, (4,))

    def thrusts(self, wrench: jax.Array) -> jax.Array:
        """The four rotor thrusts the allocation gives `(f, M)`, saturated.

        **Arguments:**
        - `wrench`: `(f, M1, M2, M3)`, `(4,)` (N, N m).

        **Returns:** `(4,)` thrusts (N)."""
        arm = self.arm if self.model_arm is None else self.model_arm
        c = self.torque_coefficient
        c = c if self.model_torque_coefficient is None else self.model_torque_coefficient
        f = dense_solve(mixing_matrix(arm, c).astype(wrench.dtype), wrench)
        f = f if self.min_thrust is None else jnp.maximum(f, self.min_thrust.astype(f.dtype))
        return f if self.max_thrust is None else jnp.minimum(f, self.max_thrust.astype(f.dtype))

    def generalized_force(self, t, q, qdot, scene, args):
        wrench = _evaluate(self.command, t, q, qdot, args, (4,))
        A = mixing_matrix(self.arm, self.torque_coefficient).astype(wrench.dtype)
        f, M = jnp.split(A @ self.thrusts(wrench), [1])
        R = chain_attitude(q)[0]
        return scene.on_base(q, f[0] * R[:, 2], M)


def _check_heading(heading) -> None:
    """A command's heading: a unit `(3,)` vector, not vertical (unless traced): parallel to
    the thrust of level flight, it leaves the commanded attitude undefined (`b3 x b1_d = 0`)."""
    base.check_vector("heading", heading, unit=True)
    if base._concrete(heading) and abs(float(heading[2])) >= 1 - 1e-6:
        message = "heading must not be vertical (the body e1 wanted, across the thrust)"
        raise ParameterError("heading", f"{message}, got {base._show(heading)}")


class Hover(AbstractCommand):
    """Hold `position` (after `step_time`, `position + step`: a step command), heading
    `heading`.

    **Arguments:**
    - `position`, `step`: `(3,)` points (m).
    - `step_time`: when the step happens (s).
    - `heading`: the desired body `e1`, a unit `(3,)` vector (default `e1`).
    """

    position: jax.Array = eqx.field(default=(0.0, 0.0, 0.0), converter=base.number("position"))
    heading: jax.Array = eqx.field(default=(1.0, 0.0, 0.0), converter=base.number("heading"))
    step: jax.Array = eqx.field(default=(0.0, 0.0, 0.0), converter=base.number("step"))
    step_time: jax.Array = eqx.field(default=0.0, converter=base.number("step_time"))

    def __check_init__(self):
        base.check_vector("position", self.position)
        _check_heading(self.heading)
        base.check_vector("step", self.step)
        base.check_shape("step_time", self.step_time, (), "a scalar")

    def __call__(self, t):
        x = self.position + jnp.where(t >= self.step_time, 1.0, 0.0) * self.step
        return x + 0.0 * t, self.heading


class Line(AbstractCommand):
    """Fly from `start` at constant `velocity`, heading along `heading`.

    **Arguments:**
    - `start`, `velocity`: `(3,)` (m, m/s).
    - `heading`: the desired body `e1`, a unit `(3,)` vector (default `e1`).
    """

    start: jax.Array = eqx.field(converter=base.number("start"))
    velocity: jax.Array = eqx.field(converter=base.number("velocity"))
    heading: jax.Array = eqx.field(default=(1.0, 0.0, 0.0), converter=base.number("heading"))

    def __check_init__(self):
        base.check_vector("start", self.start)
        base.check_vector("velocity", self.velocity)
        _check_heading(self.heading)

    def __call__(self, t):
        return self.start + t * self.velocity, self.heading


class Circle(AbstractCommand):
    """Fly the horizontal circle `center + radius (cos(w t + phase), sin(w t + phase), 0)`,
    heading along `heading`.

    **Arguments:**
    - `center`: `(3,)` (m).
    - `radius`: (m, `> 0`).
    - `angular_frequency`: `w` (rad/s).
    - `phase`: (rad).
    - `heading`: the desired body `e1`, a unit `(3,)` vector (default `e1`).
    """

    center: jax.Array = eqx.field(converter=base.number("center"))
    radius: jax.Array = eqx.field(converter=base.number("radius"))
    angular_frequency: jax.Array = eqx.field(converter=base.number("angular_frequency"))
    phase: jax.Array = eqx.field(default=0.0, converter=base.number("phase"))
    heading: jax.Array = eqx.field(default=(1.0, 0.0, 0.0), converter=base.number("heading"))

    def __check_init__(self):
        base.check_vector("center", self.center)
        base.check_sign("radius", self.radius, " (m)", scalar=True)
        base.check_shape("angular_frequency", self.angular_frequency, (), "a scalar")
        base.check_shape("phase", self.phase, (), "a scalar")
        _check_heading(self.heading)

    def __call__(self, t):
        angle = self.angular_frequency * t + self.phase
        offset = jnp.stack([jnp.cos(angle), jnp.sin(angle), jnp.zeros_like(angle)])
        return self.center + self.radius * offset, self.heading


def _derivatives(f, t, order: int):
    """`f(t), f'(t), ..., f^(order)(t)` by nested forward-mode autodiff."""
    if order == 0:
        return (f(t),)
    inner = lambda s: _derivatives(f, s, order - 1)
    values, tangents = jax.jvp(inner, (t,), (jnp.ones_like(t),))
    return (*values, tangents[-1])


def _unit(x):
    return x / jnp.linalg.norm(x)


_COMMAND = (
    "command must be an AbstractCommand (Hover, Line, Circle) or a function"
    " command(t) -> (x_d, b1_d), two (3,) vectors"
)


_STATE_SHAPES = dict(t=(), x=(3,), v=(3,), R=(3, 3), Omega=(3,))


def _check_state(method: str, **state) -> None:
    """Static check of `GeometricControl.<method>`'s state arguments' shapes."""
    for name, a in state.items():
        if np.shape(a) != _STATE_SHAPES[name]:
            message = f"GeometricControl.{method}: {name} must have shape {_STATE_SHAPES[name]}"
            raise ValueError(f"{message}, got {np.shape(a)}.")


class GeometricControl(AbstractDrive):
    """The geometric tracking controller on SE(3) of Lee, Leok and McClamroch (2010), for
    `Rotors` (`(f, M)`), in a frame whose `e3` points up (thrust `f R e3`, gravity `-g e3`):

    `F = -kx e_x - kv e_v + m g e3 + m xddot_d`, `f = F . R e3`; the command attitude
    `R_c = [b2 x b3, b2, b3]`, `b3 = F / |F|`, `b2 = b3 x b1_d / |b3 x b1_d|`;
    `e_R = vee(R_c^T R - R^T R_c) / 2`, `e_Omega = Omega - R^T R_c Omega_c`;
    `M = -kR e_R - kOmega e_Omega + Omega x J Omega - J (hat(Omega) R^T R_c Omega_c -
    R^T R_c Omegadot_c)`. `Omega_c` and `Omegadot_c` are the first and second time
    derivatives of `R_c`, taken by autodiff along the controller's model of the flight
    (the rigid body alone: `xddot = -g e3 + f R e3 / m`, `Rdot = R hat(Omega)`), and the
    command's derivatives too: nothing is differentiated by hand.
    Where `F` is zero (hovering at the target with `g = 0`) its direction is free and
    `b3` is the body's own `R e3`.

    **Arguments:**
    - `mass`, `inertia`: the controller's model of the vehicle (kg; `(3,)` or `(3, 3)`
      kg m^2), e.g. the body plus the payload it carries as `mass`.
    - `kx`, `kv`, `kR`, `kOmega`: the gains (`> 0`).
    - `command`: an `AbstractCommand` (`Hover`, `Line`, `Circle`) or any function
      `command(t) -> (x_d, b1_d)`.
    - `g`: gravity (m/s^2, default 9.81).
    """

    mass: jax.Array = eqx.field(converter=base.number("mass"))
    inertia: jax.Array = eqx.field(converter=inertia_matrix)
    kx: jax.Array = eqx.field(converter=base.number("kx"))
    kv: jax.Array = eqx.field(converter=base.number("kv"))
    kR: jax.Array = eqx.field(converter=base.number("kR"))
    kOmega: jax.Array = eqx.field(converter=base.number("kOmega"))
    command: AbstractCommand | Callable = Hover()
    g: jax.Array = eqx.field(default=9.81, converter=base.number("g"))

    def __check_init__(self):
        base.check_sign("mass", self.mass, " (kg)", scalar=True)
        check_rigid_inertia(self.inertia)
        if isinstance(self.command, AbstractDrive):
            what = type(self.command).__name__
            raise ParameterError("command", f"{_COMMAND}, not a drive, got a {what}")
        if not callable(self.command):
            raise ParameterError("command", f"{_COMMAND}, got {self.command!r}")
        for name in ("kx", "kv", "kR", "kOmega"):
            base.check_sign(name, getattr(self, name), "", scalar=True)
        base.check_sign("g", self.g, " (m/s^2)", strict=False, scalar=True)

    def check(self, scene):
        if scene.rigid_body is None:
            raise ParameterError("", "GeometricControl needs a RigidBase in the scene")
        out = jax.eval_shape(self.command, jax.ShapeDtypeStruct((), jnp.result_type(float)))
        shapes = [x.shape for x in jax.tree.leaves(out)]  # ShapeDtypeStructs
        if not isinstance(out, tuple | list) or shapes != [(3,), (3,)]:
            raise ParameterError("command", f"{_COMMAND}; it returns shapes {shapes}")

    def thrust_vector(self, t, x, v):
        """The force the thrust should give and the heading the command asks for (in
        `x`'s floating type, whatever the command's and the gains' own).

        **Arguments:**
        - `t`, `x`, `v`: time, the centre of mass and its velocity `(3,)`.

        **Returns:** `(F, b1_d)`, `(3,)` each (world axes)."""
        _check_state("thrust_vector", t=t, x=x, v=v)
        x, v = jnp.asarray(x), jnp.asarray(v)
        dtype = jnp.result_type(x, v)
        dtype = dtype if jnp.issubdtype(dtype, jnp.floating) else jnp.result_type(float)
        x, v = x.astype(dtype), v.astype(dtype)
        command = lambda s: tuple(jnp.asarray(y).astype(dtype) for y in self.command(s))
        t = jnp.asarray(t).astype(dtype)
        (x_d, b1_d), (v_d, _), (a_d, _) = _derivatives(command, t, 2)
        kx, kv, m, g = (a.astype(dtype) for a in (self.kx, self.kv, self.mass, self.g))
        F = -kx * (x - x_d) - kv * (v - v_d) + m * (g * jnp.asarray(E3, dtype) + a_d)
        return F, b1_d

    def command_attitude(self, t, x, v, R):
        """The command attitude `R_c = [b2 x b3, b2, b3]`, `b3 = F / |F|`; where the
        thrust vector `F` is zero (hovering with `g = 0`) the thrust's direction is free
        and `b3` is the body's own `R e3`.

        **Arguments:**
        - `t`, `x`, `v`: time, the centre of mass and its velocity `(3,)`.
        - `R`: the attitude `(3, 3)` (body to world).

        **Returns:** `R_c`, `(3, 3)`."""
        _check_state("command_attitude", t=t, x=x, v=v, R=R)
        F, b1_d = self.thrust_vector(t, x, v)
        b3 = _unit(jnp.where(jnp.any(F != 0), F, R[:, 2]))
        b2 = _unit(jnp.cross(b3, b1_d))
        return jnp.stack([jnp.cross(b2, b3), b2, b3], axis=-1)

    def __call__(self, t, q, qdot, args):
        x, v = chain_parts(q)[0], chain_parts(qdot)[0]
        R, Rdot = chain_attitude(q)[0], chain_attitude(qdot)[0]
        return self.wrench(t, x, v, R, vee(R.T @ Rdot))

    def wrench(self, t, x, v, R, Omega):
        """The commanded thrust and moments of a vehicle in this state (the drive a scene's
        `Rotors` evaluate, for a vehicle modelled outside a scene too).

        **Arguments:**
        - `t`: time.
        - `x`, `v`: the centre of mass and its velocity `(3,)` (world axes).
        - `R`, `Omega`: the attitude `(3, 3)` (body to world) and the body angular
          velocity `(3,)`.

        **Returns:** `(f, M1, M2, M3)`, `(4,)` (N, N m), in the floating type of the state."""
        _check_state("wrench", t=t, x=x, v=v, R=R, Omega=Omega)
        t, x, v, R, Omega = (jnp.asarray(a) for a in (t, x, v, R, Omega))
        dtype = jnp.result_type(x, v, R, Omega)
        dtype = dtype if jnp.issubdtype(dtype, jnp.floating) else jnp.result_type(float)
        t, x, v, R, Omega = (a.astype(dtype) for a in (t, x, v, R, Omega))
        m, J = self.mass.astype(dtype), self.inertia.astype(dtype)
        kR, kOmega, g = (a.astype(dtype) for a in (self.kR, self.kOmega, self.g))

        def flow(z):  # the controller's model: (t, x, v, R) move as the body alone would
            t_, x_, v_, R_ = z
            F, _ = self.thrust_vector(t_, x_, v_)
            e3 = R_[:, 2]
            a = (F @ e3) * e3 / m - g * jnp.asarray(E3, dtype)
            return jnp.ones_like(t_), v_, a, R_ @ hat(Omega)

        Rc = lambda z: self.command_attitude(*z)
        with_rate = lambda z: jax.jvp(Rc, (z,), (flow(z),))  # (R_c, its rate along the flow)
        z = (t, x, v, R)
        (R_c, Rc_d), (_, Rc_dd) = jax.jvp(with_rate, (z,), (flow(z),))
        Omega_c, Omegadot_c = vee(R_c.T @ Rc_d), vee(R_c.T @ Rc_dd)
        F, _ = self.thrust_vector(t, x, v)
        e_R = 0.5 * vee(R_c.T @ R - R.T @ R_c)
        e_Omega = Omega - R.T @ R_c @ Omega_c
        M = (
            -kR * e_R
            - kOmega * e_Omega
            + jnp.cross(Omega, J @ Omega)
            - J @ (hat(Omega) @ R.T @ R_c @ Omega_c - R.T @ R_c @ Omegadot_c)
        )
        return jnp.concatenate([(F @ R[:, 2])[None], M])
