"""`sphere-mech run`: the default scene, scene-file errors (one line, exit status 2),
every example, the figure and the animation, and that a failing run keeps earlier
outputs."""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from helpers import CART_SCENE

import sphere_mech as sm
from sphere_mech._cli import CACHE_ENV, CACHE_READ_ERROR, cache_dir, main
from sphere_mech._cli.figures import figure
from sphere_mech._program import SEGMENTS, build, fixed_steps_taken, segment_times
from sphere_mech._report import run_scene
from sphere_mech._scene_files import SceneFileError, load_scene

EXAMPLES = sorted((Path(__file__).resolve().parents[1] / "examples").glob("*.toml"))
FILES = ("trajectory.npz", "summary.json", "plot.png", "animation.html")

GOOD = """
name = "test pendulum"
[[effects]]
type = "chain"
masses = [1.0, 1.0]
lengths = [1.0, 1.0]
[[effects]]
type = "gravity"
[initial]
polar_deg = [90.0, 120.0]
azimuth_deg = [0.0, 90.0]
[simulate]
solver = "Projected(Tsit5)"
t1 = 0.5
"""


MASSES = "masses = [1.0, 1.0]"
ONE_VALUE = "masses = [1.0, 1.0]\nlengths = [1.0, 1.0]"
STILL = """
name = "still bead"
[[effects]]
type = "particles"
masses = 1.0
radii = 1.0
count = 1
[[effects]]
type = "joint_damping"
coefficient = 0.5
[initial]
polar_deg = 90.0
azimuth_deg = 0.0
[simulate]
t1 = 0.1
"""
"""A forced scene in which nothing moves: energy and work zero throughout."""


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """`sphere-mech run` with no argument, from another directory, default --out."""
    cwd = tmp_path_factory.mktemp("cwd")
    import os

    old = os.getcwd()
    os.chdir(cwd)
    try:
        status = main(["run", "--no-progress"])
    finally:
        os.chdir(old)
    return status, cwd / "sphere_mech_out"


