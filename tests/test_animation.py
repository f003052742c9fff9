"""`sm.animate` and `animation.html`: one plotly viewer for scenes and for any system, a
bounded number of frames holding the drawn points, no network, and (where a chromium binary
exists) the page rendered in a real headless browser with WebGL: not blank, the 3-D scene,
the controls and the time."""

import json
import os
import re
import shutil
import subprocess
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import plotly.graph_objects as go
import pytest

import sphere_mech as sm
from sphere_mech._animation import MAX_FRAMES, TRAIL, figure, frame_indices, page
from sphere_mech._cli import main
from sphere_mech._drawing import skeleton

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _figure(html: str) -> dict:
    """The figure a viewer embeds (the first one)."""
    found = re.search(r'<script type="application/json" class="sm-figure">(.*?)</script>', html)
    return json.loads(found.group(1))  # JSON reads "<\\/" as "</"


def _trace(fig: dict, name: str, frame: int) -> np.ndarray:
    """The points `(m, 3)` of the first trace named `name` in a frame (NaN: a gap)."""
    i = [trace["name"] for trace in fig["data"]].index(name)
    trace = fig["frames"][frame]["data"][fig["frames"][frame]["traces"].index(i)]
    return np.array([trace[k] for k in "xyz"], dtype=float).T


def _offline(html: str) -> None:
    """Nothing fetched: no URL at all (plotly.js is compressed), no external script or sheet."""
    assert "://" not in html and "<script src" not in html and "<link" not in html


def _circling(n: int, steps: int):
    """A solution-like object: `n` points turning about the vertical, 45 deg below it."""
    t = np.linspace(0.0, 2.0, steps)
    phase = np.pi * t[:, None] + np.arange(n)
    q = np.stack([np.cos(phase), np.sin(phase), -np.ones_like(phase)], axis=-1) / np.sqrt(2)
    return types.SimpleNamespace(ts=jnp.asarray(t), ys=(jnp.asarray(q), jnp.zeros_like(q)))


def _controls(fig: dict) -> None:
    buttons = fig["layout"]["updatemenus"][0]["buttons"]
    assert [b["label"] for b in buttons] == ["Play", "Pause"]
    slider = fig["layout"]["sliders"][0]
    assert slider["currentvalue"]["prefix"] == "t = " and slider["currentvalue"]["suffix"] == " s"
    steps = [step["args"][0] for step in slider["steps"]]
    assert steps == [[frame["name"]] for frame in fig["frames"]]  # one step a frame, in order


def test_animate_a_scene():
    scene = sm.chain_pendulum(masses=[1.0, 0.5], lengths=[1.0, 0.5])
    sol = _circling(2, 301)
    html = sm.animate(scene, sol)
    assert isinstance(html, str) and html._repr_html_() == str(html)
    assert "MB of HTML" in repr(html)  # not the whole page
    _offline(html)
    fig = _figure(html)
    go.Figure(fig)  # plotly's schema: every property exists
    _controls(fig)
    assert len(fig["frames"]) == MAX_FRAMES == 150
    labels = [step["label"] for step in fig["layout"]["sliders"][0]["steps"]]
    assert labels[0] == "0.00" and labels[-1] == "2.00"  # both ends kept
    assert len(_figure(sm.animate(scene, sol, frames=20))["frames"]) == 20
    ids = re.findall(r'<div id="(sm-viewer-[0-9a-f]+)"', html + sm.animate(scene, sol))
    assert len(ids) == len(set(ids)) == 2  # two viewers on one page do not clash


