"""Forward mode vs checkpointed reverse mode for fitting through `simulate`.

The fit problem of tests/test_fit.py: a damped double spherical pendulum, 5 s of noisy
positions of both masses (51 times), four parameters (mass ratio, two lengths, damping)
fitted from 30 % off. Measures (after compilation, median of repeats):

1. the gradient of the scalar loss: `jax.grad` with `diffrax.RecursiveCheckpointAdjoint`
   against `jax.jacfwd` with `diffrax.ForwardMode`;
2. the whole Levenberg-Marquardt fit: `sm.fit(jac="fwd")` against `sm.fit(jac="bwd")`.

Prints a markdown table and writes benchmarks/results/fit_adjoint.png.
"""

import pathlib
import sys

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _harness import bars, publish, pyplot, save_figure, table, timing

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "tests"))
from helpers import SIM, chain_initial_states  # noqa: E402
from test_fit import START, TRUE, _record, damped_chain, mass_positions  # noqa: E402

import sphere_mech as sm  # noqa: E402


def main():
    y0 = jax.tree.map(lambda x: x[0], chain_initial_states(1))
    ts, obs = _record(y0, 5.0, 51, jax.random.PRNGKey(0))

    def loss(p, adjoint):
        system = damped_chain(p)
        sol = sm.simulate(system, y0, ts[-1], saveat=diffrax.SaveAt(ts=ts), adjoint=adjoint, **SIM)
        pred = jax.vmap(system.chain.positions)(sol.ys[0])
        return 0.5 * jnp.sum((pred - obs) ** 2)

    rev = eqx.filter_jit(jax.grad(lambda p: loss(p, diffrax.RecursiveCheckpointAdjoint())))
    fwd = eqx.filter_jit(jax.jacfwd(lambda p: loss(p, diffrax.ForwardMode())))
    g_rev, g_fwd = rev(START), fwd(START)
    assert all(np.isclose(g_rev[k], g_fwd[k], rtol=1e-8) for k in g_rev)
    fit = lambda jac: (
        sm.fit(
            damped_chain,
            START,
            ts,
            obs,
            mass_positions,
            y0=y0,
            positive=True,
            jac=jac,
            simulate_options=SIM,
        ).params
    )
    rows = [
        (
            "gradient of the loss",
            timing(lambda: rev(START), what="reverse").median,
            timing(lambda: fwd(START), what="forward").median,
        ),
        (
            "fit (Levenberg-Marquardt)",
            timing(lambda: fit("bwd"), 3, what="fit, reverse").median,
            timing(lambda: fit("fwd"), 3, what="fit, forward").median,
        ),
    ]
    fitted = fit("fwd")
    publish(
        table(
            ["task", "reverse (checkpointed) [s]", "forward [s]", "reverse / forward"],
            [(name, f"{r:.3f}", f"{f:.3f}", f"{r / f:.1f}") for name, r, f in rows],
        )
    )
    print("\nfitted / true - 1:", {k: f"{float(fitted[k] / TRUE[k] - 1):+.1e}" for k in TRUE})

    fig, ax = pyplot().subplots(figsize=(5, 3))
    series = {
        "reverse (RecursiveCheckpointAdjoint)": [r[1] for r in rows],
        "forward (ForwardMode)": [r[2] for r in rows],
    }
    bars(ax, [r[0] for r in rows], series, fontsize=10)
    ax.set_yscale("log")
    ax.set_ylabel("time [s]")
    save_figure(fig, "fit_adjoint.png")


if __name__ == "__main__":
    main()