def test_default_run_writes_four_sane_files(default_run):
    status, out = default_run
    assert status == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(FILES)  # no temporary left
    data = np.load(out / "trajectory.npz")
    t, q, v, x = data["t"], data["q"], data["v"], data["x"]
    assert t[0] == 0.0 and t[-1] == pytest.approx(20.0) and len(t) == 2001
    assert q.shape == v.shape == x.shape == (2001, 2, 3)
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-13)
    np.testing.assert_allclose(x[:, 1], q[:, 0] + q[:, 1], atol=1e-13)  # unit lengths
    summary = json.loads((out / "summary.json").read_text())
    assert summary["scene"] == "double spherical pendulum" and summary["t1"] == 20.0
    assert summary["solver"] == "Projected(Tsit5)" and summary["steps"] > 100
    assert summary["wall_time_s"] > 0
    assert summary["max_constraint_error"] < 1e-13
    assert 0 < summary["max_relative_energy_error"] < 1e-5
    energy, scale = data["energy"], summary["energy_scale_J"]
    assert np.max(np.abs(energy - energy[0])) / scale == pytest.approx(
        summary["max_relative_energy_error"]
    )
    png = (out / "plot.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    page = (out / "animation.html").read_text()
    assert page.startswith("<!DOCTYPE html>") and "<title>double spherical pendulum" in page
    assert "://" not in page and "<script src" not in page  # self-contained
    figure = json.loads(page.split('class="sm-figure">', 1)[1].split("</script>", 1)[0])
    assert len(figure["frames"]) == 150  # 2001 saved states, at most 150 frames
    assert [b["label"] for b in figure["layout"]["updatemenus"][0]["buttons"]] == ["Play", "Pause"]
    assert len(page) < 3e6  # plotly.js compressed


def run_cli(scene, out, *options):
    """`sphere-mech run SCENE --out OUT OPTIONS...` in this process: the exit status."""
    return main(["run", str(scene), "--out", str(out), *options])


def _bad(tmp_path, text):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    return path


EDITS = {  # case: (text of GOOD, what replaces it, field, what the error says)
    "unknown effect": ('type = "gravity"', 'type = "magnetism"', "effects[1].type", "effect type"),
    "unknown field": (MASSES, MASSES + "\ncolour = 1", "effects[0].colour", "no such field"),
    "missing field": ("lengths = [1.0, 1.0]\n", "", "effects[0].lengths", "missing"),
    "wrong type": (MASSES, 'masses = "heavy"', "effects[0].masses", "array of numbers"),
    # the effect's own words, as in Python (before: the loader's "expected an integer, got
    # 2.5", and "expected a number ..., got nan" where sm.Gravity(nan) names finiteness)
    "wrong integer": (
        MASSES,
        "masses = 1.0\nlinks = 2.5",
        "effects[0].links",
        "links must be an integer from 1 to 100000, got 2.5",
    ),
    "nan g": (
        'type = "gravity"',
        'type = "gravity"\ng = nan',
        "effects[1].g",
        "g must be finite and at most 1e+100 in magnitude, got nan",
    ),
    "old table": ("[simulate]", "[integrator]", "integrator", "no such field"),
    "old key": ("t1 = 0.5", "duration = 0.5", "simulate.duration", "no such field"),
    "bad solver": ("Projected(Tsit5)", "rk4", "simulate.solver", "spelled as in Python"),
    "syntax": ("t1 = 0.5", "t1 = ", "(syntax)", "valid TOML"),
    "wrong unit": (
        "polar_deg = [90.0, 120.0]",
        "polar_deg = [90.0, 240.0]",
        "initial.polar_deg",
        "degrees",
    ),
    "non-unit direction": (
        "polar_deg = [90.0, 120.0]\nazimuth_deg = [0.0, 90.0]",
        "q = [[1.0, 0.0, 0.0], [1.0, 1.0, 0.0]]",
        "initial.q",
        # simulate's words (before: the file's own check, "unit vectors (length 1 within ...)")
        "q is not on the spheres: some |q_i| differs from 1 by more than 1e-06 (normalize q, "
        "e.g. with sphere_mech.normalize). Got length 1.41421 for q[1].",
    ),
    "not tangent": (  # simulate's check: relative to the largest speed, not each sphere's
        "polar_deg = [90.0, 120.0]\nazimuth_deg = [0.0, 90.0]",
        "q = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]\nqdot = [[0.1, 0.0, 0.0], [0.0, 1.0, 0.0]]",
        "initial.qdot",
        "qdot is not tangent to the spheres: some q_i . qdot_i exceeds 1e-06 (relative)",
    ),
    "negative mass": (
        MASSES,
        "masses = [1.0, -1.0]",
        "effects[0].masses",
        "masses must be > 0 (kg), got [1.0, -1.0]",
    ),
    "negative length": (
        "lengths = [1.0, 1.0]",
        "lengths = [-1.0, 1.0]",
        "effects[0].lengths",
        "> 0",
    ),
    # sizes and ranges: refused where read, before anything is allocated or integrated
    "negative links": (
        ONE_VALUE,
        "masses = 1.0\nlengths = 1.0\nlinks = -2",
        "effects[0].links",
        "links must be an integer from 1 to 100000, got -2",
    ),
    "huge links": (
        ONE_VALUE,
        f"masses = 1.0\nlengths = 1.0\nlinks = {2**63 - 1}",
        "effects[0].links",
        "from 1 to 100000",
    ),
    "1e9 links": (
        ONE_VALUE,
        "masses = 1.0\nlengths = 1.0\nlinks = 1000000000",
        "effects[0].links",
        "from 1 to 100000",
    ),
    "huge mass": (
        MASSES,
        "masses = [1.0, 1e308]",
        "effects[0].masses",
        "masses must be finite and at most 1e+100 in magnitude, got 1e+308",
    ),
    "huge g": (
        'type = "gravity"',
        'type = "gravity"\ng = 1e308',
        "effects[1].g",
        "g must be finite and at most 1e+100",
    ),
    "huge t1": ("t1 = 0.5", "t1 = 1e308", "simulate.t1", "t1 must be at most 1e+100 s"),
    # simulate's own words (sm.simulate(..., t1=True) says the same)
    "boolean t1": ("t1 = 0.5", "t1 = true", "simulate.t1", "t1 must be a real number (got True)"),
    "t1 before t0": ("t1 = 0.5", "t1 = -0.5", "simulate.t1", "expected a time in s after t0"),
    "tiny fixed step": (
        '"Projected(Tsit5)"',
        '"RK4"\ndt0 = 1e-300',
        "simulate.dt0",
        "dt0 must give at most max_steps = 100000 fixed steps",
    ),
    "fixed steps in segments": (  # 5 segments of 0.1 s (200 save intervals), one step each
        '"Projected(Tsit5)"',
        '"Projected(RK4)"\ndt0 = 0.1\nmax_steps = 4',
        "simulate.dt0",
        "dt0 must give at most max_steps = 4 fixed steps from t0 to t1 (got 0.1: 5 steps in "
        "5 segments)",
    ),
    "huge max_steps": (
        "t1 = 0.5",
        "t1 = 0.5\nmax_steps = 100000000000000000000",
        "simulate.max_steps",
        "max_steps must be an integer from 1 to 2147483647 or None",
    ),
    "centers": (
        '[[effects]]\ntype = "chain"\nmasses = [1.0, 1.0]\nlengths = [1.0, 1.0]',
        '[[effects]]\ntype = "particles"\nmasses = 1.0\nradii = 1.0\ncount = 2\n'
        "centers = [1.0, 2.0]",
        "effects[0].centers",
        "centers must be a (3,) or (2, 3) array, got shape (2,)",
    ),
    "deep solver": (
        '"Projected(Tsit5)"',
        '"' + "Projected(" * 3000 + "Tsit5" + ")" * 3000 + '"',
        "simulate.solver",
        "solver must be at most 200 characters",
    ),
}
ADDED = {  # case: (what follows GOOD, field, what the error says)
    "link out of range": (
        '[[effects]]\ntype = "base_torque"\ntorque = [0.0, 0.0, 1.0]\nlink = 7\n',
        "effects[2].link",
        "got 7",
    ),
    "huge gain": (
        '[[effects]]\ntype = "base_torque"\ntorque = { type = "pd_torque", kp = 1e308 }\n',
        "effects[2].torque.kp",
        "kp must be finite and at most 1e+100",
    ),
    "tiny save_dt": (
        "[output]\nsave_dt = 1e-300",
        "output.save_dt",
        "save_dt must give at most 1e+08 saved numbers",
    ),
}
ERRORS = {  # case: (scene file, field, what the error says)
    **{case: (GOOD.replace(old, new), *error) for case, (old, new, *error) in EDITS.items()},
    **{case: (GOOD + added, *error) for case, (added, *error) in ADDED.items()},
    "huge base velocity": (
        CART_SCENE.format(extra="", simulate="").replace("base = [0.0]", "base_velocity = [1e308]"),
        "initial.base_velocity",
        "at most 1e+100 in magnitude",
    ),
}


@pytest.mark.parametrize("case", list(ERRORS))
def test_scene_file_error_is_one_line_exit_2(case, tmp_path, capsys):
    text, field, expected = ERRORS[case]
    path = _bad(tmp_path, text)
    assert run_cli(path, tmp_path / "out") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"sphere-mech: error: {path}: {field}: ")
    assert expected in err
    assert not (tmp_path / "out").exists()


