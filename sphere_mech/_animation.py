"""The animation (`animation.html` of `sphere-mech run`, `sm.animate`): an interactive 3-D
viewer made with plotly.js (orbit, zoom, play, pause, a time slider; tips' trails, a rigid
base's arms), one self-contained HTML fragment: the figure as JSON and plotly.js itself,
gzip-compressed and base64-encoded (2 MB instead of 4.8), unpacked by the browser
(`DecompressionStream`), so that it works offline, in a file or a notebook's output."""

import base64
import functools
import gzip
import html
import json
import math
import string
import uuid

import diffrax
import jax
import numpy as np

from ._drawing import Skeleton, cube, positions, skeleton, wireframe
from ._misc import check_integer
from ._scene.scene import Scene
from ._spaces import Spheres
from ._system import AbstractSystem

MAX_FRAMES = 150
TRAIL = 1 / 6  # each tip's recent path: this fraction of the frames
MAX_TRAILS = 8  # more tips than this: no trails
COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f")


def frame_indices(t: np.ndarray, frames: int) -> np.ndarray:
    """At most `frames` increasing indices of `t` (a run's times: increasing, or decreasing
    for a backward run), nearest to evenly spaced times."""
    if len(t) <= frames:
        return np.arange(len(t))
    s = t if t[-1] >= t[0] else -t  # increasing
    targets = np.linspace(s[0], s[-1], frames)
    idx = np.clip(np.searchsorted(s, targets), 1, len(s) - 1)
    idx = np.where(targets - s[idx - 1] < s[idx] - targets, idx - 1, idx)
    return np.unique(idx)


def _label(t: float, digits: int) -> str:
    """A time with `digits` decimals, a zero unsigned (not `-0.000`)."""
    label = f"{t:.{digits}f}"
    return label.removeprefix("-") if float(label) == 0 else label


def _joined(lines) -> np.ndarray:
    """The indices of polylines in one sequence, -1 (a gap) between two."""
    return np.concatenate([np.append(line, -1) for line in lines])[:-1]


def _xyz(points: np.ndarray) -> dict:
    """A trace's `x`, `y`, `z` from points `(m, 3)`, null (a gap) where one is not finite."""
    cols = points.T.tolist()
    return {
        k: [v if math.isfinite(v) else None for v in c] for k, c in zip("xyz", cols, strict=True)
    }


def _trace(name: str, mode: str, **style) -> dict:
    return dict(type="scatter3d", name=name, mode=mode, **style)


def _moving(skel: Skeleton) -> list[tuple[np.ndarray, dict]]:
    """The traces that move, as indices into `points(x)` (-1: a gap) and a style: links
    (dots at the masses unless a cable), a rigid base's arms and rotors, moving bases, the
    tips."""
    traces = []
    if skel.links:
        seq = _joined(skel.links)
        starts = np.cumsum([0] + [len(link) + 1 for link in skel.links[:-1]])
        dots = (seq >= 0) & ~np.isin(np.arange(len(seq)), starts)
        dots &= max(len(link) for link in skel.links) <= 9
        marker = dict(size=np.where(dots, 5, 0).tolist(), color=COLOURS[0])
        lines = dict(color="black", width=3)
        traces.append((seq, _trace("links", "lines+markers", line=lines, marker=marker)))
    if skel.frame:
        arms = dict(color=COLOURS[0], width=8)
        traces.append((_joined(skel.frame), _trace("body", "lines", line=arms)))
    if len(skel.rotors):
        hubs = dict(symbol="circle-open", size=10, color=COLOURS[0], line=dict(width=3))
        traces.append((skel.rotors, _trace("rotors", "markers", marker=hubs)))
    square = dict(symbol="square", size=6, color="black")
    if len(skel.bases):
        traces.append((skel.bases, _trace("base", "markers", marker=square)))
    if len(skel.tips):
        traces.append((skel.tips, _trace("tips", "markers", marker=dict(size=5, color=COLOURS[3]))))
    return traces


def _still(skel: Skeleton) -> list[dict]:
    """The traces that stay: the anchors (squares) and the spheres (grey wireframes)."""
    traces = []
    if len(skel.anchors):
        square = dict(symbol="square", size=4, color="black")
        name = "pivot" if skel.links else "centre"
        traces.append(_xyz(skel.anchors) | _trace(name, "markers", marker=square))
    for c, r in skel.spheres:
        grid = wireframe(c, r)
        rings = [*grid.transpose(1, 2, 0), *grid.transpose(2, 1, 0)]  # parallels, meridians
        gap = np.full((1, 3), np.nan)
        points = np.concatenate([np.concatenate([ring, gap]) for ring in rings])
        line = dict(color="#c8c8c8", width=1)
        traces.append(_xyz(points) | _trace("sphere", "lines", hoverinfo="skip", line=line))
    return traces


