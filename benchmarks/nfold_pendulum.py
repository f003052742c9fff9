"""The adaptive N-fold pendulum of Celledoni, Cokaj, Leone, Murari and Owren ("Lie group
integrators for mechanical systems", Int. J. Comput. Math. 99:1, 2022), with their
RKMK(5,4) as the baseline, measured in the same run.

The experiment: P = 2, 4, ..., 20 links of length 5/P each, unit point masses at the
links' outer ends, g = 9.81, every link horizontal along (1, 0, 0) at rest, T = 3.

- Reference: the same chain written here independently, in the P link angles of its
  (planar) motion, Euler-Lagrange equations derived by hand, integrated by scipy's
  DOP853 at rtol = atol = 1e-13.
- Error: the 2-norm over all q_i and omega_i (omega_i = q_i x qdot_i) at T.
- Baseline (the paper's method, as in their public MATLAB code): RKMK over the Dopri5
  tableau with the SE(3) action (`sm.LieRK(DormandPrince54(), action="SE3",
  error="algebra")`: Dormand and Prince's original embedded weights, as in their code,
  not diffrax's Shampine weights), their error estimate (the 2-norm of the difference of the 5th and
  4th order Lie-algebra increments, unscaled), a step accepted when it is below 1e-6,
  `h <- min(0.85 (tol/err)^(1/4) h, T - t)` after every attempt, `h0 = T/100` (a
  diffrax step-size controller below). It must take 52 accepted steps at P = 2 and 675 at
  P = 20 (checked: the script fails otherwise).
- Our solvers: `LieRK` over several tableaus and both actions, `Projected(Tsit5)` and
  `Projected(Dopri5)`, with diffrax's `PIDController(rtol=tol, atol=tol)` over a range of
  tolerances, all started with `dt0 = T/100`, integrating `MechanicsTerm(chain)` (the
  constant-inertia chain, state (q, qdot)) with `diffrax.diffeqsolve`.
- Counted: accepted and rejected steps, vector-field evaluations (from the step counts:
  1 + (accepted + rejected) x (stages - 1) for first-same-as-last tableaus, as executed;
  for the baseline also its MATLAB code's 7 per attempt), wall time (median of repeats
  after compilation; one repeat, so also its minimum).

Comparison at equal error: for each method and P, its evaluations and accepted steps are
interpolated (log-log, between its tolerances) at the baseline's final error.

    python benchmarks/nfold_pendulum.py           # full run (about 15 min on 2 cores)
    python benchmarks/nfold_pendulum.py --quick   # P = 2 and 20, 2 methods + baseline (< 2 min)

Writes `<out>/nfold_pendulum{,_quick}.{md,json,png}`.
"""

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.integrate

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _harness, when the tests import us
from _harness import RESULTS as RESULTS_DIR, publish, pyplot, save_figure, table, timing  # noqa: E402

import sphere_mech as sm  # noqa: E402

T = 3.0
G = 9.81
TOTAL_LENGTH = 5.0
PAPER_TOL = 1e-6
PAPER_ACCEPTED = {2: 52, 20: 675}
"""Accepted steps of the paper's RKMK(5,4) (their code, h0 = T/100, tol = 1e-6)."""
REFERENCE_TOL = 1e-13
TOLERANCES = tuple(10.0**-k for k in range(5, 11))
PAPER = "paper RKMK(5,4)"

# ----------------------------------------------------------------------------------------
# The independent reference: the planar chain in link angles