def test_frames_hold_the_drawn_points_and_trails():
    scene = sm.chain_pendulum(masses=[1.0, 0.5], lengths=[1.0, 0.5])
    sol = _circling(2, 301)
    t, q = np.asarray(sol.ts), np.asarray(sol.ys[0])
    skel = skeleton(scene, 2)
    fig = figure(skel, t, q, frames=40)
    idx = frame_indices(t, 40)
    pts = skel.points(q[idx])
    assert [list(link) for link in skel.links] == [[0, 1, 2]] and list(skel.tips) == [2]
    trail = max(2, round(TRAIL * len(idx)))
    for f in (0, 17, len(idx) - 1):
        np.testing.assert_allclose(_trace(fig, "links", f), pts[f, [0, 1, 2]], rtol=0, atol=1e-12)
        np.testing.assert_allclose(_trace(fig, "tips", f), pts[f, [2]], rtol=0, atol=1e-12)
        recent = pts[max(0, f - trail) : f + 1, 2]
        np.testing.assert_allclose(_trace(fig, "trail", f), recent, rtol=0, atol=1e-5)
    assert len(_trace(fig, "trail", 17)) == trail + 1
    pivot = fig["data"][[trace["name"] for trace in fig["data"]].index("pivot")]
    assert [pivot[k] for k in "xyz"] == [[0.0], [0.0], [0.0]]
    ranges = np.array([fig["layout"]["scene"][f"{k}axis"]["range"] for k in "xyz"])
    assert np.allclose(np.diff(ranges, axis=1), ranges[0, 1] - ranges[0, 0])  # equal aspect
    assert np.all(ranges[:, :1] <= pts.min(axis=(0, 1))[:, None])
    assert np.all(ranges[:, 1:] >= pts.max(axis=(0, 1))[:, None])


def test_a_rigid_base_draws_its_arms():
    quad = sm.Scene(
        sm.RigidBase(0.5, [5.57e-3, 5.57e-3, 1.05e-2], attach=[0.0, 0.0, -0.05]),
        sm.Chain(0.02, 0.2, links=2),
        sm.Gravity(),
    )
    skel = skeleton(quad, quad.n)
    assert len(skel.frame) == 3  # +-e1, +-e2, e3
    p = 1 + max(int(np.max(line)) for line in skel.links + skel.frame)
    x = np.random.default_rng(1).normal(size=(5, p, 3))
    fig = figure(skel, np.arange(5.0), x)
    body = _trace(fig, "body", 3)
    gap = np.isnan(body[:, 0])
    lines = np.split(body[~gap], np.cumsum([len(line) for line in skel.frame])[:-1])
    for line, drawn in zip(skel.frame, lines, strict=True):
        np.testing.assert_allclose(drawn, skel.points(x[3])[line], rtol=0, atol=1e-12)
    assert gap.sum() == 2 and "base" in [trace["name"] for trace in fig["data"]]
    assert "rotors" not in [trace["name"] for trace in fig["data"]]  # a body without Rotors
    flown = sm.Scene(*quad.effects, sm.Rotors(jnp.array([6.0, 0.0, 0.0, 0.0]), 0.17, 0.0135))
    skel = skeleton(flown, flown.n)
    fig = figure(skel, np.arange(5.0), x)
    ends = [line[k] for line in skel.frame[:2] for k in (0, -1)]  # +-e1, +-e2
    assert list(skel.rotors) == ends
    np.testing.assert_allclose(_trace(fig, "rotors", 3), skel.points(x[3])[ends], atol=1e-12)


def test_animate_any_system_draws_points_on_the_unit_sphere():
    system = sm.Lagrangian(lambda t, q, qdot, args: 0.5 * jnp.sum(qdot**2) - 9.81 * q[0, 2])
    skel = skeleton(system, 1)
    assert skel.links == () and [r for _, r in skel.spheres] == [1.0]
    fig = _figure(sm.animate(system, _circling(1, 40)))
    assert len(fig["frames"]) == 40  # fewer saved states than the bound: all of them
    sphere = fig["data"][[trace["name"] for trace in fig["data"]].index("sphere")]
    r = np.linalg.norm(np.array([sphere[k] for k in "xyz"], dtype=float), axis=0)
    assert np.allclose(r[np.isfinite(r)], 1.0)  # the wireframe of the unit sphere


