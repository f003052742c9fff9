"""The animation (`animation.html` of `sphere-mech run`, `sm.animate`): a self-contained HTML
player whose frames are transparent PNGs of the pixels that differ from the still image
(blitting): 150 frames take well under a second to draw and about 2-4 kB each."""

import base64
import html
import io
import json
import string
import uuid

import diffrax
import jax
import numpy as np

from ._drawing import Skeleton, draw_static, equal_axes, positions, skeleton
from ._system import AbstractSystem

MAX_FRAMES = 150
TRAIL = 1 / 6  # each tip's recent path: this fraction of the frames


def frame_indices(t: np.ndarray, frames: int) -> np.ndarray:
    """At most `frames` indices of `t`, nearest to evenly spaced times."""
    if len(t) <= frames:
        return np.arange(len(t))
    targets = np.linspace(t[0], t[-1], frames)
    idx = np.clip(np.searchsorted(t, targets), 1, len(t) - 1)
    idx = np.where(targets - t[idx - 1] < t[idx] - targets, idx - 1, idx)
    return np.unique(idx)


def _png(rgba: np.ndarray) -> str:
    import matplotlib.image

    buf = io.BytesIO()
    matplotlib.image.imsave(buf, rgba, format="png", pil_kwargs={"compress_level": 6})
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _artists(ax, skel: Skeleton) -> tuple:
    line = lambda *style, **kwargs: ax.plot([], [], [], *style, animated=True, **kwargs)[0]
    marker = "" if max([len(link) for link in skel.links] + [0]) > 9 else "o"
    link = dict(color="k", lw=1.4, marker=marker, ms=4, mfc="tab:blue", markevery=slice(1, None))
    links = [line("-", **link) for _ in skel.links]
    links += [line("-", color="tab:blue", lw=2.6) for _ in skel.frame]  # a rigid base's arms
    tips, bases = line("o", color="tab:red", ms=5), line("ks", ms=7)
    n_trails = len(skel.tips) if len(skel.tips) <= 8 else 0
    trails = [line("-", lw=0.8, alpha=0.7, color=f"C{k}") for k in range(n_trails)]
    return links, tips, bases, trails


def render(
    skel: Skeleton, t: np.ndarray, x: np.ndarray, *, title: str = "", frames: int = MAX_FRAMES
) -> tuple[str, list[str], np.ndarray]:
    """The still image and at most `frames` overlays (base64 PNG), and their times."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    idx = frame_indices(t, frames)
    pts = skel.points(x[idx])
    fig = Figure(figsize=(5.6, 5.6), dpi=90)
    canvas, ax = FigureCanvasAgg(fig), fig.add_subplot(projection="3d")
    fig.subplots_adjust(0.0, 0.02, 0.94, 0.96)
    equal_axes(ax, skel, x)
    draw_static(ax, skel)
    ax.set_title(title, fontsize=10)
    links, tips, bases, trails = _artists(ax, skel)
    canvas.draw()
    still = canvas.copy_from_bbox(fig.bbox)
    base = np.array(canvas.buffer_rgba())
    pixels = lambda: np.asarray(canvas.buffer_rgba()).view(np.uint32)[..., 0]  # RGBA as one
    overlays, trail = [], max(2, round(TRAIL * len(idx)))
    for f in range(len(idx)):
        canvas.restore_region(still)
        for line, link in zip(links, skel.links + skel.frame, strict=True):
            line.set_data_3d(*pts[f, link].T)
        tips.set_data_3d(*pts[f, skel.tips].T)
        bases.set_data_3d(*pts[f, skel.bases].T)
        for line, i in zip(trails, skel.tips, strict=False):
            line.set_data_3d(*pts[max(0, f - trail) : f + 1, i].T)
        for artist in [*trails, *links, tips, bases]:
            ax.draw_artist(artist)
        frame = np.where(pixels() == base.view(np.uint32)[..., 0], 0, pixels())
        overlays.append(_png(frame.view(np.uint8).reshape(base.shape)))  # unchanged: clear
    return _png(base), overlays, t[idx]


_ICONS = {  # 16 x 16 inline SVG shapes
    "first": '<rect x="1" y="2" width="2" height="12"/><polygon points="10,2 3,8 10,14"/>'
    '<polygon points="16,2 9,8 16,14"/>',
    "previous": '<rect x="3" y="2" width="2" height="12"/><polygon points="13,2 5,8 13,14"/>',
    "play": '<polygon points="4,2 14,8 4,14"/>',
    "pause": '<rect x="3" y="2" width="3.5" height="12"/><rect x="9.5" y="2" width="3.5" '
    'height="12"/>',
    "next": '<polygon points="3,2 11,8 3,14"/><rect x="11" y="2" width="2" height="12"/>',
    "last": '<polygon points="0,2 7,8 0,14"/><polygon points="6,2 13,8 6,14"/>'
    '<rect x="13" y="2" width="2" height="12"/>',
    "slower": '<rect x="3" y="7" width="10" height="2"/>',
    "faster": '<rect x="3" y="7" width="10" height="2"/><rect x="7" y="3" width="2" height="10"/>',
}

_TEMPLATE = string.Template("""\
<div class="sm-player" id="$id" style="display:inline-block;font-family:sans-serif">
<div style="display:grid">
<img style="grid-area:1/1" alt="$alt" src="data:image/png;base64,$still">
<img class="sm-frame" style="grid-area:1/1" alt="">
</div>
<div style="display:flex;align-items:center;gap:4px;margin-top:4px">
$buttons
<input class="sm-slider" type="range" min="0" max="$last" step="1" value="0"
 aria-label="time" style="flex:1">