def _angle_rates(_, x, lengths, masses):
    """`d(theta, thetadot)/dt` with `q_i = (cos theta_i, 0, sin theta_i)`:
    `sum_j L_ij [cos(th_i - th_j) thdd_j + sin(th_i - th_j) thd_j^2] + g l_i mu_i cos th_i
    = 0`, `L_ij = l_i l_j mu_max(i,j)`, `mu_i = sum_{k >= i} m_k`."""
    p = len(lengths)
    th, thd = x[:p], x[p:]
    mu = np.cumsum(masses[::-1])[::-1]
    big = lengths[:, None] * lengths[None, :] * mu[np.maximum.outer(np.arange(p), np.arange(p))]
    diff = th[:, None] - th[None, :]
    mass = big * np.cos(diff)
    rhs = -(big * np.sin(diff)) @ thd**2 - G * lengths * mu * np.cos(th)
    return np.concatenate([thd, np.linalg.solve(mass, rhs)])


def reference_state(p):
    """`(q, omega)` at T, flattened, from scipy DOP853 on the angle formulation."""
    lengths, masses = np.full(p, TOTAL_LENGTH / p), np.ones(p)
    sol = scipy.integrate.solve_ivp(
        _angle_rates,
        (0.0, T),
        np.zeros(2 * p),
        method="DOP853",
        rtol=REFERENCE_TOL,
        atol=REFERENCE_TOL,
        args=(lengths, masses),
    )
    th, thd = sol.y[:p, -1], sol.y[p:, -1]
    q = np.stack([np.cos(th), np.zeros(p), np.sin(th)], -1)
    omega = np.stack([np.zeros(p), -thd, np.zeros(p)], -1)  # q_i x (thd_i dq_i/dth_i)
    return np.concatenate([q.ravel(), omega.ravel()])


def state_vector(q, qdot):
    q, qdot = np.asarray(q), np.asarray(qdot)
    return np.concatenate([q.ravel(), np.cross(q, qdot).ravel()])


# ----------------------------------------------------------------------------------------
# The paper's method: Dopri5 with the original embedded weights, and their controller

_DOPRI5 = diffrax.Dopri5.tableau
_DORMAND_PRINCE_HAT = np.array(
    [5179 / 57600, 0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40]
)


class DormandPrince54(diffrax.AbstractERK):
    """Dormand and Prince's 5(4) pair with the original embedded weights (those of the
    paper's code; diffrax's `Dopri5` has the same order-5 weights but Shampine's embedded
    order-4 solution, whose estimate is smaller)."""

    tableau: ClassVar[diffrax.ButcherTableau] = diffrax.ButcherTableau(
        c=_DOPRI5.c,
        b_sol=_DOPRI5.b_sol,
        b_error=_DOPRI5.b_sol - _DORMAND_PRINCE_HAT,
        a_lower=_DOPRI5.a_lower,
    )
    interpolation_cls: ClassVar = diffrax.ThirdOrderHermitePolynomialInterpolation.from_k

    def order(self, terms):
        return 5


class PaperController(diffrax.AbstractAdaptiveStepSizeController):
    """Accept a step when the unscaled 2-norm of the solver's error estimate is below
    `tol`; after every attempt `h <- 0.85 (tol/err)^(1/4) h` (diffrax clips the last step
    to `T`, as their `min(., T - t)` does)."""

    tol: float
    rtol: float = 0.0
    atol: float = 0.0
    norm: object = None

    def wrap(self, direction):
        return self

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        return t0 + dt0, None

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, state):
        err = jnp.sqrt(sum(jnp.sum(e**2) for e in jax.tree.leaves(y_error)))
        keep = err < self.tol
        factor = 0.85 * (self.tol / err) ** 0.25
        next_t0 = jnp.where(keep, t1, t0)
        return keep, next_t0, next_t0 + factor * (t1 - t0), False, state, diffrax.RESULTS.successful


# ----------------------------------------------------------------------------------------
# Methods and runs


@dataclasses.dataclass
class Method:
    label: str
    solver: diffrax.AbstractSolver
    evals_per_step: int  # new vector-field evaluations per attempted step
    lie: bool = False  # a Lie-group solver (candidate for "best Lie-group solver")
    quick: bool = False


def _fsal_evals(solver):
    return solver.tableau.num_stages - 1


