"""The command line: `sphere-mech run [SCENE.toml] [--out DIR]`.

Runs a scene file (default: a double spherical pendulum, 20 s) and writes `trajectory.npz`,
`summary.json`, `plot.png` and `animation.html`; exit status 2 for a problem in the file or
`--out`, 1 for a failed run, 130/143 on SIGINT/SIGTERM. Compiled programs are kept in JAX's
persistent compilation cache (`cache_dir`). See docs/getting-started.md."""

import argparse
import contextlib
import json
import math
import os
import re
import shutil
import signal
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

# JAX is imported where it is used, after `main` has taken over SIGINT and SIGTERM: Ctrl-C
# during its import (a second or more) is then one line and status 130, not a traceback.
PROG = "sphere-mech"
DEFAULT_SCENE = Path(__file__).resolve().parents[1] / "scenes" / "default.toml"


CACHE_ENV = "SPHERE_MECH_CACHE_DIR"
TEMP_PREFIX = ".sphere-mech-"  # a run completes its files in `.sphere-mech-<pid>-<random>`
_TEMP_NAME = re.compile(re.escape(TEMP_PREFIX) + r"(\d+)-[A-Za-z0-9_]+")  # mkdtemp's names
STALE_AFTER_S = 24 * 3600  # such a folder, its process gone or older than this: removed
_WRITING: set[Path] = set()  # this process's temporary folders, removed on a signal
_REPLACING = threading.Lock()  # held while a run's files move into place: a signal waits
_WRITTEN = threading.Event()  # set once they have


def cache_dir() -> Path | None:
    """The compilation cache's folder: `$SPHERE_MECH_CACHE_DIR` (`off`: `None`), else the user's."""
    env = os.environ.get(CACHE_ENV)
    if env is not None:
        return None if env.strip().lower() in ("", "off", "0", "no") else Path(env)
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local"))
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "sphere_mech" / "jax"


def enable_compilation_cache(folder: Path) -> None:
    """Keep every compiled program in JAX's persistent cache under `folder` (call first)."""
    import jax

    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)


class CommandError(Exception):
    """A problem with an argument or output: one line naming the option, and the exit status."""

    def __init__(self, message: str, status: int = 2):
        super().__init__(message)
        self.status = status


def check_out(out: Path) -> None:
    """Create `out` and write a file in it before integrating, else raise `CommandError`."""
    try:
        _probe(out)
        remove_stale(out)
    except OSError as e:
        raise CommandError(f"--out: cannot create or write the folder {out} ({e})") from None


def _probe(folder: Path) -> None:
    """Create `folder` and write a file in it (raises `OSError`)."""
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryFile(dir=folder, prefix=".sphere-mech-probe-") as f:
        f.write(bytes(65536))  # a full disk fails here
        f.flush()
        os.fsync(f.fileno())


def usable_cache(folder: Path) -> bool:
    """Whether the compilation cache can live in `folder`; if not, one line naming
    `$SPHERE_MECH_CACHE_DIR` (before: JAX warned once per program, naming neither)."""
    try:
        _probe(folder)
        return True
    except OSError as e:
        print(
            f"{PROG}: compilation cache off: cannot create or write the folder {folder} ({e}); "
            f"set ${CACHE_ENV} to another folder or 'off'",
            file=sys.stderr,
        )
        return False


CACHE_READ_ERROR = "Error reading persistent compilation cache entry"  # JAX's warning


@contextlib.contextmanager
def repairing_cache(folder: Path | None):
    """Run with JAX's warnings about unreadable entries of the cache in `folder` caught;
    after the run, if there were any, remove the cache's entries and say so in one line.
    JAX compiles such a program again but never rewrites its entry: before, every later
    run printed dozens of warnings and compiled those programs again."""
    damaged = []
    with warnings.catch_warnings():
        warnings.filterwarnings("always", message=CACHE_READ_ERROR)
        show = warnings.showwarning

        def sort(message, *args, **kwargs):
            if str(message).startswith(CACHE_READ_ERROR):
                damaged.append(message)
            else:
                show(message, *args, **kwargs)

        warnings.showwarning = sort
        try:
            yield
        finally:
            if damaged and folder is not None:
                entries = [p for p in folder.glob("*-cache") if p.is_file()]
                for path in entries + list(folder.glob("*-atime")):
                    path.unlink(missing_ok=True)
                n = len(set(map(str, damaged)))
                print(
                    f"{PROG}: {n} program{'s' * (n != 1)} could not be read from the compilation "
                    f"cache {folder} (damaged entries): its {len(entries)} entries were removed, "
                    "and the next run compiles and stores them again",
                    file=sys.stderr,
                )