def _controls(labels: list[str], delay: float) -> dict:
    """Play and pause buttons and a slider of the frames, labelled `t = ... s`."""
    jump = dict(mode="immediate", frame=dict(duration=0, redraw=True), transition=dict(duration=0))
    play = jump | dict(fromcurrent=True, frame=dict(duration=round(delay), redraw=True))
    buttons = [
        dict(label="Play", method="animate", args=[None, play]),
        dict(label="Pause", method="animate", args=[[None], jump]),
    ]
    steps = [dict(label=s, method="animate", args=[[str(f)], jump]) for f, s in enumerate(labels)]
    below = dict(x=0, y=0, xanchor="left", yanchor="top")
    return dict(
        updatemenus=[
            below
            | dict(
                type="buttons",
                direction="left",
                buttons=buttons,
                showactive=False,
                pad=dict(t=48, r=8),
            )
        ],
        sliders=[
            below
            | dict(
                x=0.18,
                len=0.82,
                steps=steps,
                pad=dict(t=30, b=8),
                currentvalue=dict(prefix="t = ", suffix=" s", font=dict(size=13, color="#444")),
                font=dict(color="rgba(0,0,0,0)"),  # a label a frame: shown as the value only
            )
        ],
    )


def figure(
    skel: Skeleton, t: np.ndarray, x: np.ndarray, *, title: str = "", frames: int = MAX_FRAMES
) -> dict:
    """The plotly figure (data, layout, frames) of positions `x` `(T, n, 3)` at times `t`:
    at most `frames` frames, each restyling the moving traces (listed first, the tips'
    trails last of them); equal-aspect axes around the whole motion."""
    idx = frame_indices(t, frames)
    pts = skel.points(x[idx])
    pts = np.concatenate([pts, np.full(pts[:, :1].shape, np.nan)], axis=1)  # [-1]: a gap
    centre, half = cube(skel, x)
    moving = _moving(skel)
    trails = skel.tips if len(skel.tips) <= MAX_TRAILS else []
    trail, decimals = max(2, round(TRAIL * len(idx))), math.ceil(-math.log10(half * 1e-5))
    path = lambda f, i: _xyz(np.round(pts[max(0, f - trail) : f + 1, i], decimals))  # cosmetic
    points = lambda f: [_xyz(pts[f, seq]) for seq, _ in moving] + [path(f, i) for i in trails]
    frame = lambda f: [xyz | dict(type="scatter3d") for xyz in points(f)]
    styles = [style for _, style in moving] + [
        _trace("trail", "lines", opacity=0.7, line=dict(color=COLOURS[k % len(COLOURS)], width=2))
        for k in range(len(trails))
    ]
    data = [xyz | style for xyz, style in zip(points(0), styles, strict=True)] + _still(skel)
    step = float(np.min(np.abs(np.diff(t[idx])))) if len(idx) > 1 else 1.0
    digits = int(np.clip(np.ceil(-np.log10(step)) if step > 0 else 3, 0, 4))
    delay = float(np.clip(1000 * abs(t[idx[-1]] - t[idx[0]]) / max(len(idx) - 1, 1), 40, 100))
    axis = lambda k: dict(
        range=[centre[k] - half, centre[k] + half],
        autorange=False,
        title=dict(text=f"{'xyz'[k]} [m]"),
    )
    layout = dict(
        title=dict(text=html.escape(title), x=0.5, font=dict(size=14)),
        showlegend=False,
        uirevision="sphere_mech",  # the camera stays where the user put it
        margin=dict(l=0, r=0, t=40 if title else 10, b=80),
        scene=dict(xaxis=axis(0), yaxis=axis(1), zaxis=axis(2), aspectmode="cube"),
        **_controls([_label(s, digits) for s in t[idx]], delay),
    )
    traces = list(range(len(styles)))
    frames_ = [dict(name=str(f), traces=traces, data=frame(f)) for f in range(len(idx))]
    return dict(data=data, layout=layout, frames=frames_)


@functools.cache
def _plotly_js() -> str:
    """plotly.js (the copy the plotly package ships), gzip-compressed and base64-encoded."""
    from plotly.offline import get_plotlyjs

    return base64.b64encode(gzip.compress(get_plotlyjs().encode(), 9, mtime=0)).decode()


