"""The FDCL quadrotor experiments of Gamagedara, Bisheban, Kaufman and Lee ("Geometric
adaptive controls of a quadrotor UAV with decoupled attitude dynamics"), reproduced with
sphere_mech, against the runs they saved in their public repository
fdcl-gwu/decoupled-yaw-controller-comparison (`Data/{Circle,Line}/{decoupled,coupled}.mat`,
ode45 at rtol = atol = 1e-6).

The quadrotor is built as a user would: `space = {"base": sm.Euclidean(3), "attitude":
sm.Rotations(1)}`, form 2 (`sm.AngularLagrangian`: base velocity `xdot`, body angular
velocity `Omega`), their frame (z down, so the potential is `U = -m g x_3`),

    L = 1/2 m |xdot|^2 + 1/2 Omega . J Omega + m g x_3,

m = 2 kg, J = diag(0.02, 0.02, 0.04) kg m^2, g = 9.81, and the controller as the system's
`forces`: thrust `-f R e3` on the base (world frame) and the moment `M` on the attitude (a
body torque), after their saturation: `(f, M)` mapped to the four rotor thrusts (arm d =
0.169 m, torque coefficient c_tf = 0.0135), each clipped to [0.1, 8] N, and mapped back.

The two controllers are written here from their published equations:
- the decoupled-yaw controller (the paper's): the position loop gives the thrust `f =
  -A . b3` and the desired thrust axis `b3c = -A/|A|` with `A = -k_x e_x - k_v e_v - m g e3
  + m xddot_d`; `b2c = b3c x b1d / |.|`, `b1c = b2c x b3c`; the roll/pitch loop acts on
  `b3` on S^2 (`e_b = b3c x b3`, `e_w = w + b3 x (b3 x w_c)`, `w = Omega_1 b1 + Omega_2
  b2`, `w_c = b3c x b3c'`), the yaw loop on `e_y = -b2 . b1c` and `e_Wy = Omega_3 -
  Omega_3c`;
- the coupled controller of Goodarzi, Lee and Lee (SE(3)): `e_R = 1/2 vee(Rc^T R - R^T
  Rc)`, `e_W = W - R^T Rc Wc`, `M = -k_R e_R - k_W e_W + hat(R^T Rc Wc) J R^T Rc Wc + J
  R^T Rc Wc'` (the feed-forward as their code evaluates it).
Both need `Rc`'s first and second time derivatives, from the closed-loop `xddot`, `x^(3)`
and `x^(4)` of the command; the derivatives of unit vectors and of `b2c` come here from
nested `jax.jvp`s, those of `b1c = b2c x b3c` from the product rule, written out so that
the runs can be reproduced *as published*: their code's second derivative of `b1c` adds
`b2c x b2c''` where the product rule calls for `b2c x b3c''`, and it reads `Wc' = vee(Rc^T
Rc'' - hat(Wc)^2)` from the upper triangle, `(-S_23, S_13, -S_12)` (the same as `sm.vee`,
the skew part, only while that matrix is skew). That upper triangle never reads the first
column of `Rc^T Rc''`, where `b1c''` sits: in their code the wrong term has no effect.
`--corrected` shows it: it also runs (a) the corrected formula (the same run to the last
bit) and (b) their formula with `Wc'` read from the skew part (what the term would have
changed).

Their adaptive estimates `theta_x`, `theta_R` are state variables of their ODE, but in
every saved run the disturbances are off and their equations of motion multiply the
estimates' rates by zero, so the estimates stay at their initial zero. We reproduce those
runs: the controller is then a plain function of `(t, x, xdot, R, Omega)`, the `forces` of
the mechanical system, and no extra ODE variable is needed (none is added; `theta = 0`
drops out of every term, and with it their adaptive gains `gamma_x`, `gamma_R`, `c1`,
`c2`, `c3`).

Gains (from their saved runs, which differ from their script's defaults in `k_x`, `k_v`):
circle + decoupled k_x = 12, k_v = 8; the three others k_x = 11, k_v = 9; all k_R = 6,
k_W = 2, k_y = 2, k_wy = 0.8. Commands: circle `x_d = (cos wt - 1, sin wt, -1)`, w =
2 pi/10, `b1d = (cos w't, sin w't, 0)`, w' = 2 pi/40, from `x0 = (1, -1, 0)`; line `x_d =
(4t, 0, -5)`, `b1d = e1`, from `x0 = 0`; both from rest at `R0 = expm((pi - 0.01)
hat(e3))` (a nearly reversed yaw).

The table is theirs beside ours: the means over t = 0:0.01:10 (1001 samples) of |e_x|,
|e_R| (`1/2 vee(Rc^T R - R^T Rc)`, for both controllers) and the norm of the four
saturated rotor thrusts, and the first sample time with |e_x| < 0.02 m; then the distance
between our tight run (`sm.LieRK(Dopri8)`, rtol = atol = 1e-10) and theirs: max over the
samples of |x - x_theirs| and of the Frobenius norm of `R - R_theirs`, and the same for
our run at their tolerance (`sm.LieRK(Dopri5)`, 1e-6) as a scale of what their tolerance
allows.

    python benchmarks/fdcl_quadrotor.py [--quick] [--corrected] [--out DIR] [--results DIR]

writes `<out>/{circle,line}_{decoupled,coupled}.npz` (`t` (1001,), `x` (1001, 3), `R`
(1001, 3, 3)) when `--out` is given, and `<results>/fdcl_quadrotor{,_quick}.{md,png}`
(default benchmarks/results). `--quick`: the circle with the decoupled controller only, at rtol =
atol = 1e-8. The reference arrays are `benchmarks/data/fdcl_reference.npz` (provenance in
benchmarks/data/README.md), rebuilt from their .mat files by `--from-mat DIR`.
"""