def test_error_from_the_installed_command(tmp_path):
    """The real executable: exit status 2, one line on stderr, no traceback."""
    path = _bad(tmp_path, GOOD.replace('type = "gravity"', 'type = "magnetism"'))
    exe = Path(sys.executable).with_name("sphere-mech")
    proc = subprocess.run(
        [str(exe), "run", str(path)], capture_output=True, text=True, cwd=tmp_path, timeout=120
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert f"{path}: effects[1].type" in proc.stderr


# slow: the examples that a test below runs whole under the same command, with tighter
# checks (drone_cable: 10 s; quadrotor_cable: 32 s, in test_rotorcraft)
WHOLE_RUNS = ("drone_cable", "quadrotor_cable")


@pytest.mark.parametrize(
    "example",
    [pytest.param(p, marks=pytest.mark.slow) if p.stem in WHOLE_RUNS else p for p in EXAMPLES],
    ids=lambda p: p.stem,
)
def test_every_example_runs(example, tmp_path, capsys):
    out = tmp_path / "out"
    assert run_cli(example, out, "--t1", "0.1", "--no-progress") == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["t1"] == 0.1 and summary["max_constraint_error"] < 1e-12
    error = summary.get(
        "max_relative_energy_error", summary.get("max_relative_work_energy_balance")
    )
    assert error < 1e-5
    assert "wrote" in capsys.readouterr().out


def test_drone_flies_the_step_and_its_work_balances(tmp_path):
    """The drone example (a moving base: dict state) over its whole 8 s: the PD controller
    brings the drone to the step target x = 1 m, the work of the controller and the cable's
    damping closes the balance to the tolerances, and the files hold the base."""
    out = tmp_path / "out"
    drone = next(p for p in EXAMPLES if p.stem == "drone_cable")
    assert run_cli(drone, out, "--no-progress", "--no-animation") == 0
    summary = json.loads((out / "summary.json").read_text())
    np.testing.assert_allclose(summary["base"], [1.0, 0.0, 0.0], atol=0.05)  # measured 0.025
    assert summary["max_relative_work_energy_balance"] < 1e-6  # measured 1.2e-8
    assert summary["max_constraint_error"] < 1e-13 and summary["n_spheres"] == 5
    data = np.load(out / "trajectory.npz")
    assert data["q.base"].shape == data["v.base"].shape == (801, 3)
    assert data["q.spheres"].shape == (801, 5, 3) and data["x"].shape == (801, 6, 3)
    np.testing.assert_array_equal(data["x"][:, 0], data["q.base"])  # the base's point first
    assert data["q.base"][-1].tolist() == summary["base"]


def test_failing_runs_keep_previous_outputs(tmp_path, capsys):
    out = tmp_path / "out"
    good = _bad(tmp_path, GOOD)
    assert run_cli(good, out, "--no-progress") == 0
    before = {f: (out / f).read_bytes() for f in FILES}
    # a scene-file error, then a solver failure (too few steps)
    bad = _bad(tmp_path, GOOD.replace("masses = [1.0, 1.0]", "masses = [1.0, -1.0]"))
    assert run_cli(bad, out) == 2
    few = tmp_path / "few.toml"
    few.write_text(GOOD.replace("t1 = 0.5", "t1 = 0.5\nmax_steps = 3"))
    assert run_cli(few, out, "--no-progress") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "simulation failed" in err[-1]
    assert {f: (out / f).read_bytes() for f in FILES} == before
    assert sorted(p.name for p in out.iterdir()) == sorted(FILES)


def test_no_animation(tmp_path, capsys):
    out = tmp_path / "out"
    good = _bad(tmp_path, GOOD)
    assert run_cli(good, out, "--no-progress") == 0
    assert (out / "animation.html").exists()
    assert run_cli(good, out, "--no-progress", "--no-animation") == 0
    assert sorted(p.name for p in out.iterdir()) == sorted(FILES[:3])  # no stale animation
    assert capsys.readouterr().out.splitlines()[-1].endswith("summary.json, plot.png")


CLI = "import sys; from sphere_mech._cli import console_main; sys.exit(console_main())"
CACHE_COUNTS = """import collections, sys
import jax.monitoring
counts = collections.Counter()
jax.monitoring.register_event_listener(lambda event, **kw: counts.update([event]))
from sphere_mech._cli import console_main
status = console_main(sys.argv[1:])
print("cache", counts["/jax/compilation_cache/cache_hits"],
      counts["/jax/compilation_cache/cache_misses"])
sys.exit(status)
"""


def _env(**extra):
    env = {
        **os.environ,
        **extra,
        "PYTHONPATH": os.pathsep.join(
            [str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")]
        ),
    }
    env.pop("EQX_ON_ERROR", None)
    return env


def test_repeated_runs_are_served_by_the_cache_and_never_fail(tmp_path):
    """The fault hunt's sequence (a run, then another end time twice; issue 28 item 1: the
    third failed with "Function ... fusion not found" from a program stored after a cache
    hit), in fresh processes: the third run compiles nothing (JAX's cache hits, no miss)
    and writes the same trajectory; a comment added to the file changes nothing."""
    cache, good = tmp_path / "cache", _bad(tmp_path, GOOD)
    env = _env(**{CACHE_ENV: str(cache)})

    def run(out, *extra):
        argv = [
            sys.executable,
            "-c",
            CACHE_COUNTS,
            "run",
            str(good),
            "--out",
            str(tmp_path / out),
            "--no-progress",
            "--no-animation",
            *extra,
        ]
        proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=300)
        assert proc.returncode == 0, proc.stderr
        hits, misses = proc.stdout.strip().splitlines()[-1].split()[1:]
        return int(hits), int(misses), np.load(tmp_path / out / "trajectory.npz")

    assert run("out0")[1] > 0
    _, misses, first = run("out1", "--t1", "0.4")
    assert misses > 0
    good.write_text("# a comment\n" + GOOD)
    # the third run: all hits, so it stores nothing and a fourth would read the same cache
    hits, misses, again = run("out2", "--t1", "0.4")
    assert hits > 0 and misses == 0
    for name in ("t", "q", "v"):
        np.testing.assert_array_equal(again[name], first[name])


DAMAGED_CACHE = """import sys, warnings
from pathlib import Path
import jax, jax.numpy as jnp
from sphere_mech._cli import enable_compilation_cache, repairing_cache
folder = Path(sys.argv[1])
enable_compilation_cache(folder)
f = jax.jit(lambda x: jnp.sin(x) * 2.0)
f(1.0).block_until_ready()
(folder / "notes.txt").write_text("kept")
for entry in folder.glob("*-cache"):
    entry.write_bytes(b"damaged")
jax.clear_caches()
with repairing_cache(folder):
    print(float(f(1.0)))
    warnings.warn("another warning")
print(sorted(p.name for p in folder.iterdir()))
"""


def test_damaged_cache_entries_are_removed_with_one_line(tmp_path):
    """A damaged entry of the compilation cache (a disk error, an interrupted copy): JAX
    warns, compiles the program again and never rewrites the entry, so every later run
    warned dozens of times and recompiled (8.1 s against 5.3 s on the default scene). Now
    the run's warnings about it become one line and the entries are removed (the next run
    stores them again); other warnings and other files are left alone. A cache folder
    that cannot be written turns the cache off with one line naming the variable."""
    folder = tmp_path / "cache"
    argv = [sys.executable, "-c", DAMAGED_CACHE, str(folder)]
    proc = subprocess.run(argv, capture_output=True, text=True, env=_env(), timeout=120)
    assert proc.returncode == 0, proc.stderr
    value, files = proc.stdout.splitlines()
    assert float(value) == pytest.approx(2 * np.sin(1.0), rel=1e-6) and files == "['notes.txt']"
    err = proc.stderr.splitlines()
    assert "another warning" in proc.stderr and CACHE_READ_ERROR not in proc.stderr
    assert err[-1] == (
        f"sphere-mech: 1 program could not be read from the compilation cache {folder} "
        "(damaged entries): its 1 entries were removed, and the next run compiles and "
        "stores them again"
    )
    afile = tmp_path / "afile"
    afile.write_text("")
    env = _env(**{CACHE_ENV: str(afile)})
    argv = [sys.executable, "-c", CLI, "run", str(tmp_path / "missing.toml")]
    proc = subprocess.run(argv, capture_output=True, text=True, env=env, timeout=120)
    assert proc.stderr.splitlines()[0].startswith(
        f"sphere-mech: compilation cache off: cannot create or write the folder {afile} ("
    )
    assert proc.stderr.splitlines()[0].endswith(
        "set $SPHERE_MECH_CACHE_DIR to another folder or 'off'"
    )


def test_main_from_python_keeps_equinox_checks(tmp_path):
    """`main` called from Python leaves equinox's run-time checks on for the rest of the
    process (before: it set `EQX_ON_ERROR=nan`, and a later `acceleration` off the sphere
    returned NaN instead of raising); the `sphere-mech` program (`console_main`) turns
    them off in its own fresh process, so that its programs can be stored."""
    code = (
        "import os, sys; import sphere_mech._cli as cli; entry = getattr(cli, sys.argv[1]);"
        "status = entry(['run', sys.argv[2], '--out', sys.argv[3]]);"
        "import equinox._config as c; print(status, os.environ.get('EQX_ON_ERROR'), c.EQX_ON_ERROR)"
    )
    missing, out = str(tmp_path / "missing.toml"), str(tmp_path / "out")
    printed = []
    for entry in ("main", "console_main"):
        argv = [sys.executable, "-c", code, entry, missing, out]
        proc = subprocess.run(argv, capture_output=True, text=True, env=_env(), timeout=120)
        printed.append(proc.stdout.split())
    assert printed == [["2", "None", "raise"], ["2", "nan", "nan"]]


def test_sigint_is_one_line_and_status_130(tmp_path):
    """Ctrl-C while compiling or integrating (issue 28 item 7: a traceback, sometimes a
    segfault): one line, exit status 130, no temporary folder left."""
    long = _bad(tmp_path, GOOD.replace("t1 = 0.5", "t1 = 1e5\nmax_steps = 100_000_000"))
    out = tmp_path / "out"
    argv = [
        sys.executable,
        "-c",
        CLI,
        "run",
        str(long),
        "--out",
        str(out),
        "--no-progress",
    ]
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True, env=_env(**{CACHE_ENV: "off"}))
    time.sleep(3)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 130, err
    assert [line for line in err.splitlines() if line] == [
        "sphere-mech: interrupted; earlier outputs kept"
    ]
    assert not list(out.glob(".sphere-mech-*"))