def remove_stale(out: Path) -> None:
    """Remove the temporary folders of killed runs in `out` (process gone, or stale): only
    names `mkdtemp` gives them (`.sphere-mech-<pid>-<random>`), not a user's folder that
    happens to start with the prefix (before: any, e.g. `.sphere-mech-notes`, was removed)."""
    now = time.time()
    for folder in out.glob(f"{TEMP_PREFIX}*"):
        match = _TEMP_NAME.fullmatch(folder.name)
        try:
            old = now - folder.stat().st_mtime > STALE_AFTER_S
        except OSError:  # removed meanwhile
            continue
        if match and folder.is_dir() and (old or not _alive(int(match[1]))):
            shutil.rmtree(folder, ignore_errors=True)


def _alive(pid: int) -> bool:
    """Whether a process `pid` exists (on this machine)."""
    if pid != os.getpid():
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        except OSError:  # another user's, or no way to tell: keep it
            pass
    return True


def output_names(animation: bool = True) -> tuple[str, ...]:
    """The files a run writes."""
    return ("trajectory.npz", "summary.json", "plot.png") + (("animation.html",) * animation)


def write_outputs(out: Path, result, scene, *, animation: bool = True) -> None:
    """Write the result files to `out`, each under a temporary name first."""
    import numpy as np

    from .._animation import page, player
    from .._drawing import skeleton
    from .._program import flat
    from .figures import plot

    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out, prefix=f"{TEMP_PREFIX}{os.getpid()}-"))
    _WRITING.add(tmp)
    try:
        states = {**flat("q", result.q), **flat("v", result.v)}
        arrays = dict(x=result.x, energy=result.energy, error_t=result.error_t, error=result.error)
        np.savez(tmp / "trajectory.npz", t=result.t, **states, **arrays)
        summary = json.dumps(result.summary, indent=2, allow_nan=False)
        (tmp / "summary.json").write_text(summary + "\n")
        plot(tmp / "plot.png", result, scene)
        if animation:
            name = result.summary["scene"]
            html = player(skeleton(scene, result.x.shape[1]), result.t, result.x, title=name)
            (tmp / "animation.html").write_text(page(html, name), encoding="utf-8")
        with _REPLACING:  # all of one run's files or all of the last's, never some of each
            for name in output_names(animation):
                os.replace(tmp / name, out / name)
            if not animation:  # the folder describes one run
                (out / "animation.html").unlink(missing_ok=True)
            _WRITTEN.set()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        _WRITING.discard(tmp)


def _print_summary(s: dict, out: Path, animation: bool) -> None:
    e = lambda x: "null" if x is None else f"{x:.1e}"
    if "max_relative_energy_error" in s:
        energy = f"max relative energy error {e(s['max_relative_energy_error'])}"
    else:
        energy = f"max work-energy balance {e(s['max_relative_work_energy_balance'])} (relative)"
    if "not_computed" in s:
        energy += f" (not computed: {', '.join(s['not_computed'])})"
    print(
        f"{s['scene']}: {s['t1']:g} s, {s['solver']}, {s['steps']} steps in "
        f"{s['wall_time_s']:.2f} s; max constraint error {e(s['max_constraint_error'])}; {energy}"
    )
    print(f"wrote {out}/" + ", ".join(output_names(animation)))


def run(scene=None, out=Path("sphere_mech_out"), *, t1=None, progress=True, animation=True):
    """Run a scene file (default: the packaged one), optionally up to `t1`; returns the summary."""
    import jax

    from .._report import run_scene
    from .._scene_files import load_scene

    jax.config.update("jax_enable_x64", True)
    spec = load_scene(DEFAULT_SCENE if scene is None else Path(scene), t1)
    check_out(Path(out))
    result = run_scene(spec, t1=t1, progress=progress)
    try:
        write_outputs(Path(out), result, spec.scene, animation=animation)
    except OSError as e:
        raise CommandError(f"--out: could not write the results to {out} ({e})", 1) from None
    return result.summary