import argparse
import sys
import time
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _harness, when imported
from _harness import RESULTS, publish, pyplot, save_figure, table  # noqa: E402

import sphere_mech as sm  # noqa: E402

REFERENCE = Path(__file__).resolve().parent / "data" / "fdcl_reference.npz"
SOURCE = "fdcl-gwu/decoupled-yaw-controller-comparison"
SOURCE_COMMIT = "1d067d5"

MASS, GRAVITY = 2.0, 9.81
INERTIA = jnp.array([0.02, 0.02, 0.04])
ARM, TORQUE_COEFFICIENT = 0.169, 0.0135
THRUST_MIN, THRUST_MAX = 0.1, 8.0
K_R, K_W, K_Y, K_WY = 6.0, 2.0, 2.0, 0.8
GAINS = {  # (k_x, k_v) of their saved runs
    ("circle", "decoupled"): (12.0, 8.0),
    ("circle", "coupled"): (11.0, 9.0),
    ("line", "decoupled"): (11.0, 9.0),
    ("line", "coupled"): (11.0, 9.0),
}
CASES = tuple(GAINS)
START = {"circle": (1.0, -1.0, 0.0), "line": (0.0, 0.0, 0.0)}
T1, SAMPLES = 10.0, 1001
TIMES = np.linspace(0.0, T1, SAMPLES)
CONVERGED = 0.02  # m, the |e_x| of their "first time converged"
E3 = jnp.array([0.0, 0.0, 1.0])
MIXER = jnp.array(
    [
        [1.0, 1.0, 1.0, 1.0],
        [0.0, -ARM, 0.0, ARM],
        [ARM, 0.0, -ARM, 0.0],
        [-TORQUE_COEFFICIENT, TORQUE_COEFFICIENT, -TORQUE_COEFFICIENT, TORQUE_COEFFICIENT],
    ]
)
"""`(f, M) = MIXER @ rotor thrusts`: rotors on the body axes +e1, +e2, -e1, -e2 (z down),
alternating spin."""
TIGHT = dict(solver=sm.LieRK(diffrax.Dopri8()), rtol=1e-10, atol=1e-10)
THEIRS = dict(solver=sm.LieRK(diffrax.Dopri5()), rtol=1e-6, atol=1e-6)
QUICK = dict(solver=sm.LieRK(diffrax.Dopri8()), rtol=1e-8, atol=1e-8)


