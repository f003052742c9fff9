"""Configuration spaces: the factors `Spheres(n)` ((S^2)^n, `(n, 3)` unit vectors) and
`Euclidean(m)` (`(m,)` arrays), and `Product`, a dict of factors whose states are dicts with
its keys (DESIGN.md section 7). Every form, check and solver asks the space: each factor owns
its projection, retraction, tangent basis, angular variables and group action. A product's
tangent coordinates are its factors' concatenated in key order: `T = blockdiag(I_m, T_S)`.
"""

import abc
from collections.abc import Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import (
    check_floating,
    check_shapes,
    nonfinite,
    off_rotation,
    off_rotation_tangent,
    off_tangent,
    off_unit,
)
from ._geometry import (
    dot,
    hat,
    nearest_rotation,
    normalize,
    project,
    rotation_increment,
    rotation_matrix,
    rotation_matrix_increment,
    sphere_exp,
    tangent_basis,
    vee,
)
from ._lie import (
    AbstractLieAction,
    ProductAction,
    RotateRight,
    RotateTranslate,
    SpecialEuclidean,
    Translate,
)
from ._misc import as_python, check_bool, is_integer


class AbstractSpace(eqx.Module):
    """A configuration space `Q` and what the library needs of its tangent bundle. A
    state `(q, v)` holds a point `q` and a vector `v` tangent at it (a velocity, angular
    velocity or momentum). Subclasses: the factors `Spheres` and `Euclidean`, and their
    `Product`."""

    @abc.abstractmethod
    def check_shapes(self, q, v, v_name: str = "v", q_name: str = "q") -> None:
        """Static checks (`ValueError`): `q` and `v` have this space's structure and
        shapes and a floating dtype."""

    @abc.abstractmethod
    def problems(self, q, v, v_name: str = "v", q_name: str = "q") -> list:
        """`[(problem, message), ...]`: boolean scalars saying whether `q` is off the space
        or not finite, or `v` not finite or not tangent at `q` (within `unit_tolerance`),
        each with its message; `check_values` raises the first one found."""

    def check_values(self, q, v, v_name: str = "v", q_name: str = "q"):
        """Run-time checks (`eqx.branched_error_if`) of `problems`: `q` on the space and
        `v` tangent at it; returns the (unchanged) `(q, v)`, tied to the checks."""
        found, messages = zip(*self.problems(q, v, v_name, q_name), strict=True)
        found = jnp.stack(found)
        return eqx.branched_error_if((q, v), jnp.any(found), jnp.argmax(found), messages)

    @abc.abstractmethod
    def check_forces(self, f, q, q_name: str = "q") -> None:
        """Static check that a generalized force `f` has the structure of `q`."""

    @abc.abstractmethod
    def normalize(self, q):
        """The nearest point of the space."""

    @abc.abstractmethod
    def project(self, q, v):
        """The tangent part of `v` at `q`."""

    @abc.abstractmethod
    def to_linear(self, q, w):
        """The linear variable (`qdot`, `mu`) of an angular one (`omega`, `pi`)."""

    @abc.abstractmethod
    def from_linear(self, q, x):
        """The angular variable (`omega`, `pi`) of a linear one (`qdot`, `mu`)."""

    @abc.abstractmethod
    def from_covector(self, q, x):
        """The angular covector (`pi`, a torque) of a linear one (`mu`, a force)."""

    @abc.abstractmethod
    def to_covector(self, q, p):
        """The linear covector (`mu`) of an angular one (`pi`)."""

    @abc.abstractmethod
    def force_covector(self, q, f):
        """A generalized force as users give it (a body torque on rotations) as the linear
        covector that pairs with `qdot`."""

    @abc.abstractmethod
    def bracket(self, a, b):
        """Form 4's `pidot = bracket(dH/dpi, pi) - torque`: `a x b` on the spheres,
        `b x a` on rotations (body frame), zero on Euclidean factors."""

    @abc.abstractmethod
    def angular_terms(self, q, w, p, mixed):
        """Form 2 reads `H_ww wdot = from_covector(q, dL/dq + f) - angular_terms(...)`, with
        `p = dL/dw` and `mixed` the derivative of `dL/dw` along `(1, qdot)` in `(t, q)`."""

    @abc.abstractmethod
    def momentum_transport(self, q, mu, dH_dmu):
        """Form 3's `mudot = momentum_transport(q, mu, dH/dmu) - P(dH/dq - f)`: the term
        that keeps `mu` tangent as `q` moves."""

    @abc.abstractmethod
    def angular(self) -> "AbstractSpace":
        """This space with angular velocities (`omega`, `pi`) as its states' second part:
        itself, except on rotations (`(k, 3)` body vectors instead of `(k, 3, 3)`)."""

    @abc.abstractmethod
    def normal_acceleration(self, q, qdot):
        """`c` with `q_i . qddot_i = -|qdot_i|^2` written `qddot = (tangent) - c`:
        `|qdot_i|^2 q_i` on the spheres, zero on Euclidean factors."""

    @abc.abstractmethod
    def tangency_covector(self, q, r, v):
        """The covector `c` with `r . dv = c . dq` for every variation `(dq, dv)` that keeps
        the tangent `v` tangent, `r` normal at `q` (the constraint force): `-(q . r) v` on
        the spheres, zero on Euclidean factors."""

    @abc.abstractmethod
    def exp(self, q, v):
        """The exponential map: the geodesic from `q` with velocity `v` at unit time."""

    @abc.abstractmethod
    def exp_step(self, q, v):
        """`exp(q, v) - q`, computed without the rounding of that difference (about `eps
        |q|`, which the chord `(q1 - q0) / h` of a small step `h` would amplify)."""

    @abc.abstractmethod
    def tangent_basis(self, q):
        """An orthonormal basis of the tangent space at `q` (a pytree of arrays)."""

    @abc.abstractmethod
    def to_tangent(self, T, v) -> jax.Array:
        """The coordinates of the tangent vector `v` in the basis `T`, flat."""

    @abc.abstractmethod
    def from_tangent(self, T, a):
        """The tangent vector with flat coordinates `a` in the basis `T`."""

    @abc.abstractmethod
    def reduced_matrix(self, hvp, T) -> jax.Array:
        """`T^T H T` for a linear map `hvp` applying `H` to tangent vectors."""

    @abc.abstractmethod
    def lie_action(self, kind: str, angular: bool) -> AbstractLieAction:
        """The group action `LieRK` moves states with: `kind` is `"SE3"` or `"SO3xR3"`
        (for the spheres); `angular`, whether `v` is an angular variable."""

    @abc.abstractmethod
    def rows(self, q) -> int:
        """The number of rows (points) of a configuration: the batch chunking measure."""

    @abc.abstractmethod
    def batch_shape(self, q) -> tuple[int, ...]:
        """The leading axes of `q` before those of one point (`()` for one point, `(B,)`
        for a batch of `B`); static, from the shapes only."""

    def retract(self, q, v):
        """Put a state back on the tangent bundle: `q` normalized, `v` made tangent."""
        q = self.normalize(q)
        return q, self.project(q, v)