def methods(quick):
    L, P = sm.LieRK, sm.Projected
    # One compilation per method and P dominates the run time, so the grid is small:
    # LieRK(Bosh3), LieRK4 and the SO3xR3 variants of Tsit5 and Dopri8 are left out (add
    # them here; each adds about 10 compilations).
    tableaus = dict(Dopri5=diffrax.Dopri5(), Tsit5=diffrax.Tsit5(), Dopri8=diffrax.Dopri8())
    chosen = (("Dopri5", "SE3"), ("Dopri5", "SO3xR3"), ("Tsit5", "SE3"), ("Dopri8", "SE3"))
    ms = [
        Method(
            f"LieRK({name}, {action})",
            L(tableaus[name], action=action),
            _fsal_evals(tableaus[name]),
            lie=True,
            quick=name == "Tsit5",
        )
        for name, action in chosen
    ]
    ms += [
        Method("Projected(Tsit5)", P(diffrax.Tsit5()), 6, quick=True),
        Method("Projected(Dopri5)", P(diffrax.Dopri5()), 6),
    ]
    return [m for m in ms if m.quick or not quick]


def chain_and_state(p):
    chain = sm.chain_pendulum(jnp.ones(p), jnp.full(p, TOTAL_LENGTH / p), g=G)
    y0 = (jnp.tile(jnp.array([1.0, 0.0, 0.0]), (p, 1)), jnp.zeros((p, 3)))
    return chain, y0


@eqx.filter_jit
def _solve(chain, solver, controller, y0):
    sol = diffrax.diffeqsolve(
        sm.MechanicsTerm(chain),
        solver,
        0.0,
        T,
        T / 100,
        y0,
        stepsize_controller=controller,
        max_steps=100_000,
        throw=False,
    )
    stats = (sol.stats["num_accepted_steps"], sol.stats["num_rejected_steps"])
    return (sol.ys[0][-1], sol.ys[1][-1]), stats, sol.result == diffrax.RESULTS.successful


def run(chain, solver, controller, y0, reference, repeats=1):
    t = timing(lambda: _solve(chain, solver, controller, y0), repeats, what=type(solver).__name__)
    (q, qdot), (acc, rej), ok = t.result
    error = float(np.linalg.norm(state_vector(q, qdot) - reference))
    return dict(
        error=error if bool(ok) else float("nan"),
        accepted=int(acc),
        rejected=int(rej),
        wall=t.median,
        wall_min=t.min,
        compile=t.compile,
        success=bool(ok),
    )


def paper_baseline(p, reference=None):
    """The paper's RKMK(5,4) at P links: a dict of the measured numbers."""
    chain, y0 = chain_and_state(p)
    solver = sm.LieRK(DormandPrince54(), action="SE3", error="algebra")
    reference = reference_state(p) if reference is None else reference
    r = run(chain, solver, PaperController(PAPER_TOL), y0, reference)
    attempts = r["accepted"] + r["rejected"]
    return r | dict(
        P=p,
        method=PAPER,
        tol=PAPER_TOL,
        evaluations=1 + 6 * attempts,
        evaluations_matlab=7 * attempts,
    )


def measure(ps, quick, progress=None):
    rows = []
    for p in ps:
        reference = reference_state(p)
        base = paper_baseline(p, reference)
        rows.append(base)
        print(
            f"P = {p}: {PAPER} {base['accepted']} accepted, {base['rejected']} rejected, "
            f"error {base['error']:.2e}",
            flush=True,
        )
        if p in PAPER_ACCEPTED and base["accepted"] != PAPER_ACCEPTED[p]:
            raise AssertionError(
                f"the baseline took {base['accepted']} accepted steps at "
                f"P = {p}, the paper's code {PAPER_ACCEPTED[p]}"
            )
        chain, y0 = chain_and_state(p)
        for m in methods(quick):
            for tol in (1e-5, 1e-7) if quick else TOLERANCES:
                r = run(chain, m.solver, diffrax.PIDController(rtol=tol, atol=tol), y0, reference)
                evals = 1 + m.evals_per_step * (r["accepted"] + r["rejected"])
                rows.append(r | dict(P=p, method=m.label, tol=tol, evaluations=evals, lie=m.lie))
        if progress is not None:
            progress.write_text(json.dumps(rows, indent=1))
    return rows