# --------------------------------------------------------------------------- commands
def circle(t):
    """Their circle: radius 1 m at height 1 m (z down), period 10 s; `b1d` turning once
    in 40 s. Returns `x_d` and its first four derivatives, `b1d` and its first two."""
    w, wy = 2 * jnp.pi / 10, 2 * jnp.pi / 40
    c, s = jnp.cos(w * t), jnp.sin(w * t)
    zero = jnp.zeros_like(t)
    xd = [jnp.stack([c - 1, s, -jnp.ones_like(t)])]
    for k in range(1, 5):  # d^k/dt^k (cos, sin) = w^k (cos, sin)(wt + k pi/2)
        ck, sk = jnp.cos(w * t + k * jnp.pi / 2), jnp.sin(w * t + k * jnp.pi / 2)
        xd.append(w**k * jnp.stack([ck, sk, zero]))
    b1 = [
        wy**k
        * jnp.stack([jnp.cos(wy * t + k * jnp.pi / 2), jnp.sin(wy * t + k * jnp.pi / 2), zero])
        for k in range(3)
    ]
    return xd, b1


def line(t):
    """Their line: 4 m/s along e1 at height 5 m, `b1d = e1`."""
    zero = jnp.zeros(3, dtype=jnp.result_type(t, float))
    xd = [jnp.stack([4.0 * t, 0.0 * t, -5.0 + 0.0 * t]), jnp.array([4.0, 0.0, 0.0])] + [zero] * 3
    return xd, [jnp.array([1.0, 0.0, 0.0]), zero, zero]


def pick(flag, yes, no):
    """`yes()` where the flag (0. or 1., an array of `args`) is set, else `no()`: both are
    computed, so that one compiled program runs every case."""
    return jax.tree.map(lambda u, v: jnp.where(flag > 0.5, u, v), yes(), no())


def command(t, args):
    """The command selected by `args["line"]` (0: circle, 1: line)."""
    return pick(args["line"], lambda: line(t), lambda: circle(t))


# ------------------------------------------------------------------------- controller
def with_derivatives(fn, p, p1, p2):
    """`fn(p)` and its first two time derivatives along `p(t)` with `p' = p1`, `p'' =
    p2`: `y' = Dfn p1`, `y'' = Dfn p2 + D^2fn[p1, p1]` by nested `jax.jvp`."""
    first = lambda q, dq: jax.jvp(fn, (q,), (dq,))
    y, y1 = first(p, p1)
    _, y2 = jax.jvp(lambda q, dq: first(q, dq)[1], (p, p1), (p1, p2))
    return y, y1, y2


def unit(a):
    return a / jnp.linalg.norm(a)


def vee_upper(S):
    """`(-S_23, S_13, -S_12)`: `vee` as their code reads it (equal to `sm.vee` on skew
    matrices)."""
    return jnp.stack([-S[1, 2], S[0, 2], -S[0, 1]])


def desired_attitude(t, x, xdot, R, W, args):
    """The position loop: thrust `f`, errors `e_x`, `e_v`, and `Rc`, `Wc`, `Wc'`."""
    kx, kv = args["kx"], args["kv"]
    (xd, vd, ad, jd, sd), (b1d, b1d1, b1d2) = command(t, args)
    ex, ev = x - xd, xdot - vd
    A = -kx * ex - kv * ev - MASS * GRAVITY * E3 + MASS * ad
    b3, b3_1 = R @ E3, R @ jnp.cross(W, E3)
    f = -A @ b3
    ev1 = GRAVITY * E3 - f / MASS * b3 - ad  # the closed loop's (unsaturated) e_v'
    A1 = -kx * ev - kv * ev1 + MASS * jd
    f1 = -A1 @ b3 - A @ b3_1
    ev2 = -f1 / MASS * b3 - f / MASS * b3_1 - jd
    A2 = -kx * ev1 - kv * ev2 + MASS * sd
    b3c, b3c1, b3c2 = with_derivatives(lambda a: unit(-a), A, A1, A2)
    b2c_of = lambda p: unit(jnp.cross(p[0], p[1]))  # b3c x b1d, normalized
    b2c, b2c1, b2c2 = with_derivatives(
        b2c_of, jnp.stack([b3c, b1d]), jnp.stack([b3c1, b1d1]), jnp.stack([b3c2, b1d2])
    )
    last = pick(args["corrected"], lambda: b3c2, lambda: b2c2)  # published: b2c''
    b1c = jnp.cross(b2c, b3c)
    b1c1 = jnp.cross(b2c1, b3c) + jnp.cross(b2c, b3c1)
    b1c2 = jnp.cross(b2c2, b3c) + 2 * jnp.cross(b2c1, b3c1) + jnp.cross(b2c, last)
    Rc = jnp.stack([b1c, b2c, b3c], axis=1)
    Rc1 = jnp.stack([b1c1, b2c1, b3c1], axis=1)
    Rc2 = jnp.stack([b1c2, b2c2, b3c2], axis=1)
    Wc = vee_upper(Rc.T @ Rc1)
    S = Rc.T @ Rc2 - sm.hat(Wc) @ sm.hat(Wc)  # hat(Wc') with the correct b1c''
    Wc1 = pick(args["skew_vee"], lambda: sm.vee(S), lambda: vee_upper(S))
    return dict(f=f, ex=ex, ev=ev, Rc=Rc, Wc=Wc, Wc1=Wc1, b3c=(b3c, b3c1, b3c2), b1c=b1c)