class AbstractFactor(AbstractSpace):
    """A factor of a configuration space: one array of the state."""

    @abc.abstractmethod
    def directions(self, T) -> jax.Array:
        """The tangent basis vectors as a stack `(dim, *shape)`."""

    @abc.abstractmethod
    def dim(self, T) -> int:
        """The dimension of the tangent space with basis `T` (static)."""


class _AbstractBlockFactor(AbstractFactor):
    """A factor of `n` blocks (spheres, rotations), each with its own tangent basis: `T`
    is `(n, *block shape, d)`, `d` directions per block, `n d` coordinates."""

    def to_tangent(self, T, v):
        return jnp.einsum("i...a,i...->ia", T, v).reshape(-1)

    def from_tangent(self, T, a):
        return jnp.einsum("i...a,ia->i...", T, a.reshape(T.shape[0], T.shape[-1]))

    def reduced_matrix(self, hvp, T):
        HT = jax.vmap(hvp)(self.directions(T))  # H applied to each basis vector
        return jax.vmap(lambda col: self.to_tangent(T, col), out_axes=1)(HT)

    def directions(self, T):
        # (n d, n, *block), each nonzero on one block: [(j, b), i, ...] = delta_ij T[j, ..., b]
        n, d = T.shape[0], T.shape[-1]
        eye = jnp.eye(n, dtype=T.dtype)
        return jnp.einsum("ij,j...b->jbi...", eye, T).reshape(n * d, n, *T.shape[1:-1])

    def dim(self, T):
        return T.shape[0] * T.shape[-1]


