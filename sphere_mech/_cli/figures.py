"""The figure of a scene run: paths of the masses, energy error, constraint error."""

import numpy as np


def plot(path, result) -> None:
    """Write `plot.png` of a `SceneResult` to `path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x, s = result.x, result.summary
    fig = plt.figure(figsize=(13, 4))
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    for i in range(x.shape[1]):
        label = f"mass {i}" if x.shape[1] <= 8 else None
        ax.plot(x[:, i, 0], x[:, i, 1], x[:, i, 2], lw=0.6, label=label)
    ax.set_title(f"{s['scene']}: paths of the masses", fontsize=9)
    if x.shape[1] <= 8:
        ax.legend(fontsize=7)
    forced = "max_relative_work_energy_balance" in s
    title = "|E - E(0) - W| / scale" if forced else "|E - E(0)| / |E(0)|"
    eps = np.finfo(np.float64).eps
    for k, (t, values, name) in enumerate(
        [(result.error_t, np.abs(result.error), title),
         # running maximum: the constraint error sits at rounding level, often exactly 0
         (result.t, np.maximum.accumulate(result.constraint),
          "max_i | |q_i| - 1 | (running maximum)")]
    ):
        a = fig.add_subplot(1, 3, k + 2)
        a.semilogy(t, np.maximum(values, eps / 100), lw=0.8)  # exact zeros drawn at eps/100
        if k == 1:
            a.axhline(eps, color="gray", lw=0.6, ls="--", label="float64 epsilon")
            a.set_ylim(eps / 300, max(1e-12, a.get_ylim()[1]))
            a.legend(fontsize=7)
        a.set_xlabel("t [s]")
        a.set_title(name, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