def decoupled_moment(R, W, d):
    """The decoupled-yaw attitude controller: roll/pitch on S^2, yaw apart."""
    J1, J3 = INERTIA[0], INERTIA[2]
    b1, b2, b3 = R[:, 0], R[:, 1], R[:, 2]
    b3c, b3c1, b3c2 = d["b3c"]
    w = W[0] * b1 + W[1] * b2
    b3_1 = jnp.cross(w, b3)
    wc, wc1 = jnp.cross(b3c, b3c1), jnp.cross(b3c, b3c2)
    eb = jnp.cross(b3c, b3)
    ew = w + jnp.cross(b3, jnp.cross(b3, wc))
    tau = -K_R * eb - K_W * ew - J1 * (b3 @ wc) * b3_1 - J1 * jnp.cross(b3, jnp.cross(b3, wc1))
    W3c = b3 @ (d["Rc"] @ d["Wc"])
    W3c1 = b3 @ (d["Rc"] @ d["Wc1"]) + (R @ jnp.cross(W, E3)) @ (d["Rc"] @ d["Wc"])
    ey, eWy = -b2 @ d["b1c"], W[2] - W3c
    return jnp.stack(
        [
            b1 @ tau + J3 * W[2] * W[1],
            b2 @ tau - J3 * W[2] * W[0],
            -K_Y * ey - K_WY * eWy + J3 * W3c1,
        ]
    )


def coupled_moment(R, W, d):
    """The coupled (Goodarzi-Lee) attitude controller on SO(3)."""
    Wr = R.T @ d["Rc"] @ d["Wc"]  # the desired rate in the body frame
    eW = W - Wr
    return (
        -K_R * attitude_error(R, d["Rc"])
        - K_W * eW
        + jnp.cross(Wr, INERTIA * Wr)
        + INERTIA * (R.T @ d["Rc"] @ d["Wc1"])
    )


def attitude_error(R, Rc):
    return 0.5 * sm.vee(Rc.T @ R - R.T @ Rc)  # 1/2 vee(Rc^T R - R^T Rc)


def rotor_thrusts(f, M):
    return jnp.linalg.solve(MIXER, jnp.concatenate([f[None], M]))


def saturate(f, M):
    """Their saturation: each rotor's thrust clipped to [0.1, 8] N."""
    fM = MIXER @ jnp.clip(rotor_thrusts(f, M), THRUST_MIN, THRUST_MAX)
    return fM[0], fM[1:]


def control(t, x, xdot, R, W, args):
    """Saturated thrust `f` and moment `M`, with the errors their table uses."""
    d = desired_attitude(t, x, xdot, R, W, args)
    M = pick(args["decoupled"], lambda: decoupled_moment(R, W, d), lambda: coupled_moment(R, W, d))
    f, M = saturate(d["f"], M)
    return dict(f=f, M=M, ex=d["ex"], eR=attitude_error(R, d["Rc"]), thrusts=rotor_thrusts(f, M))