class Spheres(_AbstractBlockFactor):
    """The factor `(S^2)^n`: its values are `(n, 3)` arrays of unit vectors, its
    velocities `(n, 3)` arrays tangent to them (`q_i . v_i = 0`).

    The space of a system built without `space=` is `Spheres()` (any `n`: the shape of
    `q` decides), so a plain `(n, 3)` array is exactly this factor. Unit length and
    tangency are checked on the sphere factors only; the solvers retract them, `LieRK`
    rotates them and `Variational` imposes `|q_i| = 1` on them by multipliers.

    **Arguments:**
    - `n`: the number of spheres (a positive int), or `None` (default) for any number.
    """

    n: int | None = eqx.field(default=None, static=True, converter=as_python)

    def __check_init__(self):
        if self.n is not None and not (is_integer(self.n) and self.n >= 1):
            raise ValueError(f"Spheres(n): n must be a positive int, got {self.n!r}.")

    def check_shapes(self, q, v, v_name="v", q_name="q"):
        if self.n is not None and jnp.ndim(q) == 2 and jnp.shape(q)[0] != self.n:
            raise ValueError(
                f"the state has {jnp.shape(q)[0]} spheres but the system has {self.n}: "
                f"{q_name} must have shape ({self.n}, 3) (Spheres({self.n})), got {jnp.shape(q)}."
            )
        check_shapes(q, v, v_name, q_name)

    def problems(self, q, v, v_name="v", q_name="q"):
        return [
            nonfinite(q, q_name),
            off_unit(q, q_name),
            nonfinite(v, v_name),
            off_tangent(q, v, v_name),
        ]

    def check_forces(self, f, q, q_name="q"):
        if jnp.shape(f) != jnp.shape(q):
            what = "an array" if q_name == "q" else f"for {q_name} an array"
            raise ValueError(
                f"forces(t, q, v, args) must return {what} of shape {jnp.shape(q)} "
                f"(one generalized force per sphere), got {jnp.shape(f)}."
            )

    def normalize(self, q):
        return normalize(q)

    def project(self, q, v):
        return project(q, v)

    def to_linear(self, q, w):
        return jnp.cross(w, q)

    def from_linear(self, q, x):
        return jnp.cross(q, x)

    def from_covector(self, q, x):
        return jnp.cross(q, x)

    def to_covector(self, q, p):
        return jnp.cross(p, q)

    def force_covector(self, q, f):
        return f

    def bracket(self, a, b):
        return jnp.cross(a, b)

    def angular_terms(self, q, w, p, mixed):
        return project(q, mixed - 2.0 * jnp.cross(w, p))

    def momentum_transport(self, q, mu, dH_dmu):
        return jnp.cross(dH_dmu, jnp.cross(mu, q))

    def angular(self):
        return self

    def normal_acceleration(self, q, qdot):
        return dot(qdot, qdot) * q

    def tangency_covector(self, q, r, v):
        return -(dot(q, r) / dot(q, q) * v)

    def exp(self, q, v):
        return sphere_exp(q, v)

    def exp_step(self, q, v):
        return rotation_increment(jnp.cross(q, v), q)

    def tangent_basis(self, q):
        return tangent_basis(q)

    def lie_action(self, kind, angular):
        return RotateTranslate() if kind == "SO3xR3" else SpecialEuclidean(angular)

    def rows(self, q):
        return jnp.shape(q)[-2]

    def batch_shape(self, q):
        return jnp.shape(q)[:-2]