def test_skeleton_of_scenes():
    beads = sm.Scene(
        sm.SharedSphere(1.0, radius=2.0, count=3),
        sm.Particles(1.0, 0.5, count=2),
        sm.Chain(1.0, 1.0, links=2, base=(0.0, 0.0, 1.0)),
    )
    skel = skeleton(beads, beads.n)
    np.testing.assert_allclose(skel.anchors, [[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], atol=0)
    assert [list(link) for link in skel.links] == [[0, 5], [0, 6], [1, 7, 8]]
    assert list(skel.free) == [0, 1, 2] and float(skel.spheres[0][1]) == 2.0
    assert list(skel.tips) == [5, 6, 8, 2, 3, 4]
    drone = sm.Scene(sm.Base(1.5), sm.Chain(0.02, 0.2, links=3))  # points(q): base first
    skel = skeleton(drone, drone.n + 1)
    assert skel.anchors.shape == (0, 3) and [list(link) for link in skel.links] == [[0, 1, 2, 3]]
    assert list(skel.bases) == [0] and list(skel.tips) == [3] and skel.mass(3) == 2


def test_animate_rejects_a_single_state_and_bad_frames():
    scene = sm.chain_pendulum(masses=[1.0], lengths=[1.0])
    one = _circling(1, 1)
    with pytest.raises(ValueError, match="sol: expected states at two times or more"):
        sm.animate(scene, one)
    with pytest.raises(ValueError, match=r"^frames must be an integer >= 2, got 1\.$"):
        sm.animate(scene, _circling(1, 5), frames=1)
    flat = types.SimpleNamespace(ts=jnp.zeros(3), ys=(jnp.zeros((3, 3)), jnp.zeros((3, 3))))
    with pytest.raises(ValueError, match=r"q \(T, n, 3\)"):
        sm.animate(scene, flat)


def _labels(fig: dict) -> list[str]:
    return [step["label"] for step in fig["layout"]["sliders"][0]["steps"]]


def test_a_backward_run_is_animated_like_a_forward_one():
    scene = sm.chain_pendulum(masses=[1.0], lengths=[1.0])
    forward = _circling(1, 301)
    backward = types.SimpleNamespace(ts=-forward.ts, ys=forward.ys)  # from t0 = 0 to t1 = -2
    assert len(_figure(sm.animate(scene, backward))["frames"]) == MAX_FRAMES
    ahead, back = (_figure(sm.animate(scene, sol, frames=30)) for sol in (forward, backward))
    assert len(back["frames"]) == 30 and back["frames"] == ahead["frames"]  # t0 first, t1 last
    assert back["layout"]["updatemenus"] == ahead["layout"]["updatemenus"]  # the same pace
    assert _labels(back) == [s if s == "0.00" else f"-{s}" for s in _labels(ahead)]  # no -0.00
    skel, x = skeleton(scene, 1), np.asarray(forward.ys[0][:4])
    few = figure(skel, np.array([0.0, -2e-4, -4e-4, -6e-4]), x)
    assert _labels(few) == ["0.0000", "-0.0002", "-0.0004", "-0.0006"]
    rounded = figure(skel, np.array([0.3, 0.2, 0.1, 0.3 - 0.1 - 0.1 - 0.1]), x)  # last: -3e-17
    assert _labels(rounded) == ["0.3", "0.2", "0.1", "0.0"]


def test_animate_refuses_what_it_cannot_draw():
    t = np.linspace(0.0, 1.0, 5)
    solution = lambda q: types.SimpleNamespace(
        ts=jnp.asarray(t), ys=(q, jax.tree.map(jnp.zeros_like, q))
    )
    down = jnp.tile(jnp.array([0.0, 0.0, -1.0]), (5, 1, 1))
    space = {"cart": sm.Euclidean(1), "p": sm.Spheres(1)}
    cart = sm.Lagrangian(lambda t, q, qdot, args: 0.5 * jnp.sum(qdot["p"] ** 2), space=space)
    drawn = r"^system_or_scene: animate draws a Scene or the points of a system on Spheres, "
    drawn += "got a system on "
    with pytest.raises(ValueError, match=drawn + r"Product\(factors=\{'cart': Euclidean"):
        sm.animate(cart, solution({"cart": jnp.zeros((5, 1)), "p": down}))
    body = sm.Lagrangian(lambda t, q, qdot, args: 0.0, space=sm.Rotations(1))
    with pytest.raises(ValueError, match=drawn + r"Rotations\(k=1"):
        sm.animate(body, solution(jnp.tile(jnp.eye(3), (5, 1, 1, 1))))
    one = sm.Lagrangian(lambda t, q, qdot, args: 0.0, space=sm.Spheres(1))
    two = jnp.concatenate([down, down], axis=1)
    for system in (one, sm.chain_pendulum(masses=[1.0], lengths=[1.0])):
        with pytest.raises(ValueError, match=r"the state has 2 spheres but the system has 1"):
            sm.animate(system, solution(two))
    assert len(_figure(sm.animate(one, solution(down)))["frames"]) == 5


def test_frame_indices_are_bounded_and_keep_both_ends():
    t = np.sort(np.random.default_rng(0).uniform(0, 5, 1000))
    idx = frame_indices(t, 150)
    assert len(idx) <= 150 and idx[0] == 0 and idx[-1] == 999 and np.all(np.diff(idx) > 0)
    gaps = np.diff(t[idx])
    assert gaps.max() < 3 * (t[-1] - t[0]) / 149  # roughly even in time


def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if path := shutil.which(name):
            return path
    if os.environ.get("SPHERE_MECH_REQUIRE_CHROMIUM"):
        pytest.fail("SPHERE_MECH_REQUIRE_CHROMIUM is set (CI) but no chromium binary is on PATH")
    pytest.skip("no chromium binary on PATH (.ci/run installs Debian's chromium)")


def _browse(browser: str, page: Path, *args: str) -> str:
    """Chromium's output on `page`; WebGL drawn by SwiftShader (on the CPU, no GPU)."""
    flags = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
    flags += ["--hide-scrollbars", "--virtual-time-budget=60000", "--window-size=720,720"]
    # A budget of virtual time, not of wall time: idle virtual time is skipped, so 60 s of
    # it costs 6 s alone and 14 s beside four busy processes. Chromium 156 hangs instead of
    # exiting when the budget runs out before the page has drawn: 1 s hung even when idle,
    # and 5 s hung beside three busy processes (CI's failure).
    run = subprocess.run([browser, *flags, *args, page.as_uri()], capture_output=True, timeout=300)
    assert run.returncode == 0, run.stderr.decode()[-2000:]
    return run.stdout.decode()


def test_animation_html_in_headless_chromium(tmp_path):
    import matplotlib.image

    browser = _chromium()
    out = tmp_path / "out"
    args = ["run", str(EXAMPLES / "double_pendulum.toml"), "--out", str(out), "--t1", "2"]
    assert main([*args, "--no-progress"]) == 0
    path = out / "animation.html"
    html = path.read_text()
    assert html.startswith("<!DOCTYPE html>")
    _offline(html)
    _controls(_figure(html))
    shot = tmp_path / "shot.png"
    dom = _browse(browser, path, f"--screenshot={shot}", "--dump-dom")
    pixels = matplotlib.image.imread(shot)[..., :3]
    assert pixels.shape[:2] == (720, 720)
    assert pixels.std() > 0.05  # not blank: a white page has 0
    assert np.mean(np.all(pixels < 0.3, axis=-1)) > 1e-3  # dark ink: links, labels, buttons
    assert "WebGL is not supported" not in dom
    assert dom.count('class="gl-container"') == 1 and "<canvas" in dom  # the 3-D scene
    assert re.search(r'class="slider-label"[^>]*>t = 0\.0* s<', dom)
    assert '<text class="updatemenu-item-text"' in dom and ">Play<" in dom
    two = tmp_path / "two.html"  # two viewers on a page: plotly.js unpacked once, both drawn
    scene = sm.chain_pendulum(masses=[1.0], lengths=[1.0])
    two.write_text(page("".join(sm.animate(scene, _circling(1, 30)) for _ in range(2)), "two"))
    assert _browse(browser, two, "--dump-dom").count('class="gl-container"') == 2