# --------------------------------------------------------------------------- the system
SPACE = {"base": sm.Euclidean(3), "attitude": sm.Rotations(1)}


def lagrangian(t, q, v, args):
    W = v["attitude"][0]
    return (
        0.5 * MASS * v["base"] @ v["base"] + 0.5 * W @ (INERTIA * W) + MASS * GRAVITY * q["base"][2]
    )


def forces(t, q, v, args):
    R = q["attitude"][0]
    u = control(t, q["base"], v["base"], R, v["attitude"][0], args)
    return {"base": -u["f"] * R @ E3, "attitude": u["M"][None]}


QUADROTOR = sm.AngularLagrangian(lagrangian, forces, quadratic_in_velocity=True, space=SPACE)


SAMPLES_CONTROL = jax.jit(jax.vmap(control, (0, 0, 0, 0, 0, None)))
"""`control` at every sample of a run (compiled once)."""


def case_args(case, controller, corrected=False, skew_vee=False):
    """The `args` of one run: gains `kx`, `kv` and flags (0. or 1.) `line`, `decoupled`,
    `corrected` (the product rule's `b1c''`) and `skew_vee` (`Wc'` read from the skew part
    of `Rc^T Rc'' - hat(Wc)^2`, as `sm.vee` does, instead of their upper triangle)."""
    kx, kv = GAINS[(case, controller)]
    flags = dict(line=case == "line", decoupled=controller == "decoupled")
    flags |= dict(corrected=corrected, skew_vee=skew_vee)
    return {"kx": jnp.asarray(kx), "kv": jnp.asarray(kv)} | {
        k: jnp.asarray(float(v)) for k, v in flags.items()
    }


def initial_state(case):
    c, s = np.cos(np.pi - 0.01), np.sin(np.pi - 0.01)
    R0 = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # expm((pi - 0.01) hat(e3))
    q0 = {"base": jnp.asarray(START[case]), "attitude": R0[None]}
    return q0, {"base": jnp.zeros(3), "attitude": jnp.zeros((1, 3))}


def run(case, controller, *, corrected=False, skew_vee=False, options=TIGHT):
    """Our run of one of their experiments, sampled at t = 0:0.01:10: `dict(t, x, R, W,
    xdot, ex, eR, thrusts)` (numpy arrays), the seconds it took (`seconds`) and the four
    figures of their table (`table`)."""
    args = case_args(case, controller, corrected, skew_vee)
    start = time.perf_counter()
    sol = sm.simulate(
        QUADROTOR,
        initial_state(case),
        T1,
        args=args,
        saveat=diffrax.SaveAt(ts=jnp.asarray(TIMES)),
        max_steps=200_000,
        **options,
    )
    (q, v) = jax.block_until_ready(sol.ys)
    seconds = time.perf_counter() - start
    R, W = q["attitude"][:, 0], v["attitude"][:, 0]
    u = SAMPLES_CONTROL(jnp.asarray(TIMES), q["base"], v["base"], R, W, args)
    out = dict(t=TIMES, x=q["base"], R=R, W=W, xdot=v["base"], ex=u["ex"], eR=u["eR"])
    out = {k: np.asarray(a) for k, a in (out | {"thrusts": u["thrusts"]}).items()}
    return out | {"seconds": seconds, "table": table_figures(out["ex"], out["eR"], out["thrusts"])}


def table_figures(ex, eR, thrusts, t=TIMES):
    """Their four figures: means of |e_x|, |e_R|, |rotor thrusts| over the samples, and
    the first sample time with |e_x| < 0.02 m (nan if never)."""
    nx = np.linalg.norm(ex, axis=-1)
    below = np.flatnonzero(nx < CONVERGED)
    return (
        float(nx.mean()),
        float(np.linalg.norm(eR, axis=-1).mean()),
        float(np.linalg.norm(thrusts, axis=-1).mean()),
        float(t[below[0]]) if below.size else float("nan"),
    )


def distance(ours, theirs):
    """Max over the samples of |x - x_theirs| (m) and ||R - R_theirs||_F."""
    dx = np.linalg.norm(ours["x"] - theirs["x"], axis=-1).max()
    dR = np.linalg.norm(ours["R"] - theirs["R"], axis=(-2, -1)).max()
    return float(dx), float(dR)