def _fail(message: str, status: int) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return status


_SIGNALS = {signal.SIGINT: "interrupted", signal.SIGTERM: "terminated"}


def _stop(signum: int) -> None:
    """Remove this run's temporary folders, print one line and exit `128 + signum` at once
    (once the files being moved into place, if any, all are)."""
    _REPLACING.acquire()
    for folder in list(_WRITING):
        shutil.rmtree(folder, ignore_errors=True)
    outputs = "this run's outputs written" if _WRITTEN.is_set() else "earlier outputs kept"
    os.write(2, f"\n{PROG}: {_SIGNALS[signum]}; {outputs}\n".encode())
    os._exit(128 + signum)


def _on_signals():
    """Call `_stop` on SIGINT or SIGTERM from a thread woken by `signal.set_wakeup_fd` (so even
    amid a compilation); returns a function that restores the previous handlers."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    read, write = os.pipe()
    os.set_blocking(write, False)
    previous = {s: signal.signal(s, lambda *_: None) for s in _SIGNALS}
    wakeup = signal.set_wakeup_fd(write, warn_on_full_buffer=False)

    def watch():
        while (byte := os.read(read, 1)) and byte[0] != 0:  # 0: restored
            if byte[0] in _SIGNALS:
                _stop(byte[0])
        os.close(read)

    threading.Thread(target=watch, daemon=True).start()

    def restore():
        signal.set_wakeup_fd(wakeup)
        for s, handler in previous.items():
            signal.signal(s, handler)
        os.write(write, b"\0")
        os.close(write)

    return restore


def console_main(argv=None) -> int:
    """The `sphere-mech` program: in a fresh process (equinox not yet imported) its
    compiled programs check nothing at run time (`EQX_ON_ERROR=nan` unless set), so that
    JAX's persistent cache can store them (a run-time check calls back to Python); then
    `main`. `main` called from Python leaves equinox's checks as they are (before, it set
    that variable too, and the rest of the process lost its run-time errors)."""
    if "equinox" not in sys.modules:
        os.environ.setdefault("EQX_ON_ERROR", "nan")
    return main(argv)


def main(argv=None) -> int:
    """The command line (see the module's docstring); returns the exit status. Programs
    compiled here keep equinox's run-time checks unless `console_main` runs it."""
    _WRITTEN.clear()
    restore = _on_signals()
    try:
        return _main(argv)
    finally:
        restore()


def _main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_run = sub.add_parser("run", help="simulate a scene file and write results")
    scene_help = "a scene file (.toml); default: the packaged double spherical pendulum"
    p_run.add_argument("scene", nargs="?", help=scene_help)
    out_help = "output folder (default ./sphere_mech_out)"
    p_run.add_argument("--out", type=Path, default=Path("sphere_mech_out"), help=out_help)
    p_run.add_argument("--t1", type=float, help="override the end time of [simulate] (s)")
    cache_help = "do not read or write the compilation cache (default folder "
    cache_help += f"{cache_dir() or 'off'}; set by ${CACHE_ENV}, 'off' disables it)"
    for flag, text in (
        ("--no-progress", "hide the progress bar"),
        ("--no-animation", "skip animation.html (saves the time to draw its frames)"),
        ("--no-cache", cache_help),
    ):
        p_run.add_argument(flag, action="store_true", help=text)
    ns = parser.parse_args(argv)
    folder = None if ns.no_cache else cache_dir()
    if folder is not None and usable_cache(folder):
        enable_compilation_cache(folder)
    else:
        folder = None
    if ns.t1 is not None and not math.isfinite(ns.t1):  # after t0: checked with the file
        return _fail(f"--t1 must be a finite time in s (got {ns.t1})", 2)
    try:
        with repairing_cache(folder):
            summary = run(
                ns.scene,
                ns.out,
                t1=ns.t1,
                progress=not ns.no_progress,
                animation=not ns.no_animation,
            )
    except CommandError as e:
        return _fail(str(e), e.status)
    except Exception as e:
        from .._scene_files import SceneFileError

        if isinstance(e, SceneFileError):
            return _fail(str(e), 2)
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        return _fail(f"{ns.scene or 'default scene'}: simulation failed: {first}", 1)
    _print_summary(summary, ns.out, not ns.no_animation)
    return 0
