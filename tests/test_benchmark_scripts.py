"""The benchmark scripts import: every name they take from the library, the test helpers
and each other exists (running them takes minutes to hours, so the suite does not)."""

import subprocess
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
PEERS = {"mujoco", "warp"}
"""What `pip install ".[bench]"` adds: a script that imports them is skipped without it."""

IMPORT_ALL = """
import importlib, sys
sys.path.insert(0, sys.argv[1])
for name in sys.argv[2:]:
    sys.argv = [name]  # scripts that parse their options on import see none
    try:
        importlib.import_module(name)
        print("imported", name)
    except ModuleNotFoundError as error:
        print("missing", name, error.name.split(".")[0])
"""


def test_every_benchmark_script_imports():
    names = sorted(path.stem for path in BENCHMARKS.glob("*.py"))
    run = subprocess.run(
        [sys.executable, "-c", IMPORT_ALL, str(BENCHMARKS), *names],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    words = (line.split() for line in run.stdout.splitlines())
    lines = [w for w in words if w[:1] in (["imported"], ["missing"])]
    assert sorted(line[1] for line in lines) == names
    missing = {line[1]: line[2] for line in lines if line[0] == "missing"}
    assert set(missing.values()) <= PEERS, missing
    assert len(missing) < len(names) // 2  # the scripts without a peer did import
