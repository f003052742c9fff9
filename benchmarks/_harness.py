"""What every benchmark shares, written once: timing under a trace guard, markdown tables,
figures and the machine's description.

`timing(fn)` / `timings(fns)` time the first call apart (trace, compile, one run), then
repeat the call and report the median and the minimum; during the repeats `no_retrace`
makes any further compilation by JAX (a function traced again into a new program) an
error. It listens to JAX's public `jax.monitoring` events, so it also sees the programs
that `sm.simulate` and `sm.simulate_batch` compile inside (no cache's private size).
JAX is imported on first use, so the MuJoCo comparisons can set its environment
(`_options`) first."""

import math
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)
"""The `jax.monitoring` duration events JAX records when it lowers and compiles a traced
program (not for a trace alone, such as `eqx.filter_eval_shape`'s in `sm.fit`)."""


class no_retrace:
    """`with no_retrace("what"):` raises `AssertionError` on leaving when JAX compiled
    anything inside (the names of the functions compiled are in the message)."""

    _events_checked = False

    def __init__(self, what="the timed function"):
        self.what, self.compiled = what, []
        self._listener = self._listen  # one bound method, to unregister the same

    def _listen(self, event, duration, **kwargs):
        if event in COMPILE_EVENTS:
            self.compiled.append(str(kwargs.get("fun_name", "?")))

    def __enter__(self):
        import jax

        if not no_retrace._events_checked:  # JAX still records the events we listen to
            no_retrace._events_checked = True
            probe = no_retrace("a new jax.jit")
            try:
                with probe:
                    jax.jit(lambda x: x + 1)(0.0)
            except AssertionError:
                pass
            if not probe.compiled:
                raise RuntimeError(f"jax.monitoring reported none of {COMPILE_EVENTS}")
        jax.monitoring.register_event_duration_secs_listener(self._listener)
        return self

    def __exit__(self, *exc):
        import jax

        jax.monitoring.unregister_event_duration_listener(self._listener)
        if self.compiled and exc[0] is None:
            names = ", ".join(sorted(set(self.compiled)))
            raise AssertionError(f"{self.what} compiled again ({names})")


class Timing(NamedTuple):
    first: float  # seconds of the first call (or of `warmup`): trace, compile, one run
    median: float  # seconds, median of the repeats
    min: float  # seconds, fastest repeat
    times: tuple  # every repeat
    result: Any  # what the last call returned

    @property
    def compile(self):
        """The first call's time less a repeat's (median): tracing and compiling."""
        return max(self.first - self.median, 0.0)


def timed_call(fn):
    """`(seconds, result)` of `fn()`, its result waited for (`jax.block_until_ready`)."""
    import jax

    start = time.perf_counter()
    result = jax.block_until_ready(fn())
    return time.perf_counter() - start, result


def timing(
    fn, repeats=5, *, warmup=None, slow=math.inf, budget=math.inf, fast=0.0, most=None, what=None
):
    """`Timing` of `fn()` (its result is waited for with `jax.block_until_ready`). The
    first call, or `warmup()` (the same programs on less work) when given, is timed
    apart; then `repeats` calls under `no_retrace`: only one when the first took over `slow` s,
    fewer once they took `budget` s in all, more (up to `most`) while under `fast` s."""
    first, result = timed_call(warmup or fn)
    times, repeats = [], 1 if first > slow else repeats
    with no_retrace(what or getattr(fn, "__name__", "the timed function")):
        while (
            not times
            or (len(times) < repeats and sum(times) < budget)
            or (len(times) < (most or repeats) and sum(times) < fast)
        ):
            seconds, result = timed_call(fn)
            times.append(seconds)
    return Timing(first, statistics.median(times), min(times), tuple(times), result)


def timings(fns, repeats=5, what=None):
    """`[Timing]` of each of `fns`, called first each once, then in turn `repeats` times
    (interleaved: a burst of load from other processes hits them all)."""
    first = [timed_call(fn) for fn in fns]
    times, results = [[] for _ in fns], [result for _, result in first]
    with no_retrace(what or "the timed functions"):
        for _ in range(repeats):
            for k, fn in enumerate(fns):
                seconds, results[k] = timed_call(fn)
                times[k].append(seconds)
    return [
        Timing(f, statistics.median(t), min(t), tuple(t), r)
        for (f, _), t, r in zip(first, times, results, strict=True)
    ]


def random_states(n, batch, seed=0, speed=1.0):
    """`batch` random states of `n` spheres, `sm.random_state` under `vmap` on the keys
    split from `PRNGKey(seed)`: `(q, v)`, each `(batch, n, 3)`."""
    import jax

    import sphere_mech as sm

    keys = jax.random.split(jax.random.PRNGKey(seed), batch)
    return jax.vmap(lambda k: sm.random_state(k, n, speed=speed))(keys)


def table(columns, rows, align=None):
    """A markdown table: header cells `columns`, `rows` of cells (`str` of each), `align`
    one letter a column, "l" (`---`) or "r" (`---:`); default all "l"."""
    align = align or "l" * len(columns)
    lines = [
        "| " + " | ".join(columns) + " |",
        "|" + "".join("---|" if a == "l" else "---:|" for a in align),
        *("| " + " | ".join(str(cell) for cell in row) + " |" for row in rows),
    ]
    return "\n".join(lines)


def publish(text, name=None, out=RESULTS, show=print):
    """Print `text` (or pass it to `show`) and, with `name` ("fast_path.md"), write it to
    `out / name`."""
    show(text)
    if name is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / name).write_text(text)


def pyplot():
    """`matplotlib.pyplot` on the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, name, out=RESULTS, dpi=120, layout=True):
    """`fig` (laid out tightly unless `layout=False`) saved as `out / name` and closed."""
    import matplotlib.pyplot as plt

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if layout:
        fig.tight_layout()
    fig.savefig(out / name, dpi=dpi)
    plt.close(fig)
    print(f"figure: {out / name}", flush=True)


def bars(ax, labels, series, fontsize=8, rotation=0):
    """A grouped bar chart on `ax`: one group per label in `labels`, one bar in each group
    per entry of `series` (`{legend: values}`, a value per label)."""
    x, width = np.arange(len(labels)), 0.8 / len(series)
    for k, (name, values) in enumerate(series.items()):
        ax.bar(x + (k - (len(series) - 1) / 2) * width, values, width, label=name)
    ax.set_xticks(x, labels, fontsize=fontsize, rotation=rotation)
    ax.legend(fontsize=8)


def load():
    """The 1-minute load average now."""
    return os.getloadavg()[0]


def cpu_name():
    """The processor: its architecture, then its model name where Linux gives it."""
    info = Path("/proc/cpuinfo")
    names = [
        line.split(":", 1)[1].strip()
        for line in (info.read_text().splitlines() if info.exists() else [])
        if line.startswith("model name")
    ]
    return f"{platform.machine()} CPU" + (f" ({names[0]})" if names else "")


def machine(loads):
    """The processor, its cores and the range of the load averages `loads`."""
    return (
        f"{cpu_name()}, {os.cpu_count()} cores, "
        f"load average {min(loads):.1f}-{max(loads):.1f} during the runs"
    )