class Euclidean(AbstractFactor):
    """The factor `R^m`: its values and velocities are `(m,)` arrays (a cart's position
    on a line, `m = 1`; a point in space, `m = 3`).

    Its momentum is `dL/dxdot`, unprojected; angular and Hamiltonian forms keep `xdot`
    and `p_x` on it (only the sphere factors change variables); `LieRK` translates it;
    nothing is retracted or constrained.

    **Arguments:**
    - `m`: the dimension (a positive int).
    """

    m: int = eqx.field(static=True, converter=as_python)

    def __check_init__(self):
        if not (is_integer(self.m) and self.m >= 1):
            raise ValueError(f"Euclidean(m): m must be a positive int, got {self.m!r}.")

    def check_shapes(self, q, v, v_name="v", q_name="q"):
        for name, x in ((q_name, q), (v_name, v)):
            if jnp.shape(x) != (self.m,):
                raise ValueError(
                    f"{name} must have shape ({self.m},) (Euclidean({self.m})), got {jnp.shape(x)}."
                )
        check_floating((q_name, q), (v_name, v))

    def problems(self, q, v, v_name="v", q_name="q"):
        return [nonfinite(q, q_name), nonfinite(v, v_name)]

    def check_forces(self, f, q, q_name="q"):
        if jnp.shape(f) != jnp.shape(q):
            raise ValueError(
                f"forces(t, q, v, args) must return for {q_name} an array of "
                f"shape {jnp.shape(q)}, got {jnp.shape(f)}."
            )

    def normalize(self, q):
        return q

    def project(self, q, v):
        return v

    # A flat factor: its vectors, covectors and tangent coordinates are its arrays.
    to_linear = from_linear = from_covector = to_covector = force_covector = project
    to_tangent = from_tangent = project

    def bracket(self, a, b):
        return jnp.zeros_like(b)

    def angular_terms(self, q, w, p, mixed):
        return mixed

    def momentum_transport(self, q, mu, dH_dmu):
        return jnp.zeros_like(mu)

    def angular(self):
        return self

    def normal_acceleration(self, q, qdot):
        return jnp.zeros_like(qdot)

    def tangency_covector(self, q, r, v):
        return jnp.zeros_like(v)

    def exp(self, q, v):
        return q + v

    def exp_step(self, q, v):
        return v

    def tangent_basis(self, q):
        return jnp.eye(self.m, dtype=jnp.result_type(q))

    def reduced_matrix(self, hvp, T):
        return jax.vmap(hvp, out_axes=1)(T)

    def directions(self, T):
        return T

    def dim(self, T):
        return self.m

    def lie_action(self, kind, angular):
        return Translate()

    def rows(self, q):
        return 1

    def batch_shape(self, q):
        return jnp.shape(q)[:-1]


def _transpose(M):
    return jnp.swapaxes(M, -1, -2)


