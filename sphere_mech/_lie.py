"""The group actions on the tangent bundle that `LieRK` integrates with: a state `y = (q, v)`
moves by `exp(u) . y`, `u` in the Lie algebra (pairs of arrays, like states).
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp

from ._geometry import dexpinv_so3, hat, left_jacobian, project, rotate, rotation_matrix, vee


class AbstractLieAction(eqx.Module):
    """A Lie group acting on `T(S^2)^n`, one copy per sphere."""

    @abc.abstractmethod
    def algebra(self, y, dy):
        """The algebra element `u` whose infinitesimal action at `y` is `dy`
        (`d/ds exp(s u) . y = dy` at `s = 0`): how RKMK reads a stage's rates."""

    @abc.abstractmethod
    def act(self, u, y):
        """`exp(u) . y`: the state `y` moved by the group element `exp(u)`, exactly (the
        points stay on their manifold to rounding)."""

    @abc.abstractmethod
    def dexpinv(self, u, k):
        """`dexp_u^{-1}(k)` (with `ad_u = [u, .]`, the matrix commutator): the derivative of
        a stage's `u` from the algebra element `k` of its rates."""

    @abc.abstractmethod
    def finish(self, y):
        """The state a step returns from `exp(u) . y0`: `y`, or `y` put back on the tangent
        bundle where the action moves velocities off it."""


class RotateTranslate(AbstractLieAction):
    """`SO(3)^n x R^(3n)`: `exp(w, a) . (q, v) = (exp(hat(w_i)) q_i, v_i + a_i)`.

    `q_i` stays on its sphere to rounding; `v` leaves the tangent planes by the local
    error and `finish` removes its normal part. The algebra element of `(dq, dv)` is
    `(q_i x dq_i, dv_i)`, so any of the four forms works unchanged."""

    def algebra(self, y, dy):
        q, _ = y
        dq, dv = dy
        return jnp.cross(q, dq), dv

    def act(self, u, y):
        w, a = u
        q, v = y
        return rotate(w, q), v + a

    def dexpinv(self, u, k):
        # Only so(3) has brackets; R^(3n) is abelian.
        return dexpinv_so3(u[0], k[0]), k[1]

    def finish(self, y):
        q, v = y
        return q, project(q, v)


class SpecialEuclidean(AbstractLieAction):
    """`SE(3)^n` acting on `T S^2` by `(A, b) . (q, w) = (A q, A w + b x A q)` on the
    angular form `(q, omega)` (Celledoni, Cokaj, Leone, Murari, Owren 2022): it keeps
    `|q_i| = 1` and `q_i . w_i = 0` to rounding, with nothing to finish.

    The algebra element of `(dq, domega)` at `(q, omega)` is `xi_i = q_i x dq_i`,
    `eta_i = q_i x (domega_i - xi_i x omega_i)` (for the system's own rates `xi_i =
    omega_i` and `eta_i = q_i x domega_i`, the paper's map). States in a linear variable
    (`qdot`, `mu`; `angular=False`) are converted: `omega_i = q_i x v_i`, and back
    `v_i = omega_i x q_i`, so the same group moves the same curves."""

    angular: bool = eqx.field(static=True)

    def _omega(self, q, v):
        return v if self.angular else jnp.cross(q, v)

    def algebra(self, y, dy):
        q, v = y
        dq, dv = dy
        omega = self._omega(q, v)
        domega = dv if self.angular else jnp.cross(dq, v) + jnp.cross(q, dv)
        xi = jnp.cross(q, dq)
        return xi, jnp.cross(q, domega - jnp.cross(xi, omega))

    def act(self, u, y):
        xi, eta = u
        q, v = y
        q1 = rotate(xi, q)
        b_x_q1 = jnp.cross(left_jacobian(xi, eta), q1)
        # Linear v = omega x q moves to (A omega + b x A q) x A q = A v + (b x A q) x A q:
        # the same as converting, without rescaling v by |q|^2 at every step.
        return q1, rotate(xi, v) + (b_x_q1 if self.angular else jnp.cross(b_x_q1, q1))

    def dexpinv(self, u, k):
        # ad_(xi, eta) = [[hat(xi), 0], [hat(eta), hat(xi)]] on (a, b), so
        # g(ad) (a, b) = (g(xi) a, g(xi) b + D_xi[g(xi) a](eta)) for g = dexpinv_so3.
        xi, eta = u
        a, b = k
        first, derivative = jax.jvp(lambda x: dexpinv_so3(x, a), (xi,), (eta,))
        return first, dexpinv_so3(xi, b) + derivative

    def finish(self, y):
        return y


class Translate(AbstractLieAction):
    """`R^m x R^m` acting on the tangent bundle of a Euclidean factor by translation:
    `exp(a, b) . (x, v) = (x + a, v + b)`; abelian, nothing to finish."""

    def algebra(self, y, dy):
        return dy

    def act(self, u, y):
        return y[0] + u[0], y[1] + u[1]

    def dexpinv(self, u, k):
        return k

    def finish(self, y):
        return y


class RotateRight(AbstractLieAction):
    """`SO(3)^k x R^d` acting on the states of `Rotations(k)` by body-frame rotation and
    translation: `exp(w, a) . (R, v) = (R_j expm(hat(w_j)), v + a)`. `R` stays a rotation
    to rounding; a body `Omega` (`body=True`) needs nothing more, a linear `Rdot` is made
    tangent by `finish`. The algebra element of `(dR, dv)` is `(vee(R^T dR), dv)`; as the
    group acts on the right, `dexpinv` is so(3)'s at `-w`."""

    body: bool = eqx.field(static=True)

    def algebra(self, y, dy):
        R, _ = y
        dR, dv = dy
        return vee(jnp.swapaxes(R, -1, -2) @ dR), dv

    def act(self, u, y):
        w, a = u
        R, v = y
        return R @ rotation_matrix(w), v + a

    def dexpinv(self, u, k):
        return dexpinv_so3(-u[0], k[0]), k[1]

    def finish(self, y):
        R, v = y
        return y if self.body else (R, R @ hat(vee(jnp.swapaxes(R, -1, -2) @ v)))


def _split(pair, keys):
    """A pair of dicts `(a, b)` as a dict of pairs."""
    return {k: (pair[0][k], pair[1][k]) for k in keys}


def _join(pairs):
    """A dict of pairs as a pair of dicts."""
    return {k: p[0] for k, p in pairs.items()}, {k: p[1] for k, p in pairs.items()}


class ProductAction(AbstractLieAction):
    """The product of one action per factor of a mixed space (states and algebra
    elements are pairs of dicts with the factors' keys): each factor's action moves its
    own part of the state (`Translate` on Euclidean factors, a rotation on spheres)."""

    actions: dict[str, AbstractLieAction]

    def algebra(self, y, dy):
        y, dy = _split(y, self.actions), _split(dy, self.actions)
        return _join({k: a.algebra(y[k], dy[k]) for k, a in self.actions.items()})

    def act(self, u, y):
        u, y = _split(u, self.actions), _split(y, self.actions)
        return _join({k: a.act(u[k], y[k]) for k, a in self.actions.items()})

    def dexpinv(self, u, k):
        u, k = _split(u, self.actions), _split(k, self.actions)
        return _join({key: a.dexpinv(u[key], k[key]) for key, a in self.actions.items()})

    def finish(self, y):
        y = _split(y, self.actions)
        return _join({k: a.finish(y[k]) for k, a in self.actions.items()})