def test_signals_are_taken_over_before_jax_is_imported():
    """`main` takes over SIGINT before anything heavy is imported: importing the command
    line imports no JAX (before: Ctrl-C during JAX's import, a second or more, gave a
    KeyboardInterrupt traceback and status -2; seen in this file's SIGINT test on a loaded
    machine)."""
    code = "import sys, sphere_mech._cli; print(sorted({'jax', 'numpy'} & set(sys.modules)))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=_env())
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_a_signal_waits_for_the_files_moving_into_place(tmp_path, monkeypatch, capfd):
    """The result files move into place under a lock that a signal's exit takes first: a
    run interrupted then leaves all of its files or all of the last run's, never some of
    each (before: trajectory.npz of one run beside summary.json of another), and says
    which."""
    import threading

    import sphere_mech._cli as cli

    exits, locked = [], []
    cli._WRITTEN.clear()
    monkeypatch.setattr(cli.os, "_exit", exits.append)
    real_replace = os.replace
    monkeypatch.setattr(
        cli.os, "replace", lambda a, b: locked.append(cli._REPLACING.locked()) or real_replace(a, b)
    )
    with cli._REPLACING:  # files moving into place
        stop = threading.Thread(target=cli._stop, args=(signal.SIGTERM,))
        stop.start()
        stop.join(0.5)
        assert stop.is_alive() and not exits  # waiting
    stop.join(5)
    assert exits == [128 + signal.SIGTERM]
    cli._REPLACING.release()  # taken by the stopped `_stop`
    result = run_scene(load_scene(_bad(tmp_path, GOOD)))
    cli.write_outputs(tmp_path / "out", result, load_scene(tmp_path / "bad.toml").scene)
    assert locked == [True] * len(FILES)
    cli._stop(signal.SIGTERM)
    cli._REPLACING.release()
    err = [line for line in capfd.readouterr().err.splitlines() if line]
    assert err == [
        "sphere-mech: terminated; earlier outputs kept",
        "sphere-mech: terminated; this run's outputs written",
    ]