class Rotations(_AbstractBlockFactor):
    """The factor `SO(3)^k` (rigid bodies' attitudes): its values are `(k, 3, 3)` rotation
    matrices `R_j` (body to world, `x_world = R x_body`). Linear forms (1, 3) carry `Rdot`
    (`(k, 3, 3)`, `R^T Rdot` skew) and `mu = P_R(dL/dRdot)`, `P_R(A) = R skew(R^T A)`;
    angular forms (2, 4) the body angular velocity `Omega` (`(k, 3)`, `Rdot = R
    hat(Omega)`) and `Pi = dL/dOmega`. Its generalized force is a body torque `(k, 3)`
    (virtual work `tau . eta` for `delta R = R hat(eta)`), in every form. `Projected`
    retracts to the nearest rotation, `LieRK` multiplies by `expm` on the right, and
    `Variational` is the Lie group variational integrator (`R1 = R0 F`, Newton on the
    rotation vector of `F`). Its tangent basis `R hat(e_a) / sqrt(2)` is orthonormal in the
    Frobenius product its projection and covectors use.

    **Arguments:**
    - `k`: the number of rotations (a positive int), or `None` (default) for any number.
    - `body`: whether a state's second part is the body `Omega` (`(k, 3)`) rather than
      `Rdot`: the angular forms' `state_space` sets it; leave it `False`.
    """

    k: int | None = eqx.field(default=None, static=True, converter=as_python)
    body: bool = eqx.field(default=False, static=True, converter=as_python)

    def __check_init__(self):
        if self.k is not None and not (is_integer(self.k) and self.k >= 1):
            raise ValueError(f"Rotations(k): k must be a positive int, got {self.k!r}.")
        check_bool(self.body, "Rotations: body")

    def check_shapes(self, q, v, v_name="v", q_name="q"):
        k = self.k or (jnp.shape(q)[0] if jnp.ndim(q) == 3 else "k")
        if k == 0:
            message = f"{q_name} must hold at least one rotation (k >= 1)"
            raise ValueError(f"{message}, got shape {jnp.shape(q)}.")
        velocity = (k, 3) if self.body else (k, 3, 3)
        for name, x, shape in ((q_name, q, (k, 3, 3)), (v_name, v, velocity)):
            if jnp.shape(x) != shape:
                spelled = f"({', '.join(map(str, shape))})"
                raise ValueError(
                    f"{name} must have shape {spelled} (Rotations({self.k or ''})), "
                    f"got {jnp.shape(x)}."
                )
        check_floating((q_name, q), (v_name, v))

    def problems(self, q, v, v_name="v", q_name="q"):
        found = [nonfinite(q, q_name), off_rotation(q, q_name), nonfinite(v, v_name)]
        return found if self.body else [*found, off_rotation_tangent(q, v, v_name)]

    def check_forces(self, f, q, q_name="q"):
        if jnp.shape(f) != jnp.shape(q)[:-1]:
            raise ValueError(
                f"forces(t, q, v, args) must return for {q_name} an array of shape "
                f"{jnp.shape(q)[:-1]} (one body torque per rotation), got {jnp.shape(f)}."
            )

    def normalize(self, q):
        return nearest_rotation(q)

    def project(self, q, v):
        return v if self.body else q @ hat(vee(_transpose(q) @ v))

    def to_linear(self, q, w):
        return q @ hat(w)

    def from_linear(self, q, x):
        return vee(_transpose(q) @ x)

    def from_covector(self, q, x):
        return 2.0 * vee(_transpose(q) @ x)

    def to_covector(self, q, p):
        return 0.5 * q @ hat(p)

    def force_covector(self, q, f):
        return self.to_covector(q, f)

    def bracket(self, a, b):
        return jnp.cross(b, a)

    def angular_terms(self, q, w, p, mixed):
        return mixed + jnp.cross(w, p)

    def momentum_transport(self, q, mu, dH_dmu):
        omega = vee(_transpose(q) @ dH_dmu)
        return mu @ hat(omega) + self.project(q, dH_dmu @ _transpose(q) @ mu)

    def angular(self):
        return Rotations(self.k, body=True)

    def normal_acceleration(self, q, qdot):
        return -qdot @ _transpose(q) @ qdot

    def tangency_covector(self, q, r, v):
        if self.body:
            return jnp.zeros_like(q)
        M = _transpose(q) @ r
        return -v @ (0.5 * (M + _transpose(M)))

    def exp(self, q, v):
        return q @ rotation_matrix(vee(_transpose(q) @ v))

    def exp_step(self, q, v):
        return q @ rotation_matrix_increment(vee(_transpose(q) @ v))

    def tangent_basis(self, q):
        if self.body:
            return jnp.broadcast_to(jnp.eye(3, dtype=q.dtype), q.shape)
        # R hat(e_a) / sqrt(2): orthonormal in the Frobenius product (|hat(e_a)|^2 = 2).
        E = hat(jnp.eye(3, dtype=q.dtype)) / jnp.sqrt(jnp.asarray(2.0, q.dtype))
        return jnp.einsum("kij,ajl->kila", q, E)

    def lie_action(self, kind, angular):
        return RotateRight(self.body)

    def rows(self, q):
        return jnp.shape(q)[-3]

    def batch_shape(self, q):
        return jnp.shape(q)[:-3]


