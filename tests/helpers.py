"""Shared test helpers."""

import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np


def tree_allclose(x, y, *, rtol=1e-5, atol=1e-8):
    """Whether two PyTrees have the same structure and allclose leaves."""
    if jtu.tree_structure(x) != jtu.tree_structure(y):
        return False
    return all(
        jnp.shape(a) == jnp.shape(b) and bool(jnp.allclose(a, b, rtol=rtol, atol=atol))
        for a, b in zip(jtu.tree_leaves(x), jtu.tree_leaves(y), strict=True)
    )


def max_rel_error(x, y):
    """`max |x - y| / max |y|` (relative error in the max norm)."""
    x, y = np.asarray(x), np.asarray(y)
    return float(np.max(np.abs(x - y)) / max(np.max(np.abs(y)), 1e-300))


def fitted_order(step_sizes, errors):
    """Slope of log(error) against log(step size): the measured order of convergence."""
    return float(np.polyfit(np.log(step_sizes), np.log(errors), 1)[0])


def jaxpr_equations(jaxpr):
    """All equations of a jaxpr, including those of nested jaxprs (pjit, custom_jvp...)."""
    for eqn in jaxpr.eqns:
        yield eqn
        for param in eqn.params.values():
            for sub in param if isinstance(param, list | tuple) else [param]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    yield from jaxpr_equations(inner)


def form_outputs(systems, variables, t, q, qdot, qddot, p):
    """For each form in `systems` (keys as in `variables`, the state variable of each at
    the same physical state): its rates (qdot, dv/dt) through the checked public entry
    points, its energy, dE/dt along the rates (jvp) and the power of its own forces.
    Plain `(n, 3)` arrays or dicts of them (mixed spaces)."""
    import jax

    out = {}
    for name, system in systems.items():
        v = variables[name]
        if name == "lag":
            rates = (qdot, qddot)
        elif name == "ang":
            rates = (system.to_linear(q, v), system.angular_acceleration(t, q, v, p))
        else:
            rates = system.vector_field(t, q, v, p)
        energy_fn = lambda t_, q_, v_, system=system: system.energy(t_, q_, v_, p)
        energy, dE = jax.jvp(energy_fn, (t, q, v), (jnp.ones_like(t), *rates))
        f = system.generalized_force(t, q, v, p)
        power = sum(
            jnp.sum(a * b)
            for a, b in zip(jtu.tree_leaves(f), jtu.tree_leaves(rates[0]), strict=True)
        )
        out[name] = dict(rates=rates, energy=energy, dE=dE, power=power)
    return out
