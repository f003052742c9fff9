"""`sm.animate` and `animation.html`: one player for scenes and for any system, a bounded
number of frames, no network, and (where a chromium binary exists) the page rendered in a
real headless browser: not blank, controls present, the script ran."""

import json
import os
import re
import shutil
import subprocess
import types
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import sphere_mech as sm
from sphere_mech._animation import MAX_FRAMES, frame_indices
from sphere_mech._cli import main
from sphere_mech._drawing import skeleton

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _frames(html: str) -> list:
    return json.loads(re.search(r"var frames = (\[.*?\]), times", html).group(1))


def _circling(n: int, steps: int):
    """A solution-like object: `n` points turning about the vertical, 45 deg below it."""
    t = np.linspace(0.0, 2.0, steps)
    phase = np.pi * t[:, None] + np.arange(n)
    q = np.stack([np.cos(phase), np.sin(phase), -np.ones_like(phase)], axis=-1) / np.sqrt(2)
    return types.SimpleNamespace(ts=jnp.asarray(t), ys=(jnp.asarray(q), jnp.zeros_like(q)))


def _controls(html: str) -> None:
    for action in ("play", "pause", "first", "previous", "next", "last"):
        assert f'data-action="{action}"' in html
    assert 'type="range"' in html


def test_animate_a_scene():
    scene = sm.chain_pendulum(masses=[1.0, 0.5], lengths=[1.0, 0.5])
    html = sm.animate(scene, _circling(2, 301))
    assert isinstance(html, str) and html._repr_html_() == str(html)
    assert "MB of HTML" in repr(html)  # not the whole page
    _controls(html)
    assert len(_frames(html)) == MAX_FRAMES == 150
    assert "://" not in html  # embedded frames and icons: no network
    assert len(_frames(sm.animate(scene, _circling(2, 301), frames=20))) == 20


def test_animate_any_system_draws_points_on_the_unit_sphere():
    system = sm.Lagrangian(lambda t, q, qdot, args: 0.5 * jnp.sum(qdot**2) - 9.81 * q[0, 2])
    skel = skeleton(system, 1)
    assert skel.links == () and [r for _, r in skel.spheres] == [1.0]
    html = sm.animate(system, _circling(1, 40))
    assert len(_frames(html)) == 40  # fewer saved states than the bound: all of them


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
    with pytest.raises(ValueError, match="frames: expected an integer >= 2"):
        sm.animate(scene, _circling(1, 5), frames=1)
    flat = types.SimpleNamespace(ts=jnp.zeros(3), ys=(jnp.zeros((3, 3)), jnp.zeros((3, 3))))
    with pytest.raises(ValueError, match=r"q \(T, n, 3\)"):
        sm.animate(scene, flat)


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


def test_animation_html_in_headless_chromium(tmp_path):
    import matplotlib.image

    browser = _chromium()
    out = tmp_path / "out"
    assert (
        main(
            [
                "run",
                str(EXAMPLES / "double_pendulum.toml"),
                "--out",
                str(out),
                "--t1",
                "2",
                "--no-progress",
            ]
        )
        == 0
    )
    page = out / "animation.html"
    html = page.read_text()
    assert html.startswith("<!DOCTYPE html>") and "://" not in html
    _controls(html)
    flags = [
        browser,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--hide-scrollbars",
        "--virtual-time-budget=3000",
        "--window-size=640,640",
    ]
    shot = tmp_path / "shot.png"
    subprocess.run(
        flags + [f"--screenshot={shot}", page.as_uri()],
        capture_output=True,
        timeout=120,
        check=True,
    )
    pixels = matplotlib.image.imread(shot)[..., :3]
    assert pixels.shape[:2] == (640, 640)
    assert pixels.std() > 0.05  # not blank: a white page has 0
    assert np.mean(np.all(pixels < 0.3, axis=-1)) > 1e-3  # dark ink: axes, links, buttons
    dom = subprocess.run(
        flags + ["--dump-dom", page.as_uri()],
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    _controls(dom)
    assert re.search(r"t = 0\.0* s</span>", dom)  # the script ran: the first frame's time
    assert re.search(r'class="sm-frame"[^>]*src="data:image/png;base64,', dom)
