"""Changes of state variables (qdot <-> omega, mu <-> pi) and of forms: `angular` (form
1 -> 2, 3 -> 4) and `legendre` (form 1 -> 3, 2 -> 4)."""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from diffrax import RESULTS

from ._geometry import _check_trailing
from ._hamiltonian import AngularHamiltonian, Hamiltonian
from ._lagrangian import AngularLagrangian
from ._misc import as_python, check_bool, fill_zeros, tree_sub, tree_vdot
from ._spaces import AbstractSpace, Spheres
from ._system import AbstractHamiltonianSystem, AbstractLagrangianSystem, AbstractSystem


def _vectors_at(q, x, name: str, fn: str) -> tuple[jax.Array, jax.Array]:
    """`q` and `x` as arrays, `q` of shape `(..., 3)` and `x` of the same shape
    (`ValueError` at trace time otherwise, naming `fn` and the arguments)."""
    q, x = _check_trailing(q, (3,), "q", fn), _check_trailing(x, (3,), name, fn)
    if x.shape != q.shape:
        raise ValueError(f"{fn}: {name} must have the same shape as q, {q.shape}, got {x.shape}.")
    return q, x


def omega_from_qdot(q, qdot):
    """Angular velocities from velocities: `omega_i = q_i x qdot_i`.

    **Arguments:**
    - `q`, `qdot`: `(n, 3)` unit vectors and velocities tangent at them (or any
      `(..., 3)`, the same shape). Spheres only: a rotation's body angular velocity is
      `vee(R^T Rdot)`.

    **Returns:** the angular velocities `omega`, `(n, 3)`, tangent at `q` too."""
    q, qdot = _vectors_at(q, qdot, "qdot", "omega_from_qdot")
    return Spheres().from_linear(q, qdot)


def qdot_from_omega(q, omega):
    """Velocities from angular velocities: `qdot_i = omega_i x q_i`.

    **Arguments:**
    - `q`, `omega`: `(n, 3)` unit vectors and angular velocities tangent at them (or any
      `(..., 3)`, the same shape). Spheres only: a rotation's is `Rdot = R hat(Omega)`.

    **Returns:** the velocities `qdot`, `(n, 3)`."""
    q, omega = _vectors_at(q, omega, "omega", "qdot_from_omega")
    return Spheres().to_linear(q, omega)


def pi_from_mu(q, mu):
    """Angular momenta from momenta: `pi_i = q_i x mu_i` (as for velocities).

    **Arguments:**
    - `q`, `mu`: `(n, 3)` unit vectors and momenta tangent at them (form 3).

    **Returns:** the angular momenta `pi` (form 4), `(n, 3)`."""
    q, mu = _vectors_at(q, mu, "mu", "pi_from_mu")
    return Spheres().from_linear(q, mu)


def mu_from_pi(q, pi):
    """Momenta from angular momenta: `mu_i = pi_i x q_i`.

    **Arguments:**
    - `q`, `pi`: `(n, 3)` unit vectors and angular momenta tangent at them (form 4).

    **Returns:** the momenta `mu` (form 3), `(n, 3)`."""
    q, pi = _vectors_at(q, pi, "pi", "mu_from_pi")
    return Spheres().to_linear(q, pi)


class _Reparametrized(eqx.Module):
    """`fn(t, q, w x q, args)`: a function of `qdot` (`mu` when `momentum`) read as one of
    `omega` (`pi`); a Module, so the system's arrays stay leaves."""

    fn: Callable
    space: AbstractSpace
    momentum: bool = eqx.field(static=True)

    def __call__(self, t, q, w, args):
        space = self.space
        return self.fn(t, q, (space.to_covector if self.momentum else space.to_linear)(q, w), args)


def angular(system: AbstractSystem) -> AbstractSystem:
    """The system in angular variables: `L~(q, omega) = L(q, omega x q)`, `H~ = H(q, pi x q)`.

    **Arguments:**
    - `system`: a form-1 Lagrangian system (`Lagrangian`, `ConstantInertiaLagrangian`, a
      `Scene`, ...) or a `Hamiltonian`; one in angular variables raises `TypeError`.

    **Returns:** an `AngularLagrangian` or an `AngularHamiltonian`, forces carried over."""
    if not isinstance(system, AbstractSystem):  # a bare L or H: say what to wrap it in
        raise TypeError(
            f"angular() takes a Lagrangian or Hamiltonian system (sm.Lagrangian(L), "
            f"sm.Hamiltonian(H), a Scene, ...), got {type(system).__name__}."
        )
    if system.angular:
        raise TypeError(
            f"angular() takes a form-1 or form-3 system; {type(system).__name__} "
            "is in angular variables already."
        )
    space = system.space
    hamiltonian = isinstance(system, AbstractHamiltonianSystem)
    forces = _Reparametrized(system.forces, space, hamiltonian) if system.has_forces else None
    if isinstance(system, AbstractLagrangianSystem):
        L = _Reparametrized(system.lagrangian, space, False)
        return AngularLagrangian(L, forces, system.quadratic_in_velocity, space)
    if hamiltonian:
        return AngularHamiltonian(_Reparametrized(system.H, space, True), forces, space)
    raise TypeError(f"angular() takes a Lagrangian or Hamiltonian system, got {type(system)}.")


