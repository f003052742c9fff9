"""`plot.png` of a scene run: the motion in 3-D, the energy (with forces, minus the work
done), its relative error, and the constraint error (a panel only above rounding level)."""

import numpy as np

from .._drawing import Skeleton, draw_static, equal_axes, skeleton

SNAPSHOTS = 8
LONG_CHAIN = 4  # more masses on one link: snapshots instead of every path


def _configuration(ax, skel, pts, style, label):
    handles = []
    for link in skel.links:
        many = len(link) > LONG_CHAIN + 1
        markers = dict(marker="" if many else "o", ms=4, markevery=slice(1, None))  # not the pivot
        handles += ax.plot(*pts[link].T, lw=1.6, **markers, **style)
        if many:  # the tip only
            ax.plot(*pts[link[-1:]].T, "o", ms=4, **style)
    dots = {**style, "ls": ""}
    if len(skel.free):
        handles += ax.plot(*pts[skel.free + len(skel.anchors)].T, marker="o", ms=6, **dots)
    if len(skel.bases):
        ax.plot(*pts[skel.bases].T, marker="s", ms=7, **dots)
    for line in skel.frame:  # a rigid base's arms
        ax.plot(*pts[line].T, lw=2.4, **style)
    if len(skel.rotors):
        ax.plot(*pts[skel.rotors].T, marker="o", ms=9, mew=1.2, **{**dots, "mfc": "none"})
    handles[0].set_label(label)
    return handles[:1]


def draw_motion(ax, skel: Skeleton, t: np.ndarray, x: np.ndarray) -> list:
    """Links at start and end, paths (or snapshots of long chains); returns handles."""
    from matplotlib import colormaps

    equal_axes(ax, skel, x)
    handles = list(draw_static(ax, skel))
    pts = skel.points(x)
    long = [link for link in skel.links if len(link) > LONG_CHAIN + 1]
    paths = [i for link in skel.links if len(link) <= LONG_CHAIN + 1 for i in link[1:]]
    paths += [link[-1] for link in long] + list(skel.free + len(skel.anchors))
    for i in skel.bases:  # faint, under the masses' paths
        handles += ax.plot(*pts[:, i].T, lw=0.8, ls=":", color="0.45", label="path of the base")
    for k, i in enumerate(paths):
        label = f"path of mass {skel.mass(i)}" if len(paths) <= 6 else None
        color = "tab:red" if long else f"C{k % 10}"  # long: not a colour of the snapshots
        handles += ax.plot(*pts[:, i].T, lw=0.6, alpha=0.8, color=color, label=label)
    if long:
        cmap = colormaps["viridis"]
        for s in np.linspace(0, len(t) - 1, SNAPSHOTS + 2)[1:-1].round().astype(int):
            for link in long:
                ax.plot(*pts[s, link].T, lw=0.8, color=cmap(t[s] / t[-1] if t[-1] else 0))
        label = f"snapshots (colour: t, {t[0]:g} to {t[-1]:g} s)"
        handles += ax.plot([], [], color=cmap(0.5), lw=0.8, label=label)
    start = {"color": "0.55", "ls": "--", "mfc": "white"}
    handles += _configuration(ax, skel, pts[0], start, f"start (t = {t[0]:g} s)")
    handles += _configuration(ax, skel, pts[-1], {"color": "k"}, f"end (t = {t[-1]:g} s)")
    return handles


def _energy(ax, result) -> None:
    t, E = result.t, result.energy
    ax.plot(t, E, lw=1.6, color="k", label="E = T + U")
    if result.potential is not None:  # on top of E: U is often close to it
        ax.plot(t, E - result.potential, lw=0.7, color="tab:red", label="kinetic T")
        ax.plot(t, result.potential, lw=0.7, color="tab:blue", label="potential U")
    if result.work is not None:
        balance, label = result.step_energy - result.work, "E - W (W: work of the forces)"
        ax.plot(result.error_t, balance, lw=1.4, ls="--", color="tab:green", label=label)
    ax.set_ylabel("energy [J]", fontsize=8)
    ax.legend(fontsize=7, ncol=4, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False)


def _semilogy(ax, t, values, title) -> None:
    eps = np.finfo(np.float64).eps
    ax.semilogy(t, np.maximum(np.abs(values), eps / 100), lw=0.8)  # zeros drawn at eps/100
    ax.set_title(title, fontsize=9)


def figure(result, scene):
    """The figure (a matplotlib `Figure`, no pyplot) of a `SceneResult` of `scene`."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    s, skel = result.summary, skeleton(scene, result.x.shape[1])
    eps, worst = np.finfo(result.constraint.dtype).eps, float(np.max(result.constraint))
    drift = worst > 1000 * eps  # the constraint error says something: a panel
    fig = Figure(figsize=(13, 6.2), dpi=100)
    FigureCanvasAgg(fig)
    layout = dict(left=0.02, right=0.98, top=0.9, bottom=0.12, hspace=0.45, wspace=0.12)
    grid = fig.add_gridspec(3 if drift else 2, 2, width_ratios=[1, 1.2], **layout)
    ax = fig.add_subplot(grid[:, 0], projection="3d")
    ax.legend(handles=draw_motion(ax, skel, result.t, result.x), fontsize=7, loc="upper left")
    _energy(fig.add_subplot(grid[0, 1]), result)
    title = "relative energy error |E - E(0)| / max(|T| + |V|)"
    if result.work is not None:
        title = "work-energy balance |E - E(0) - W| / scale"
    _semilogy(fig.add_subplot(grid[1, 1]), result.error_t, result.error, title)
    if drift:
        title = "constraint error max_i | |q_i| - 1 |"
        _semilogy(fig.add_subplot(grid[2, 1]), result.t, result.constraint, title)
    for a in fig.axes[1:]:
        a.set_xlabel("t [s]", fontsize=8)
        a.tick_params(labelsize=7)
    title = f"{s['scene']}: {s['t1']:g} s, {s['solver']}, {s['steps']} steps"
    fig.suptitle(title, fontsize=11, parse_math=False)  # the name is plain text
    worst_text = f"max_i,t | |q_i| - 1 | = {worst:.1e} ({worst / eps:.1f} x machine epsilon)"
    fig.text(0.5, 0.02, f"constraint error {worst_text}", ha="center", fontsize=9)
    return fig


def plot(path, result, scene) -> None:
    """Write `plot.png` of a `SceneResult` of `scene` to `path`."""
    figure(result, scene).savefig(path, dpi=100)