def test_stale_temporary_folders_are_removed(tmp_path, capsys):
    """A folder left by a killed run (its pid gone) is removed by the next run; one of a
    live process stays, and so do a user's folders that merely share the prefix (before,
    `.sphere-mech-notes` and `.sphere-mech-1-` were removed)."""
    out = tmp_path / "out"
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    ).stdout.strip()
    stale, live = out / f".sphere-mech-{gone}-abc", out / f".sphere-mech-{os.getppid()}-x"
    users = [
        out / name for name in (".sphere-mech-notes", f".sphere-mech-{gone}-", ".sphere-mech-")
    ]
    for folder in (stale, live, *users):
        folder.mkdir(parents=True)
        (folder / "trajectory.npz").write_bytes(b"partial")
    assert run_cli(_bad(tmp_path, GOOD), out, "--no-progress", "--no-animation") == 0
    assert not stale.exists() and live.exists()
    kept = sorted(p.name for p in out.glob(".sphere-mech-*"))
    assert kept == sorted([live.name, *(p.name for p in users)])


def test_no_cache_writes_nothing(tmp_path, monkeypatch, capsys):
    """`--no-cache` leaves JAX's cache as it was (off for a user; the test suite's own
    folder here, see conftest.py) even where the environment names a folder."""
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    assert cache_dir() == tmp_path / "cache"
    good = _bad(tmp_path, GOOD)
    before = jax.config.jax_compilation_cache_dir
    assert run_cli(good, tmp_path / "out", "--no-progress", "--no-animation", "--no-cache") == 0
    assert not (tmp_path / "cache").exists()
    assert jax.config.jax_compilation_cache_dir == before
    monkeypatch.setenv(CACHE_ENV, "off")
    assert cache_dir() is None


