"""How the test suite compiles, for every process it starts: the tests themselves, the
notebooks' kernels (nbmake) and the command line's subprocesses inherit this environment.

Most of the suite's time is XLA compiling programs that then run for milliseconds, so the
suite compiles them with few optimizations (`JAX_DISABLE_MOST_OPTIMIZATIONS`: 16-20 % less
CPU time in the heaviest test files; notebook 08 200 s instead of 228 s, notebook 07 88 s
instead of 113 s) and with XLA's older CPU code generator
(`--xla_cpu_use_fusion_emitters=false`: compilation 13-25 % shorter in the four-forms and
fit tests, measured on jaxlib 0.10.2 on a 2-core CPU). XLA aborts on a flag it does not
know, so that flag is set only for the jaxlib minor version it was measured on. The
suite's tolerances hold under both (491 passed); users' programs compile with JAX's
defaults (and the benchmarks measure those). Measured again on 2026-12-04 (an AMD EPYC
2-core machine): with both, the whole suite in 946 s and 1129 s (two runs); without the
first, 55 % of it after 16 minutes, though notebook 09 alone, which runs more than it
compiles, takes 63 s without it against 93 s with it.

The processes of one run share JAX's persistent compilation cache in a fresh temporary
folder (made by the first process, inherited through the environment, removed at the
end): a program another process already compiled (the two workers, the notebooks'
kernels and the command line's subprocesses compile many of the same ones) is read back
instead of compiled again. It held 5062 of 9450 compilations in the two workers alone,
and the suite took 954 to 1159 s against 1334 s without it (jaxlib 0.10.2, 2-core CPU).
The command line's runs use that folder too (`SPHERE_MECH_CACHE_DIR`), not the user's.
A `JAX_COMPILATION_CACHE_DIR` already set is used as it is.

Which file runs when: with `--dist loadfile` each file is one unit of work, and a worker
that finishes early idles while the other runs what is left. The files are therefore
handed out longest first, from the seconds each took when last measured
(`tests/durations.json`; a file not in it goes first). `--store-durations` writes the
seconds of the files a run ran back into that file."""

import atexit
import json
import math
import os
import shutil
import tempfile
from collections import Counter
from importlib.metadata import version
from pathlib import Path

os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
if version("jaxlib").split(".")[:2] == ["0", "10"]:
    flags = os.environ.get("XLA_FLAGS", "")
    os.environ["XLA_FLAGS"] = f"{flags} --xla_cpu_use_fusion_emitters=false".strip()

if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="sphere-mech-suite-jax-")
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)  # by the process that made it
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    os.environ.setdefault("SPHERE_MECH_CACHE_DIR", _cache)  # the command line's, not ~/.cache

DURATIONS = Path(__file__).parent / "tests" / "durations.json"
_seconds = Counter()  # per file, this run (on xdist's controller: every worker's reports)


def _file(nodeid: str) -> str:
    return nodeid.split("::")[0]


def pytest_addoption(parser):
    parser.addoption(
        "--store-durations",
        action="store_true",
        help=f"write each file's seconds in this run to {DURATIONS.name} (the order files run in)",
    )


def pytest_collection_modifyitems(config, items):
    seconds = json.loads(DURATIONS.read_text()) if DURATIONS.exists() else {}
    items.sort(key=lambda item: -seconds.get(_file(item.nodeid), math.inf))  # stable


def pytest_runtest_logreport(report):
    _seconds[_file(report.nodeid)] += report.duration


def pytest_sessionfinish(session):
    if session.config.getoption("store_durations") and "PYTEST_XDIST_WORKER" not in os.environ:
        seconds = json.loads(DURATIONS.read_text()) if DURATIONS.exists() else {}
        seconds.update({name: round(s, 1) for name, s in _seconds.items()})
        ranked = dict(sorted(seconds.items(), key=lambda item: -item[1]))
        DURATIONS.write_text(json.dumps(ranked, indent=1) + "\n")