<span class="sm-time" style="font-size:13px;min-width:7em"></span>
<label style="font-size:13px"><input class="sm-loop" type="checkbox" checked>loop</label>
</div>
<script>
(function () {
  var root = document.getElementById("$id");
  var frames = $frames, times = $times, delay = $delay;
  var img = root.querySelector(".sm-frame"), slider = root.querySelector(".sm-slider");
  var clock = root.querySelector(".sm-time"), loop = root.querySelector(".sm-loop");
  var frame = 0, timer = null;
  function show(i) {
    frame = Math.max(0, Math.min(frames.length - 1, i));
    img.src = "data:image/png;base64," + frames[frame];
    slider.value = frame;
    clock.textContent = "t = " + times[frame].toFixed($digits) + " s";
  }
  function pause() { clearInterval(timer); timer = null; }
  function tick() {
    if (frame + 1 < frames.length) { show(frame + 1); }
    else if (loop.checked) { show(0); }
    else { pause(); }
  }
  function play() {
    pause();
    if (frame + 1 >= frames.length) { show(0); }
    timer = setInterval(tick, delay);
  }
  function speed(factor) {
    delay = Math.min(2000, Math.max(10, delay * factor));
    if (timer) { pause(); timer = setInterval(tick, delay); }
  }
  var actions = {
    first: function () { pause(); show(0); },
    previous: function () { pause(); show(frame - 1); },
    play: play, pause: pause,
    next: function () { pause(); show(frame + 1); },
    last: function () { pause(); show(frames.length - 1); },
    slower: function () { speed(1.5); }, faster: function () { speed(1 / 1.5); }
  };
  root.querySelectorAll("button[data-action]").forEach(function (b) {
    b.addEventListener("click", actions[b.getAttribute("data-action")]);
  });
  slider.addEventListener("input", function () { pause(); show(parseInt(slider.value, 10)); });
  show(0);
})();
</script>
</div>""")


def _button(action: str) -> str:
    title = action.capitalize() + " frame" * (action in ("first", "previous", "next", "last"))
    return (
        f'<button type="button" data-action="{action}" title="{title}" '
        f'aria-label="{title}" style="line-height:0;padding:4px 6px">'
        '<svg viewBox="0 0 16 16" width="14" height="14" fill="currentColor" '
        f'aria-hidden="true">{_ICONS[action]}</svg></button>'
    )


def player(
    skel: Skeleton, t: np.ndarray, x: np.ndarray, *, title: str = "", frames: int = MAX_FRAMES
) -> str:
    """The HTML player (a fragment, one `div`) of positions `x` `(T, n, 3)` at times `t`."""
    still, overlays, times = render(skel, t, x, title=title, frames=frames)
    step = float(np.min(np.diff(times))) if len(times) > 1 else 1.0
    digits = int(np.clip(np.ceil(-np.log10(step)) if step > 0 else 3, 0, 4))
    delay = float(np.clip(1000 * (times[-1] - times[0]) / max(len(times) - 1, 1), 40, 100))
    return _TEMPLATE.substitute(
        id=f"sm-player-{uuid.uuid4().hex[:12]}",
        alt=html.escape(title or "animation"),
        still=still,
        last=len(overlays) - 1,
        buttons="\n".join(map(_button, _ICONS)),
        frames=json.dumps(overlays),
        times=json.dumps([float(s) for s in times]),
        delay=f"{delay:.0f}",
        digits=digits,
    )


def page(player_html: str, title: str) -> str:
    """A standalone HTML page holding the player."""
    return (
        '<!DOCTYPE html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f"<title>{html.escape(title)}</title>\n</head>\n<body>\n{player_html}\n"
        "</body>\n</html>\n"
    )


class Animation(str):
    """The player's HTML; a notebook displays it (`_repr_html_`)."""

    def _repr_html_(self) -> str:
        return str(self)

    def __repr__(self) -> str:
        return f"<sphere_mech animation: {len(self) / 1e6:.2f} MB of HTML>"


def _trajectory(system, sol) -> tuple[np.ndarray, np.ndarray]:
    """The finite save times `(T,)` of `sol` and the points drawn at them, `(T, p, 3)`."""
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
    return t[keep], positions(system, jax.tree.map(lambda x: np.asarray(x)[keep], q))


def animate(
    system_or_scene: AbstractSystem, sol: diffrax.Solution, *, frames: int = MAX_FRAMES
) -> Animation:
    """An animation of a solution: an HTML player with play, pause, step and a time
    slider, that a notebook displays (no network needed). A `Scene` is drawn from its
    kinetic terms at `scene.points(q)` (chains from their pivot or the moving `Base`, drawn
    as a square, beads with their shared sphere); any other system as the points `q` on
    the unit sphere.

    **Arguments:**
    - `system_or_scene`, `sol`: the system simulated and a solution of `sm.simulate` saved at
      several times (e.g. `saveat=diffrax.SaveAt(ts=...)`).
    - `frames`: the most frames embedded (states are subsampled evenly).

    **Returns:** the player's HTML as a `str` subclass that notebooks display (write it
    into a page's body to keep it).
    """
    t, x = _trajectory(system_or_scene, sol)
    if len(t) < 2:
        raise ValueError(
            f"sol: expected states at two times or more, got {len(t)}; "
            "save them with saveat=diffrax.SaveAt(ts=...)"
        )
    if not (isinstance(frames, int) and frames >= 2):
        raise ValueError(f"frames: expected an integer >= 2, got {frames!r}")
    skel = skeleton(system_or_scene, x.shape[1])
    return Animation(player(skel, t, x, frames=frames))