# ----------------------------------------------------------------------------------------
# Analysis and output


def at_error(rows, p, method, error, key):
    """`key` (evaluations or accepted steps) of `method` at P = p, interpolated log-log
    at the final error `error` (NaN outside the measured range)."""
    pts = sorted(
        (r["error"], r[key])
        for r in rows
        if r["P"] == p and r["method"] == method and r["success"] and r["error"] > 0
    )
    if len(pts) < 2:
        return float("nan")
    le = np.log([e for e, _ in pts])
    lv = np.log([v for _, v in pts])
    x = math.log(error)
    if not le[0] <= x <= le[-1]:
        return float("nan")
    order = np.argsort(le)
    return float(np.exp(np.interp(x, le[order], lv[order])))


def equal_error_table(rows, ps):
    """Per method: evaluations and accepted steps relative to the baseline at the
    baseline's error, per P (geometric mean over P where interpolable)."""
    base = {r["P"]: r for r in rows if r["method"] == PAPER}
    labels = [m for m in dict.fromkeys(r["method"] for r in rows) if m != PAPER]
    lines, summary = [], {}
    for m in labels:
        cells, ratios = [], []
        for p in ps:
            ev = at_error(rows, p, m, base[p]["error"], "evaluations") / base[p]["evaluations"]
            st = at_error(rows, p, m, base[p]["error"], "accepted") / base[p]["accepted"]
            cells.append("—" if math.isnan(ev) else f"{ev:.2f} / {st:.2f}")
            if not math.isnan(ev):
                ratios.append((ev, st))
        mean = tuple(float(np.exp(np.mean(np.log(x)))) for x in zip(*ratios, strict=True))
        summary[m] = mean if ratios else (float("nan"), float("nan"))
        tail = f"{mean[0]:.2f} / {mean[1]:.2f}" if ratios else "—"
        lines.append((m, *cells, tail))
    return table(["method", *(f"P={p}" for p in ps), "geo. mean"], lines), summary


def best_at_one_tolerance(rows, ps, method):
    """The loosest tolerance at which `method`'s error is at most the baseline's for
    most P, and its row per P."""
    base = {r["P"]: r for r in rows if r["method"] == PAPER}
    tols = sorted({r["tol"] for r in rows if r["method"] == method}, reverse=True)
    for tol in tols:
        mine = {r["P"]: r for r in rows if r["method"] == method and r["tol"] == tol}
        if sum(mine[p]["error"] <= base[p]["error"] for p in ps) > len(ps) / 2:
            return tol, mine
    return tols[-1], {r["P"]: r for r in rows if r["method"] == method and r["tol"] == tols[-1]}


def comparison_table(rows, ps, method, tol, mine, tsit_tol, tsit):
    base = {r["P"]: r for r in rows if r["method"] == PAPER}
    columns = [
        "P",
        f"{PAPER}: accepted / rejected / evals (MATLAB evals) / error",
        f"{method} tol {tol:.0e}: accepted / rejected / evals / error",
        f"Projected(Tsit5) tol {tsit_tol:.0e}: accepted / rejected / evals / error",
    ]
    cells = []
    for p in ps:
        b, m, t = base[p], mine[p], tsit[p]
        cells.append(
            (
                p,
                f"{b['accepted']} / {b['rejected']} / {b['evaluations']} "
                f"({b['evaluations_matlab']}) / {b['error']:.2e}",
                f"{m['accepted']} / {m['rejected']} / {m['evaluations']} / {m['error']:.2e}",
                f"{t['accepted']} / {t['rejected']} / {t['evaluations']} / {t['error']:.2e}",
            )
        )
    return table(columns, cells)