_TEMPLATE = string.Template("""\
<div class="sm-viewer">
<div id="$id" style="width:100%;max-width:720px;height:620px"></div>
<script type="application/json" class="sm-figure">$figure</script>
<script type="application/octet-stream" class="sm-plotly">$plotly</script>
<script>
(function () {
  var div = document.getElementById("$id"), root = div.parentNode;
  var figure = JSON.parse(root.querySelector(".sm-figure").textContent);
  function unpack() {  // plotly.js, once a page: gunzip, run (module loaders hidden)
    var packed = root.querySelector(".sm-plotly").textContent.trim();
    var bytes = Uint8Array.from(atob(packed), function (c) { return c.charCodeAt(0); });
    var stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream("gzip"));
    return new Response(stream).text().then(function (source) {
      new Function("define", "module", "exports", source)();
      return window.Plotly;
    });
  }
  if (!window.smPlotly) {
    window.smPlotly = window.Plotly ? Promise.resolve(window.Plotly) : unpack();
  }
  window.smPlotly.then(function (Plotly) {
    figure.config = {responsive: true, displaylogo: false, showSendToCloud: false};
    Plotly.newPlot(div, figure);
  }, function (error) {
    window.smPlotly = null;  // the next viewer tries again
    div.textContent = "sphere_mech viewer: plotly.js did not load (" + error + "); it needs "
      + "DecompressionStream (Chrome 80, Firefox 113, Safari 16.4 or later).";
  });
})();
</script>
</div>""")


def player(
    skel: Skeleton, t: np.ndarray, x: np.ndarray, *, title: str = "", frames: int = MAX_FRAMES
) -> str:
    """The viewer (an HTML fragment, one `div`) of positions `x` `(T, n, 3)` at times `t`."""
    fig = json.dumps(figure(skel, t, x, title=title, frames=frames), allow_nan=False)
    return _TEMPLATE.substitute(
        id=f"sm-viewer-{uuid.uuid4().hex[:12]}",
        figure=fig.replace("</", "<\\/"),  # no end of the script inside it
        plotly=_plotly_js(),
    )


def page(player_html: str, title: str) -> str:
    """A standalone HTML page holding the viewer."""
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n</head>\n<body>\n{player_html}\n"
        "</body>\n</html>\n"
    )


class Animation(str):
    """The viewer's HTML; a notebook displays it (`_repr_html_`)."""

    def _repr_html_(self) -> str:
        return str(self)

    def __repr__(self) -> str:
        return f"<sphere_mech animation: {len(self) / 1e6:.2f} MB of HTML>"


def _trajectory(system, sol) -> tuple[np.ndarray, np.ndarray]:
    """The finite save times `(T,)` of `sol`, two or more, and the points drawn at them,
    `(T, p, 3)`."""
    if not isinstance(system, Scene) and not isinstance(system.space, Spheres):
        raise ValueError(
            "system_or_scene: animate draws a Scene or the points of a system on Spheres, "
            f"got a system on {system.space}"
        )
    ts, ys = sol.ts, sol.ys
    if isinstance(ts, list | tuple):  # SaveAt(subs=[...]): the first
        ts, ys = ts[0], ys[0]
    t, q = np.asarray(ts), ys[0] if isinstance(ys, list | tuple) else ys
    if t.ndim != 1 or system.space.batch_shape(q) != t.shape:
        raise ValueError(
            f"sol: expected the solution of one run, times (T,) and q (T, n, 3)"
            f" (or a dict of arrays with a leading T axis), got times {t.shape}"
            f" and q {jax.tree.map(np.shape, q)}"
        )
    keep = np.isfinite(t)  # SaveAt(steps=True) pads with inf
    t, q = t[keep], jax.tree.map(lambda x: np.asarray(x)[keep], q)
    if len(t) < 2:
        raise ValueError(
            f"sol: expected states at two times or more, got {len(t)}; "
            "save them with saveat=diffrax.SaveAt(ts=...)"
        )
    first = jax.tree.map(lambda x: x[0], q)
    system.space.check_shapes(first, first, q_name="each q of sol")  # shapes only: v as q
    return t, positions(system, q)


def animate(
    system_or_scene: AbstractSystem, sol: diffrax.Solution, *, frames: int = MAX_FRAMES
) -> Animation:
    """An animation of a solution: an interactive 3-D viewer (plotly.js: orbit, zoom, play,
    pause and a time slider; the tips' recent paths as trails) that a notebook displays,
    with no network needed (plotly.js is embedded, compressed: about 2 MB). A `Scene` is
    drawn from its kinetic terms at `scene.drawn_points(q)` (chains from their pivot or the
    moving `Base`, drawn as a square, a `RigidBase`'s arms and its `Rotors` as rings, beads
    with their shared sphere); a system on `Spheres` (a plain `(n, 3)` state) as its points
    `q` on the unit sphere about the origin. Any other system (on a dict of factors, on
    `Rotations`) raises `ValueError`, and so do states `q` without the shapes of the
    system's space (e.g. not `n` points on `Spheres(n)`).

    **Arguments:**
    - `system_or_scene`, `sol`: the system simulated and a solution of `sm.simulate` saved at
      several times (e.g. `saveat=diffrax.SaveAt(ts=...)`).
    - `frames`: the most frames embedded (states are subsampled evenly).

    **Returns:** the viewer's HTML as a `str` subclass that notebooks display (write it
    into a page's body to keep it).
    """
    t, x = _trajectory(system_or_scene, sol)
    check_integer(frames, "frames", 2)
    skel = skeleton(system_or_scene, x.shape[1])
    return Animation(player(skel, t, x, frames=frames))