# -------------------------------------------------------------------------- reference
def reference(case, controller, path=REFERENCE):
    """Their saved run: `x`, `R` (float64), `ex_norm`, `eR_norm`, `thrust_norm` over the
    samples, and `table` (their mean |e_x|, mean |e_R|, mean thrust norm, converged time)."""
    with np.load(path) as data:
        key = f"{case}_{controller}_"
        return {k[len(key) :]: data[k] for k in data.files if k.startswith(key)}


def store_reference(mat_dir, path=REFERENCE):
    """Rebuild `path` from their `Data/{Circle,Line}/{decoupled,coupled}.mat` under
    `mat_dir` (scipy.io.loadmat)."""
    import scipy.io

    arrays = {}
    for case, controller in CASES:
        mat = Path(mat_dir) / case.capitalize() / f"{controller}.mat"
        data = scipy.io.loadmat(mat, squeeze_me=True, struct_as_record=False)
        assert (
            np.allclose(data["t"], TIMES)
            and (data["k"].x, data["k"].v) == GAINS[(case, controller)]
        )
        key = f"{case}_{controller}_"
        arrays[key + "x"] = data["x"].T
        arrays[key + "R"] = np.moveaxis(data["R"], -1, 0)
        arrays[key + "ex_norm"] = np.linalg.norm(data["e"].x, axis=0).astype(np.float32)
        arrays[key + "eR_norm"] = np.linalg.norm(data["e"].R, axis=0).astype(np.float32)
        arrays[key + "thrust_norm"] = np.linalg.norm(data["thr"], axis=0).astype(np.float32)
        table = [data["avg_ex"], data["avg_eR"], data["avg_f"], data["converge_t"]]
        arrays[key + "table"] = np.array(table, dtype=float)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    print(f"wrote {path} ({path.stat().st_size / 1e3:.0f} kB)")


# ------------------------------------------------------------------------------- main
def plot(ax_x, ax_R, ours, theirs, label="ours"):
    ax_x.plot(TIMES, np.linalg.norm(ours["ex"], axis=-1), label=label)
    ax_x.plot(TIMES, theirs["ex_norm"], "k:", label="theirs (ode45, 1e-6)")
    ax_R.plot(TIMES, np.linalg.norm(ours["eR"], axis=-1), label=label)
    ax_R.plot(TIMES, theirs["eR_norm"], "k:", label="theirs (ode45, 1e-6)")
    for ax, name in ((ax_x, "|e_x| (m)"), (ax_R, "|e_R|")):
        ax.set_yscale("log")
        ax.set_ylabel(name)
        ax.set_xlabel("t (s)")


FORMATS = ("{:.5f} m", "{:.5f}", "{:.4f} N", "{:.2f} s")


def cells(figures):
    return [f.format(v) for f, v in zip(FORMATS, figures, strict=True)]