@pytest.fixture(scope="module")
def pendulum_result(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "pendulum.toml"
    path.write_text(GOOD)
    spec = load_scene(path)
    return run_scene(spec), spec.scene


def test_energy_error_is_relative_to_the_energy_scale(pendulum_result, tmp_path):
    """`(E - E(0)) / max(|T| + |V|)`, also for a run that starts at `E(0) = 0` to rounding
    (released at rest level with its pivot); before, divided by `|E(0)| = 1e-16`, it
    reported a relative energy error of 1e6 for a correct run."""
    result, _ = pendulum_result
    kinetic = result.energy - result.potential
    scale = np.max(np.abs(kinetic) + np.abs(result.potential))
    np.testing.assert_allclose(result.error, (result.energy - result.energy[0]) / scale)
    assert result.summary["energy_scale_J"] == pytest.approx(scale)
    path = tmp_path / "level.toml"
    path.write_text(GOOD.replace("[90.0, 120.0]", "[90.0, 90.0]"))
    level = run_scene(load_scene(path))
    assert abs(level.energy[0]) < 1e-14 and level.summary["energy_scale_J"] > 1.0
    assert 0 < level.summary["max_relative_energy_error"] < 1e-6


def test_figure_is_equal_aspect_and_shows_the_constraint_only_above_rounding(pendulum_result):
    import dataclasses

    result, scene = pendulum_result
    fig = figure(result, scene)
    ax3d, *panels = fig.axes
    spans = [np.ptp(lim) for lim in (ax3d.get_xlim(), ax3d.get_ylim(), ax3d.get_zlim())]
    np.testing.assert_allclose(spans, spans[0], rtol=1e-12)
    assert len(panels) == 2  # energy, energy error: the constraint error is a text line
    assert "constraint error" in " ".join(t.get_text() for t in fig.texts)
    labels = panels[0].get_legend_handles_labels()[1]
    assert labels == ["E = T + U", "kinetic T", "potential U"]
    drifting = dataclasses.replace(result, constraint=np.linspace(0, 1e-9, len(result.t)))
    assert len(figure(drifting, scene).axes) == 4  # now a panel
    named = dataclasses.replace(result, summary={**result.summary, "scene": "a $x^$ b"})
    fig = figure(named, scene)
    fig.canvas.draw()  # a title parsed as mathtext would raise here
    assert fig.get_suptitle().startswith("a $x^$ b: ")


def test_segments_cover_the_save_times_once():
    for t1, save_dt in ((20.0, 0.01), (0.5, 0.5 / 1001), (1.0, 0.5)):
        ts, count = segment_times(0.0, t1, save_dt)
        n_out = max(2, round(t1 / save_dt) + 1)
        assert len(ts) <= SEGMENTS and ts[0, 0] == 0.0 and ts[-1, -1] == t1
        rows = enumerate(zip(ts, count, strict=True))
        joined = np.concatenate([row[(k > 0) : c] for k, (row, c) in rows])
        np.testing.assert_array_equal(joined, np.linspace(0.0, t1, n_out))
        np.testing.assert_array_equal(ts[1:, 0], ts[:-1, -1])  # each starts where one ends
        assert np.all(np.diff(ts, axis=1) >= 0)  # padding repeats the end


def test_segmented_run_matches_one_simulate_call(pendulum_result, tmp_path):
    """The stitched segments against one `simulate` call over the whole interval: with
    adaptive steps (they differ at the segment ends) to the tolerances, with fixed steps
    (whole steps per segment) to rounding; in this process equinox's run-time checks call
    back to Python, so the program is not stored."""
    import diffrax

    import sphere_mech as sm

    result, scene = pendulum_result
    spec = load_scene(_bad(tmp_path, GOOD))
    sol = sm.simulate(
        scene, spec.y0, spec.t1, solver=spec.solver, saveat=diffrax.SaveAt(ts=result.t)
    )
    np.testing.assert_allclose(result.q, sol.ys[0], atol=1e-7)  # measured 2e-9
    np.testing.assert_allclose(result.v, sol.ys[1], atol=1e-6)  # measured 8e-8
    # Steps shorter and longer than the save interval: before, a segment (here 0.005 s)
    # shorter than dt0 = 0.02 took steps of its own length (100 of 0.005 s).
    for dt0, save_dt, steps, saves in ((0.005, 0.01, 100, 51), (0.02, 0.005, 25, 101)):
        text = GOOD.replace('"Projected(Tsit5)"', f'"Projected(RK4)"\ndt0 = {dt0}')
        fixed = load_scene(_bad(tmp_path, text + f"[output]\nsave_dt = {save_dt}"))
        run = run_scene(fixed)
        sol = sm.simulate(
            scene,
            fixed.y0,
            fixed.t1,
            solver=fixed.solver,
            dt0=fixed.dt0,
            saveat=diffrax.SaveAt(ts=run.t),
        )
        assert run.summary["steps"] == sol.stats["num_steps"] == steps and len(run.t) == saves
        assert run.summary["max_step"] == pytest.approx(dt0, rel=1e-12)
        np.testing.assert_allclose(run.q, sol.ys[0], atol=1e-13)
        np.testing.assert_allclose(run.v, sol.ys[1], atol=1e-12)
    # No common multiple of dt0 and save_dt within the run: as many equal steps as fit.
    assert fixed_steps_taken(0.0, 1.0, 0.3, 0.07) == (15, pytest.approx(1 / 15), 3)


def test_end_time_must_follow_t0(tmp_path, capsys):
    """`--t1` before the file's `t0` (it integrated backwards) or not finite: exit 2,
    one line naming `--t1`, nothing written."""
    path = _bad(tmp_path, GOOD.replace("t1 = 0.5", "t0 = 10.0\nt1 = 10.5"))
    out = tmp_path / "out"
    assert run_cli(path, out, "--t1", "5") == 2
    assert run_cli(path, out, "--t1", "inf") == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == (
        f"sphere-mech: error: {path}: --t1: --t1 must be a time in s after "
        "t0 = 10 and at most 1e+100 (got 5.0)"
    )
    assert err[1] == "sphere-mech: error: --t1 must be a finite time in s (got inf)"
    assert not out.exists()
    spec = load_scene(path, 12.0)  # the reader applies --t1; save_dt stays the file's
    assert spec.t1 == 12.0 and spec.save_dt == pytest.approx(0.5 / 1000)
    # run_scene's t1: the same check and words (before: it integrated backwards, or NaN
    # raised "cannot convert float NaN to integer"), and the limits of a file's t1
    for t1 in (5.0, float("nan"), True):
        expected = f"{path}: t1: t1 must be a time in s after t0 = 10 and at most 1e+100 (got {t1})"
        with pytest.raises(SceneFileError, match=f"^{re.escape(expected)}$"):
            run_scene(spec, t1=t1)
    with pytest.raises(SceneFileError, match=r"save_dt must give at most 1e\+08 saved numbers"):
        run_scene(spec, t1=1e9)


def test_output_folder_is_checked_before_integrating(tmp_path, capsys):
    """An `--out` that is a file, or under a file: exit 2 naming `--out`, before any
    compilation or integration (nothing printed on stdout)."""
    good, blocker = _bad(tmp_path, GOOD), tmp_path / "file"
    blocker.write_text("not a folder")
    for out in (blocker, blocker / "sub"):
        assert run_cli(good, out, "--no-progress") == 2
        captured = capsys.readouterr()
        assert captured.out == "" and captured.err.count("\n") == 1
        assert captured.err.startswith(
            f"sphere-mech: error: --out: cannot create or write the folder {out} ("
        )
    assert blocker.read_text() == "not a folder"


def test_still_forced_scene_writes_strict_json(tmp_path, capsys):
    """A forced scene in which nothing moves: the relative work-energy balance (0/0) is
    null with its reason, and summary.json is strict JSON (no NaN); so is the relative
    energy error of the same scene unforced."""
    out = tmp_path / "out"
    assert run_cli(_bad(tmp_path, STILL), out, "--no-progress", "--no-animation") == 0
    text = (out / "summary.json").read_text()
    summary = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in summary.json"))
    assert summary["max_relative_work_energy_balance"] is None
    assert summary["balance_scale_J"] == 0.0 and summary["work_done_J"] == 0.0
    assert "no scale" in summary["not_computed"]["max_relative_work_energy_balance"]
    # the tolerances the run used: the file sets none, so simulate's float64 defaults
    assert (summary["rtol"], summary["atol"]) == sm.DEFAULT_TOLERANCES[np.dtype("float64")]
    assert "balance null (relative) (not computed" in capsys.readouterr().out
    # unforced (no damping): the relative energy error is null, with its reason
    free = STILL.replace('[[effects]]\ntype = "joint_damping"\ncoefficient = 0.5\n', "")
    assert free != STILL
    assert run_cli(_bad(tmp_path, free), out, "--no-progress", "--no-animation") == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["max_relative_energy_error"] is None and summary["energy_scale_J"] == 0.0
    assert "energies are zero" in summary["not_computed"]["max_relative_energy_error"]


def test_strict_json_replaces_what_is_not_finite():
    from sphere_mech._report import strict_json

    out = strict_json(
        {"a": 1.0, "b": float("inf"), "c": [0.0, float("nan")], "d": None}, {"d": "why"}
    )
    assert out == {
        "a": 1.0,
        "b": None,
        "c": [0.0, None],
        "d": None,
        "not_computed": {
            "b": "not finite (inf): the run overflowed",
            "c": "not finite (nan): the run overflowed",
            "d": "why",
        },
    }
    json.dumps(out, allow_nan=False)


def test_forced_program_memory_does_not_grow_with_max_steps(tmp_path):
    """The work of the forces is summed during the run (`WithWork`), not saved at every
    step: the compiled segment program's buffers are the same for max_steps = 10^3 and
    10^6 (they were 56 kB and 55 MB), and max_steps = 10^9 runs (it used to hang)."""
    damped = GOOD + '[[effects]]\ntype = "joint_damping"\ncoefficient = 0.1\n'
    sizes = []
    for max_steps in (1000, 10**6, 10**9):
        spec = load_scene(
            _bad(tmp_path, damped.replace("t1 = 0.5", f"t1 = 0.5\nmax_steps = {max_steps}"))
        )
        program, compiled = build(spec)
        memory = compiled.memory_analysis()
        sizes.append((memory.temp_size_in_bytes, memory.output_size_in_bytes))
    assert sizes[0] == sizes[1] == sizes[2] and sum(sizes[0]) < 20_000  # measured 5317
    run = program.integrate()
    assert run.work_index.tolist() == [0, *np.cumsum(program.count - 1)]
    assert run.work[0] == 0.0 and run.work[-1] < 0  # damping takes energy out


@pytest.mark.parametrize("solver", ["Projected(Tsit5)", "Projected(Kvaerno5)", "LieRK4"])
def test_work_summed_during_the_run_matches_the_steps(solver, tmp_path):
    """`WithWork`'s work equals `sm.work_energy_balance` over the same run's saved steps
    (the same corrected trapezoidal rule, summed in the loop instead of afterwards),
    around a wrapped implicit solver too (diffrax's `isinstance` sees through it)."""
    import diffrax

    import sphere_mech as sm
    from sphere_mech._solvers.work import WithWork, work_done

    text = GOOD.replace("Projected(Tsit5)", solver)
    spec = load_scene(
        _bad(
            tmp_path,
            text + '[[effects]]\ntype = "joint_damping"\n'
            'coefficient = 0.3\n[[effects]]\ntype = "tip_force"\n'
            "force = [0.5, 0.0, 1.0]\n",
        )
    )
    saveat = diffrax.SaveAt(t0=True, steps=True, solver_state=True)
    sol = sm.simulate(
        spec.scene, spec.y0, spec.t1, solver=WithWork(spec.solver), saveat=saveat, max_steps=1000
    )
    keep = np.isfinite(np.asarray(sol.ts))
    q, v = (np.asarray(y)[keep] for y in sol.ys)
    _, W, balance = sm.work_energy_balance(spec.scene, np.asarray(sol.ts)[keep], q, v)
    assert abs(W[-1]) > 0.1
    np.testing.assert_allclose(work_done(sol.solver_state), W[-1], rtol=1e-12)
    assert np.max(np.abs(balance)) < 1e-5  # J; measured 1.0e-6 (Tsit5)