def _check_keys(tree, keys, name):
    if not isinstance(tree, Mapping):
        raise ValueError(
            f"{name} must be a dict with the keys of the space, {list(keys)}, "
            f"got a {type(tree).__name__}."
        )
    missing = [k for k in keys if k not in tree]
    extra = [k for k in tree if k not in keys]
    if missing or extra:
        raise ValueError(
            f"{name} must have the keys of the space, {list(keys)}: "
            f"missing {missing}, unexpected {extra}."
        )


def _factorwise(*methods: str):
    """Give a `Product` class `methods` that apply each factor's own to its entries of the
    arguments (states, vectors, bases: dicts with the factors' keys)."""

    def method(name):
        def apply(self, *trees):
            return {k: getattr(f, name)(*(t[k] for t in trees)) for k, f in self.factors.items()}

        apply.__name__, apply.__doc__ = name, getattr(AbstractSpace, name).__doc__
        return apply

    def decorate(cls):
        for name in methods:
            setattr(cls, name, method(name))
        return abc.update_abstractmethods(cls)

    return decorate


@_factorwise(
    *"normalize project to_linear from_linear from_covector to_covector force_covector "
    "bracket angular_terms momentum_transport normal_acceleration tangency_covector exp "
    "exp_step tangent_basis".split()
)
class Product(AbstractSpace):
    """The product of the factors of a dict: states are dicts with the same keys, one
    array per factor. Built by `as_space` from a system's `space=` dict."""

    factors: dict[str, AbstractFactor]

    def check_shapes(self, q, v, v_name="v", q_name="q"):
        _check_keys(q, self.factors, q_name)
        _check_keys(v, self.factors, v_name)
        for k, f in self.factors.items():
            f.check_shapes(q[k], v[k], f"{v_name}[{k!r}]", f"{q_name}[{k!r}]")

    def problems(self, q, v, v_name="v", q_name="q"):
        return [
            p
            for k, f in self.factors.items()
            for p in f.problems(q[k], v[k], f"{v_name}[{k!r}]", f"{q_name}[{k!r}]")
        ]

    def check_forces(self, f, q, q_name="q"):
        _check_keys(f, self.factors, "forces(t, q, v, args)")
        for k, factor in self.factors.items():
            factor.check_forces(f[k], q[k], f"{q_name}[{k!r}]")

    def to_tangent(self, T, v):
        return jnp.concatenate([f.to_tangent(T[k], v[k]) for k, f in self.factors.items()])

    def from_tangent(self, T, a):
        out, start = {}, 0
        for k, f in self.factors.items():
            size = f.dim(T[k])
            out[k] = f.from_tangent(T[k], a[start : start + size])
            start += size
        return out

    def reduced_matrix(self, hvp, T):
        D = {k: f.directions(T[k]) for k, f in self.factors.items()}
        columns = []
        for k in self.factors:  # H applied to the basis vectors of factor k
            dirs = {
                j: D[k] if j == k else jnp.zeros(D[k].shape[:1] + D[j].shape[1:], D[k].dtype)
                for j in self.factors
            }
            columns.append(jax.vmap(lambda d: self.to_tangent(T, hvp(d)))(dirs))
        return jnp.concatenate(columns, axis=0).T

    def angular(self):
        return Product({k: f.angular() for k, f in self.factors.items()})

    def lie_action(self, kind, angular):
        return ProductAction({k: f.lie_action(kind, angular) for k, f in self.factors.items()})

    def rows(self, q):
        return sum(f.rows(q[k]) for k, f in self.factors.items())

    def batch_shape(self, q):
        _check_keys(q, self.factors, "q")
        shapes = {f.batch_shape(q[k]) for k, f in self.factors.items()}
        if len(shapes) != 1:
            raise ValueError(
                "the arrays of a state must have the same leading (batch) axes, got "
                f"{ {k: jnp.shape(x) for k, x in q.items()} }."
            )
        return shapes.pop()