def _velocity(system, t, q, p, args, quadratic):
    """The inverse Legendre map, NaN where it failed (not raised: a run's result code)."""
    v, result = system.velocity_from_momentum(t, q, p, args, quadratic=quadratic)
    return jax.tree.map(lambda x: jnp.where(result == RESULTS.successful, x, jnp.nan), v)


@eqx.filter_custom_jvp
def _legendre_value(system, t, q, p, args, *, quadratic):
    """`H(t, q, p) = p . v - L(t, q, v)`, `v` the inverse Legendre map of `p`."""
    v = _velocity(system, t, q, p, args, quadratic)
    return tree_vdot(p, v) - system.lagrangian(t, q, v, args)


@_legendre_value.def_jvp
def _legendre_jvp(primals, tangents, *, quadratic):
    """Envelope theorem (`r = p - dL/dv` normal at `q`, `r . dv = c . dq` for the variations
    that keep `v` tangent, `c` the space's `tangency_covector`; `-rho_i v_i` on the spheres):
    `dH = v . dp - dL|_(v fixed) + c . dq`, `dL` also in `t`, `args` and the system's
    arrays; no derivative of the inverse Legendre map, itself differentiable."""
    system, t, q, p, args = primals
    tangents = fill_zeros(tangents, primals)
    t_system, t_t, t_q, t_p, t_args = tangents
    v = _velocity(system, t, q, p, args, quadratic)

    L_fixed_v = lambda system_, t_, q_, args_: system_.lagrangian(t_, q_, v, args_)
    L, dL = eqx.filter_jvp(L_fixed_v, (system, t, q, args), (t_system, t_t, t_q, t_args))
    r = tree_sub(p, jax.grad(lambda v_: system.lagrangian(t, q, v_, args))(v))
    dH = -fill_zeros(dL, L)  # a symbolic zero when L depends on no differentiated input
    if t_p is not None:
        dH = dH + tree_vdot(v, t_p)
    if t_q is not None:
        dH = dH + tree_vdot(system.state_space.tangency_covector(q, r, v), t_q)
    return tree_vdot(p, v) - L, dH


class _LegendreH(eqx.Module):
    """`_legendre_value` with `system` and `quadratic` fixed."""

    system: AbstractLagrangianSystem
    quadratic: bool | None = eqx.field(static=True)

    def __call__(self, t, q, p, args):
        return _legendre_value(self.system, t, q, p, args, quadratic=self.quadratic)

    def forces(self, t, q, p, args):
        """The system's forces `f(t, q, v)` as a function of the momentum."""
        v = _velocity(self.system, t, q, p, args, self.quadratic)
        return self.system.forces(t, q, v, args)


def legendre(system: AbstractSystem, *, quadratic: bool | None = None) -> AbstractSystem:
    """The Hamiltonian counterpart of a Lagrangian system, computed numerically (form 1 ->
    3, 2 -> 4). The velocity comes from `velocity_from_momentum`: O(n) and exact for
    constant inertia (chains, scenes), one linear solve for `L` quadratic in the velocity,
    else Newton (globalized by a line search). `H` is differentiated by the envelope theorem.

    **Arguments:**
    - `system`: a Lagrangian system (forms 1 and 2); anything else raises `TypeError`.
    - `quadratic`: overrides `quadratic_in_velocity` on the general path: `True` means one
      linear solve (a wrong velocity if `L` is not quadratic), `False` forces Newton,
      `None` (default) keeps the system's declaration.

    **Returns:** a `Hamiltonian` or an `AngularHamiltonian`, with the forces carried over."""
    if not isinstance(system, AbstractLagrangianSystem):
        raise TypeError(f"legendre() takes a Lagrangian system, got {type(system)}.")
    if quadratic is not None:
        check_bool(quadratic, "legendre: quadratic")
    H = _LegendreH(system, as_python(quadratic))
    forces = H.forces if system.has_forces else None
    return (AngularHamiltonian if system.angular else Hamiltonian)(H, forces, system.space)