def report(runs, tol, corrected):
    """The markdown: the table beside theirs, the distances, and (with `corrected`) what
    the corrected formula changes."""
    rows, dist_rows, fix_rows = [], [], []
    for (case, controller), ours in runs.items():
        theirs, name = reference(case, controller), f"{case}, {controller}"
        rows.append([name, "theirs", *cells(theirs["table"])])
        rows.append(["", f"ours ({tol})", *cells(ours["table"])])
        d_tight, d_loose = distance(ours, theirs), distance(ours["at_their_tolerance"], theirs)
        dist_rows.append([name, *(f"{d:.1e}" for d in d_tight + d_loose)])
        if corrected:
            for key, label in (("corrected", "corrected b1c''"), ("skew_vee", "skew-part vee")):
                other = ours[key]
                rows.append(["", f"ours, {label}", *cells(other["table"])])
                change = np.subtract(other["table"], ours["table"])
                fix_rows.append(
                    [name, label, *(f"{c:+.1e}" for c in change)]
                    + [f"{d:.1e}" for d in distance(other, ours)]
                )
    text = (
        "# FDCL quadrotor: their saved runs beside ours\n\n"
        f"Their runs: {SOURCE} (commit {SOURCE_COMMIT}), `Data/*/*.mat`, MATLAB ode45 at "
        "rtol = atol = 1e-6. Ours: `sm.AngularLagrangian` on `{base: Euclidean(3), attitude: "
        f"Rotations(1)}}`, `sm.LieRK(Dopri8)` at rtol = atol = {tol}, their `b1c''` formula"
        + (" (and the corrected one)" if corrected else "")
        + ". Means over t = 0:0.01:10 (1001 samples); the last column is the first sample "
        "with |e_x| < 0.02 m.\n\n"
        + table(
            ["run", "", "mean abs(e_x)", "mean abs(e_R)", "mean rotor-thrust norm", "converged"],
            rows,
            "llrrrr",
        )
        + "\n\nDistance to their run, max over the samples of abs(x - x_theirs) (m) and of "
        f"the Frobenius norm of R - R_theirs: ours at {tol}, and ours with `LieRK(Dopri5)` "
        "at their tolerance 1e-6 (a scale of what that tolerance allows):\n\n"
        + table(
            ["run", f"x ({tol})", f"R ({tol})", "x (Dopri5, 1e-6)", "R (Dopri5, 1e-6)"],
            dist_rows,
            "lrrrr",
        )
        + "\n"
    )
    if corrected:
        text += (
            "\nWhat their `b1c''` formula changes: (a) the corrected formula (`b2c x b3c''` "
            "for their `b2c x b2c''`); (b) their formula, with `Wc'` read from the skew part "
            "of `Rc^T Rc'' - hat(Wc)^2` (as `sm.vee` does) instead of their `vee`'s upper "
            "triangle `(-S_23, S_13, -S_12)`. The upper triangle of `Rc^T Rc''` never reads "
            "its first column, `b1c''`: so in their code the wrong term has no effect, and "
            "(a) is identical to the published run to the last bit. Each row: that run "
            "minus ours as published (same solver and tolerance), then the largest "
            "distance between the two runs (x in m, R Frobenius):\n\n"
            + table(
                ["run", "variant", "mean abs(e_x)", "mean abs(e_R)", "mean thrust"]
                + ["converged", "max x", "max R"],
                fix_rows,
                "llrrrrrr",
            )
            + "\n"
        )
    return text


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="circle, decoupled, 1e-8")
    parser.add_argument("--corrected", action="store_true", help="also the corrected b1c''")
    parser.add_argument("--out", type=Path, help="write our runs, DIR/<case>_<controller>.npz")
    parser.add_argument("--results", type=Path, default=RESULTS, help="the .md and .png")
    parser.add_argument("--from-mat", type=Path, help="rebuild the reference from their Data/")
    opts = parser.parse_args(argv)
    if opts.from_mat:
        store_reference(opts.from_mat)
    cases = CASES[:1] if opts.quick else CASES
    tight = QUICK if opts.quick else TIGHT
    if opts.out:
        opts.out.mkdir(parents=True, exist_ok=True)
    runs = {}
    for case, controller in cases:
        ours = runs[case, controller] = run(case, controller, options=tight)
        if opts.out:
            arrays = {k: ours[k] for k in ("t", "x", "R")}
            np.savez(opts.out / f"{case}_{controller}.npz", **arrays)
        ours["at_their_tolerance"] = run(case, controller, options=THEIRS)
        if opts.corrected:
            ours["corrected"] = run(case, controller, corrected=True, options=tight)
            ours["skew_vee"] = run(case, controller, skew_vee=True, options=tight)
        print(f"{case}, {controller}: {ours['seconds']:.2f} s (the first with compilation)")
    stem = "fdcl_quadrotor" + ("_quick" if opts.quick else "")
    publish(report(runs, f"{tight['rtol']:g}", opts.corrected), stem + ".md", opts.results)
    plt = pyplot()
    fig, axes = plt.subplots(2, len(cases), figsize=(3.6 * len(cases), 5.5), squeeze=False)
    for j, (case, controller) in enumerate(cases):
        plot(axes[0, j], axes[1, j], runs[case, controller], reference(case, controller))
        axes[0, j].set_title(f"{case}, {controller}")
    axes[0, 0].legend()
    save_figure(fig, stem + ".png", opts.results)
    return runs


if __name__ == "__main__":
    main()
