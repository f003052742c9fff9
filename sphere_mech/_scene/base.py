"""The three kinds of effect a scene is assembled from."""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp


def as_float(x) -> jax.Array:
    """`x` as a floating array (float64 when x64 is enabled)."""
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.result_type(float))


class AbstractEffect(eqx.Module):
    """Anything a scene can list. Parameters are array leaves; counts and indices are
    static."""


class AbstractKinetic(AbstractEffect):
    """A block of spheres carrying one point mass each, with a constant scalar inertia.

    Its kinetic energy is `1/2 sum_jk M_jk qdot_j . qdot_k` on its own spheres."""

    @property
    @abc.abstractmethod
    def n(self) -> int:
        """Number of spheres (= number of masses), static."""

    @abc.abstractmethod
    def inertia(self) -> jax.Array:
        """The `(n, n)` scalar inertia matrix."""

    @abc.abstractmethod
    def inverse_inertia_bands(self) -> tuple[jax.Array, jax.Array]:
        """`M^-1` is tridiagonal for every kinetic term here: its diagonal `(n,)` and
        off-diagonal `(n - 1,)` (used by the O(n) fast path)."""

    @abc.abstractmethod
    def point_masses(self) -> jax.Array:
        """The `(n,)` masses."""

    @abc.abstractmethod
    def positions(self, q: jax.Array) -> jax.Array:
        """Positions of the masses in the support frame, `(n, 3)`, from this block's `q`."""

    def parents(self) -> tuple[int, ...]:
        """For each sphere, the local index of the sphere it is jointed to (-1: the
        support). Used by joint damping and joint torques."""
        return (-1,) * self.n

    def bends(self) -> tuple[tuple[int, int], ...]:
        """Local index pairs of consecutive links (where bending stiffness acts)."""
        return ()


class AbstractPotential(AbstractEffect):
    """A conservative effect: a potential energy `U(t, q)` of the scene's configuration."""

    @abc.abstractmethod
    def potential(self, t, q, scene, args) -> jax.Array:
        """Potential energy (scalar); `scene` gives positions, masses and joints."""


class AbstractForce(AbstractEffect):
    """A non-conservative or driven effect: a generalized force `f` with virtual work
    `sum_i f_i . delta q_i`."""

    @abc.abstractmethod
    def force(self, t, q, qdot, scene, args) -> jax.Array:
        """The `(n, 3)` generalized force."""


def check_vector(name: str, x) -> None:
    if jnp.shape(x) != (3,):
        raise ValueError(f"{name} must be a (3,) vector, got shape {jnp.shape(x)}.")


def check_scalar_param(name: str, x) -> None:
    if jnp.shape(x) != ():
        raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(x)}.")