def full_table(rows):
    columns = ["P", "method", "tol", "accepted", "rejected", "evals", "error at T", "time (ms)"]
    return table(
        columns,
        [
            (r["P"], r["method"], f"{r['tol']:.0e}", r["accepted"], r["rejected"])
            + (r["evaluations"], f"{r['error']:.2e}", f"{1e3 * r['wall']:.1f}")
            for r in rows
        ],
    )


def figure(rows, ps, out, name):
    plt = pyplot()
    shown = [p for p in (2, 10, 20) if p in ps]
    labels = [m for m in dict.fromkeys(r["method"] for r in rows) if m != PAPER]
    fig, axes = plt.subplots(1, len(shown), figsize=(5.0 * len(shown), 4.4), squeeze=False)
    palette = [plt.cm.tab20(i) for i in range(20)]
    for ax, p in zip(axes[0], shown, strict=True):
        for i, m in enumerate(labels):
            pts = sorted(
                (r["error"], r["evaluations"])
                for r in rows
                if r["P"] == p and r["method"] == m and r["success"]
            )
            style = "--" if m.startswith("Projected") else "-"
            ax.loglog(*zip(*pts, strict=True), style, marker="o", ms=3, color=palette[i], label=m)
        b = next(r for r in rows if r["P"] == p and r["method"] == PAPER)
        ax.loglog([b["error"]], [b["evaluations"]], "k*", ms=12, label=PAPER)
        ax.set_title(f"N-fold pendulum, P = {p}, T = 3", fontsize=10)
        ax.set_xlabel("error at T (2-norm over q, omega)")
        ax.grid(True, which="major", alpha=0.3)
    axes[0][0].set_ylabel("vector-field evaluations")
    axes[0][-1].legend(fontsize=7, loc="upper right")
    save_figure(fig, name, out)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="P = 2 and 20, two methods and the baseline"
    )
    parser.add_argument("--out", default=str(RESULTS_DIR))
    a = parser.parse_args(argv)
    ps = (2, 20) if a.quick else tuple(range(2, 21, 2))
    name = "nfold_pendulum_quick" if a.quick else "nfold_pendulum"
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = measure(ps, a.quick, out / f"{name}_partial.json")
    report(rows, ps, out, name)
    return rows


def report(rows, ps, out, name):
    """Print the tables and write `<out>/<name>.{md,json,png}`."""

    equal, summary = equal_error_table(rows, ps)
    lie = [m for m in summary if m.startswith("LieRK") and not math.isnan(summary[m][0])]
    best = min(lie, key=lambda m: summary[m][0])
    tol, mine = best_at_one_tolerance(rows, ps, best)
    tsit_tol, tsit = best_at_one_tolerance(rows, ps, "Projected(Tsit5)")
    text = "\n\n".join(
        [
            f"N-fold pendulum (Celledoni et al. 2022), T = {T}, float64, errors against scipy "
            f"DOP853 at {REFERENCE_TOL:g} on an angle formulation. {PAPER}: their controller, "
            f"tol {PAPER_TOL:g}, h0 = T/100.",
            f"Best Lie-group solver (fewest evaluations at the baseline's error): {best}. "
            "At one tolerance for all P (the loosest whose error is at most the baseline's for "
            "most P), against the baseline and Projected(Tsit5) chosen the same way:",
            comparison_table(rows, ps, best, tol, mine, tsit_tol, tsit),
            "Evaluations / accepted steps relative to the baseline at the baseline's error "
            "(log-log interpolation between tolerances; below 1 is cheaper):",
            equal,
            "All runs:",
            full_table(rows),
        ]
    )
    publish(text + "\n", f"{name}.md", out)
    (out / f"{name}.json").write_text(
        json.dumps(dict(rows=rows, best=best, tol=tol, summary=summary), indent=1)
    )
    figure(rows, ps, out, f"{name}.png")


if __name__ == "__main__":
    main()