def as_space(space) -> AbstractSpace:
    """A system's `space=` argument as a space: a factor stays itself, a dict of factors
    becomes their `Product`; anything else raises `ValueError`."""
    if isinstance(space, AbstractSpace):
        return space
    if (
        isinstance(space, Mapping)
        and space
        and all(isinstance(k, str) and isinstance(f, AbstractFactor) for k, f in space.items())
    ):
        return Product(dict(sorted(space.items())))
    raise ValueError(
        "space must be a factor (sphere_mech.Spheres(n), sphere_mech.Euclidean(m), "
        "sphere_mech.Rotations(k)) or a "
        'non-empty dict of them with string keys, e.g. {"base": sm.Euclidean(3), '
        f'"cable": sm.Spheres(4)}}; got {space!r}.'
    )


BASE, _SPHERES, ATTITUDE = "base", "spheres", "attitude"  # the keys of a chain_space
"""The names of a `chain_space`'s base and attitude parts: their keys in states, and the
names scene files (`[initial]`) and run summaries give them."""


def chain_space(base: int | None, n: int | None, attitude: bool = False) -> AbstractSpace:
    """The space of spheres hanging from a pivot that may move (scenes, the fast path):
    `Spheres(n)`, or with a point-mass base moving in `R^base` the product
    `{"base": Euclidean(base), "spheres": Spheres(n)}`, and with a rigid base (`attitude`)
    also its attitude `"attitude": Rotations(1)`. Its states, velocities and forces are
    taken apart by `chain_parts` and `chain_attitude` and put together by `chain_state`:
    no other module spells its keys.

    **Arguments:**
    - `base`: the dimension `m` of the space the base moves in (1: a line, 2: a plane,
      3: space), or `None` for a fixed support.
    - `n`: the number of spheres, or `None` for any number.
    - `attitude`: whether the base is a rigid body with an attitude (`base` must be 3).

    **Returns:** `Spheres(n)`, or the `Product` of the base's `Euclidean(m)`, `Spheres(n)`
    and with `attitude` `Rotations(1)`.
    """
    if not isinstance(attitude, bool | np.bool_):
        raise ValueError(f"chain_space: attitude must be True or False, got {attitude!r}.")
    if attitude and base != 3:  # a fixed support (None) has no attitude either
        raise ValueError(f"chain_space: a rigid base moves in 3-D space, got base={base}.")
    spheres = Spheres(n)
    if base is None:
        return spheres
    factors = {BASE: Euclidean(base), _SPHERES: spheres}
    if attitude:
        factors[ATTITUDE] = Rotations(1)
    return Product(dict(sorted(factors.items())))


def chain_parts(tree):
    """`(base, spheres)`: the parts of a state, velocity or force of a `chain_space`
    (`base` is `None` without a base)."""
    return (tree[BASE], tree[_SPHERES]) if isinstance(tree, Mapping) else (None, tree)


def chain_attitude(tree):
    """The attitude part of a state, velocity or force of a `chain_space` (`(1, 3, 3)`,
    `(1, 3)` for a torque), or `None` without a rigid base."""
    return tree.get(ATTITUDE) if isinstance(tree, Mapping) else None


def chain_state(base, spheres, attitude=None):
    """The state (velocity, force) of a `chain_space` with these parts (`base` `None`:
    the spheres' array itself; `attitude` only with a rigid base)."""
    if base is None:
        return spheres
    return {BASE: base, _SPHERES: spheres} | ({} if attitude is None else {ATTITUDE: attitude})
