"""Scene files: TOML data (never code) describing effects, initial state, integrator and
times. Every problem raises `SceneFileError(file, field, expected)`."""

import dataclasses
import math
import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

import numpy as np

from .forces import BaseTorque, JointDamping, PDTorque, TipForce, VibratingSupport
from .kinetic import Chain, Particles, SharedSphere
from .potentials import Bending, Gravity, PairInteraction, Spring
from .scene import Scene

UNIT_TOLERANCE = 1e-6
"""How far from unit length an initial direction or a `direction` field may be."""


class SceneFileError(ValueError):
    """A problem in a scene file, reported as `<file>: <field>: <what was expected>`."""

    def __init__(self, path, field: str, expected: str):
        self.path, self.field, self.expected = str(path), field, expected
        super().__init__(f"{self.path}: {field}: {expected}")


# ---- field kinds: each checks a TOML value and returns it converted -----------------

def _number(x):
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


class _Kind:
    def __init__(self, expected: str, check):
        self.expected, self.check = expected, check


def _scalar(lo=None, strict=False, unit=""):
    def check(x):
        if not _number(x):
            return None
        if lo is not None and (x < lo or (strict and x == lo)):
            return None
        return float(x)
    sign = "" if lo is None else (" > 0" if strict else " >= 0")
    return _Kind(f"a number{sign}{unit}", check)


def _list(lo=None, strict=False, unit=""):
    item = _scalar(lo, strict)

    def check(x):
        if not (isinstance(x, list) and x and all(item.check(a) is not None for a in x)):
            return None
        return [float(a) for a in x]
    return _Kind(f"a non-empty array of numbers{item.expected[8:]}{unit}", check)


def _vector(unit_length=False, unit=""):
    def check(x):
        if not (isinstance(x, list) and len(x) == 3 and all(_number(a) for a in x)):
            return None
        if unit_length and abs(math.hypot(*x) - 1.0) > UNIT_TOLERANCE:
            return None
        return [float(a) for a in x]
    what = "a unit vector [x, y, z] (length 1 within 1e-6)" if unit_length else \
        "a vector [x, y, z] of numbers"
    return _Kind(what + unit, check)


def _vectors():
    v = _vector()
    return _Kind("an array of vectors [x, y, z]",
                 lambda x: [v.check(a) for a in x] if isinstance(x, list) and x and all(
                     v.check(a) is not None for a in x) else None)


def _integer(lo=None):
    def check(x):
        ok = isinstance(x, int) and not isinstance(x, bool) and (lo is None or x >= lo)
        return x if ok else None
    return _Kind("an integer" + ("" if lo is None else f" >= {lo}"), check)


def _indices():
    i = _integer(0)
    return _Kind("an array of mass indices (integers >= 0)",
                 lambda x: tuple(x) if isinstance(x, list) and len(x) >= 2 and all(
                     i.check(a) is not None for a in x) else None)


def _end():
    i, v = _integer(), _vector()

    def check(x):
        return i.check(x) if not isinstance(x, list) else v.check(x)
    return _Kind("a mass index (integer) or a fixed point [x, y, z] in m", check)


def _angle(lo, hi):
    return _Kind(f"an angle in degrees within [{lo}, {hi}]",
                 lambda x: float(x) if _number(x) and lo <= x <= hi else None)


def _string(choices=None):
    text = "a string" if choices is None else "one of " + ", ".join(sorted(choices))
    return _Kind(text, lambda x: x if isinstance(x, str) and (
        choices is None or x in choices) else None)


REQUIRED = object()

# effect type -> (builder, {field: (kind, default)})
EFFECTS = {
    "chain": (lambda masses, lengths, base: Chain(masses, lengths, base), {
        "masses": (_list(0, True, " (kg)"), REQUIRED),
        "lengths": (_list(0, True, " (m)"), REQUIRED),
        "base": (_vector(unit=" (m)"), [0.0, 0.0, 0.0])}),
    "particles": (lambda masses, radii, centers: Particles(masses, radii, centers), {
        "masses": (_list(0, True, " (kg)"), REQUIRED),
        "radii": (_list(0, True, " (m)"), REQUIRED),
        "centers": (_vectors(), None)}),
    "shared_sphere": (lambda masses, radius, center: SharedSphere(masses, radius, center), {
        "masses": (_list(0, True, " (kg)"), REQUIRED),
        "radius": (_scalar(0, True, " (m)"), 1.0),
        "center": (_vector(unit=" (m)"), [0.0, 0.0, 0.0])}),
    "gravity": (lambda g, direction: Gravity(g, direction), {
        "g": (_scalar(0, unit=" (m/s^2)"), 9.81),
        "direction": (_vector(True), [0.0, 0.0, -1.0])}),
    "spring": (lambda a, b, stiffness, rest_length: Spring(a, b, stiffness, rest_length), {
        "a": (_end(), REQUIRED), "b": (_end(), REQUIRED),
        "stiffness": (_scalar(0, unit=" (N/m)"), REQUIRED),
        "rest_length": (_scalar(0, unit=" (m)"), 0.0)}),
    "bending": (lambda stiffness: Bending(stiffness), {
        "stiffness": (_scalar(0, unit=" (N m per rad^2)"), REQUIRED)}),
    "pair_interaction": (
        lambda strength, exponent, charges, masses: PairInteraction(
            strength, exponent, None if charges is None else np.asarray(charges), masses), {
            "strength": (_scalar(unit=" (J m^exponent)"), REQUIRED),
            "exponent": (_scalar(0, True), 1.0),
            "charges": (_list(), None),
            "masses": (_indices(), None)}),
    "joint_damping": (lambda coefficient: JointDamping(coefficient), {
        "coefficient": (_scalar(0, unit=" (N m s)"), REQUIRED)}),
    "base_torque": (lambda torque, link: BaseTorque(np.asarray(torque), link), {
        "torque": (_vector(unit=" (N m)"), REQUIRED), "link": (_integer(0), 0)}),
    "pd_torque": (lambda kp, kd, target, link: BaseTorque(PDTorque(kp, kd, target, link),
                                                         link), {
        "kp": (_scalar(0, unit=" (N m)"), REQUIRED), "kd": (_scalar(0, unit=" (N m s)"), 0.0),
        "target": (_vector(True), [0.0, 0.0, 1.0]), "link": (_integer(0), 0)}),
    "tip_force": (lambda force, point: TipForce(np.asarray(force), point), {
        "force": (_vector(unit=" (N)"), REQUIRED), "point": (_integer(), -1)}),
    "vibrating_support": (
        lambda amplitude, angular_frequency, direction, phase_deg: VibratingSupport(
            amplitude, angular_frequency, direction, math.radians(phase_deg)), {
            "amplitude": (_scalar(0, unit=" (m)"), REQUIRED),
            "angular_frequency": (_scalar(0, unit=" (rad/s)"), REQUIRED),
            "direction": (_vector(True), [0.0, 0.0, 1.0]),
            "phase_deg": (_angle(-360, 360), 0.0)}),
}


def _fields(path, where: str, table, schema: dict, ignore=()) -> dict:
    if not isinstance(table, dict):
        raise SceneFileError(path, where, "a table")
    for key in table:
        if key not in schema and key not in ignore:
            raise SceneFileError(path, f"{where}.{key}" if where else key,
                                 "no such field (expected one of "
                                 f"{', '.join(sorted(schema))})")
    out = {}
    for key, (kind, default) in schema.items():
        name = f"{where}.{key}" if where else key
        if key not in table:
            if default is REQUIRED:
                raise SceneFileError(path, name, f"missing; expected {kind.expected}")
            out[key] = default
            continue
        value = kind.check(table[key])
        if value is None:
            raise SceneFileError(path, name, f"expected {kind.expected}, got "
                                 f"{_show(table[key])}")
        out[key] = value
    return out


def _show(x) -> str:
    text = repr(x)
    return text if len(text) <= 40 else text[:37] + "..."


# ---- integrators: a fixed whitelist of names ----------------------------------------

def solvers() -> dict:
    """Integrator names a scene file may use -> `(factory, fixed_step)`. Adaptive diffrax
    solvers run under `Projected`; `rk4` is `Projected(RK4())` with fixed steps;
    `lie_rk4` is `LieRK4()` (adaptive); `variational`/`variational4` are
    `Variational(order=2/4)` (fixed steps; forced Lagrange-d'Alembert with forces)."""
    import diffrax

    import sphere_mech as sm

    table = {
        "tsit5": (lambda: sm.Projected(diffrax.Tsit5()), False),
        "dopri5": (lambda: sm.Projected(diffrax.Dopri5()), False),
        "dopri8": (lambda: sm.Projected(diffrax.Dopri8()), False),
        "kvaerno5": (lambda: sm.Projected(diffrax.Kvaerno5()), False),
        "rk4": (lambda: sm.Projected(sm.RK4()), True),
    }
    if hasattr(sm, "LieRK4"):
        table["lie_rk4"] = (lambda: sm.LieRK4(), False)
    if hasattr(sm, "Variational"):
        table["variational"] = (lambda: sm.Variational(order=2), True)
        table["variational4"] = (lambda: sm.Variational(order=4), True)
    return table


# ---- the whole file -----------------------------------------------------------------

@dataclasses.dataclass
class SceneSpec:
    """Everything a scene file says, checked and converted."""

    path: Path
    name: str
    scene: Scene
    y0: tuple
    solver_name: str
    solver: object
    fixed_step: bool
    rtol: float | None
    atol: float | None
    dt: float | None
    max_steps: int
    duration: float
    output_dt: float


TOP = {"name", "effects", "initial", "integrator", "time"}


def _effect(path, k: int, table):
    where = f"effects[{k}]"
    if not isinstance(table, dict):
        raise SceneFileError(path, where, "a table with a `type` field")
    kind = table.get("type")
    if kind not in EFFECTS:
        raise SceneFileError(path, f"{where}.type", "an effect type, one of "
                             + ", ".join(sorted(EFFECTS)) + f"; got {_show(kind)}")
    build, schema = EFFECTS[kind]
    values = _fields(path, where, table, schema, ignore=("type",))
    try:
        return build(**values)
    except ValueError as e:
        raise SceneFileError(path, where, f"{kind}: {e}") from None


def _check_indices(path, scene: Scene, effects):
    n = scene.n
    for k, e in enumerate(effects):
        where = f"effects[{k}]"
        idx = []
        if isinstance(e, Spring):
            idx = [(f"{where}.{f}", i) for f, i in zip("ab", e.ends, strict=True) if i is not None]
        elif isinstance(e, TipForce):
            idx = [(f"{where}.point", e.point)]
        elif isinstance(e, BaseTorque):
            idx = [(f"{where}.link", e.link)]
        elif isinstance(e, PairInteraction) and e.masses is not None:
            idx = [(f"{where}.masses", i) for i in e.masses]
            if e.charges is not None and len(e.charges) != len(e.masses):
                raise SceneFileError(path, f"{where}.charges",
                                     f"one charge per interacting mass ({len(e.masses)})")
        if isinstance(e, PairInteraction) and e.masses is None and e.charges is not None \
                and len(e.charges) != n:
            raise SceneFileError(path, f"{where}.charges", f"one charge per mass ({n})")
        if isinstance(e, Bending) and len(scene.bend_pairs()[0]) == 0:
            raise SceneFileError(path, where, "bending needs a chain with two links or more")
        for name, i in idx:
            if not -n <= i < n:
                raise SceneFileError(path, name, f"a mass index in [0, {n - 1}] (or negative "
                                     f"from the end), got {i}")


def _initial(path, table, n: int):
    if not isinstance(table, dict):
        raise SceneFileError(path, "initial", "a table")
    allowed = {"q", "qdot", "polar_deg", "azimuth_deg", "polar_rate_deg", "azimuth_rate_deg"}
    angles = {"polar_deg": _angle(0, 180), "azimuth_deg": _angle(-360, 360),
              "polar_rate_deg": _scalar(unit=" (deg/s)"),
              "azimuth_rate_deg": _scalar(unit=" (deg/s)")}
    for key in table:
        if key not in allowed:
            raise SceneFileError(path, f"initial.{key}", "no such field (expected q and qdot, "
                                 "or polar_deg and azimuth_deg with optional rates)")

    def values(key, kind, size):
        x = table[key]
        if not isinstance(x, list) or len(x) != size:
            raise SceneFileError(path, f"initial.{key}", f"an array of {size} entries (one per "
                                 f"sphere of the scene), got {_show(x)}")
        for a in x:
            if kind.check(a) is None:
                raise SceneFileError(path, f"initial.{key}",
                                     f"entries that are {kind.expected}, got {_show(a)}")
        return np.asarray([kind.check(a) for a in x], dtype=float)

    if "q" in table:
        if {"polar_deg", "azimuth_deg", "polar_rate_deg", "azimuth_rate_deg"} & set(table):
            raise SceneFileError(path, "initial", "either q (with qdot) or angles, not both")
        q = values("q", _vector(), n)
        norms = np.linalg.norm(q, axis=-1)
        bad = int(np.argmax(np.abs(norms - 1.0)))
        if abs(norms[bad] - 1.0) > UNIT_TOLERANCE:
            raise SceneFileError(path, "initial.q", f"unit vectors (length 1 within "
                                 f"{UNIT_TOLERANCE:g}), got length {norms[bad]:.6g} for "
                                 f"q[{bad}]")
        qdot = values("qdot", _vector(), n) if "qdot" in table else np.zeros((n, 3))
    else:
        for key in ("polar_deg", "azimuth_deg"):
            if key not in table:
                raise SceneFileError(path, f"initial.{key}", "missing; expected q (unit "
                                     "vectors) or polar_deg and azimuth_deg")
        th, ph = (np.radians(values(k, angles[k], n)) for k in ("polar_deg", "azimuth_deg"))
        rates = [np.radians(values(k, angles[k], n)) if k in table else np.zeros(n)
                 for k in ("polar_rate_deg", "azimuth_rate_deg")]
        if "qdot" in table and any(k in table for k in ("polar_rate_deg", "azimuth_rate_deg")):
            raise SceneFileError(path, "initial", "either qdot or angle rates, not both")
        st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
        q = np.stack([st * cp, st * sp, ct], axis=-1)
        d_th = np.stack([ct * cp, ct * sp, -st], axis=-1)
        d_ph = np.stack([-st * sp, st * cp, np.zeros(n)], axis=-1)
        qdot = rates[0][:, None] * d_th + rates[1][:, None] * d_ph
        if "qdot" in table:
            qdot = values("qdot", _vector(), n)
    normal = np.abs(np.sum(q * qdot, axis=-1))
    if np.any(normal > UNIT_TOLERANCE * (1.0 + np.linalg.norm(qdot, axis=-1))):
        raise SceneFileError(path, "initial.qdot", "velocities tangent to the spheres "
                             "(q_i . qdot_i = 0)")
    return q, qdot


def _integrator(path, table):
    table = {} if table is None else table
    names = solvers()
    schema = {"method": (_string(set(names)), "tsit5"),
              "rtol": (_scalar(0, True), None), "atol": (_scalar(0, True), None),
              "dt": (_scalar(0, True, " (s)"), None), "max_steps": (_integer(1), 100_000)}
    out = _fields(path, "integrator", table, schema)
    factory, fixed = names[out["method"]]
    if fixed:
        if out["dt"] is None:
            raise SceneFileError(path, "integrator.dt", f"missing; expected a step size in s "
                                 f"for the fixed-step method {out['method']}")
        for key in ("rtol", "atol"):
            if out[key] is not None:
                raise SceneFileError(path, f"integrator.{key}", f"not used by the fixed-step "
                                     f"method {out['method']} (give dt only)")
    else:
        out["rtol"] = 1e-8 if out["rtol"] is None else out["rtol"]
        out["atol"] = 1e-10 if out["atol"] is None else out["atol"]
    return out, factory(), fixed


def _read(path: Path) -> dict:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise SceneFileError(path, "(file)", "an existing scene file") from None
    except tomllib.TOMLDecodeError as e:
        raise SceneFileError(path, "(syntax)", f"valid TOML ({e})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise SceneFileError(path, "(file)", f"a readable UTF-8 text file ({e})") from None


def load_scene(path) -> SceneSpec:
    """Read and check a scene file (TOML, data only). Raises `SceneFileError`."""
    import jax.numpy as jnp

    path = Path(path)
    data = _read(path)
    for key in data:
        if key not in TOP:
            raise SceneFileError(path, key, "no such field (expected one of "
                                 + ", ".join(sorted(TOP)) + ")")
    name = _fields(path, "", {"name": data.get("name", path.stem)},
                   {"name": (_string(), path.stem)})["name"]
    tables = data.get("effects")
    if not isinstance(tables, list) or not tables:
        raise SceneFileError(path, "effects", "an array of effect tables ([[effects]] with "
                             "a type field)")
    effects = [_effect(path, k, t) for k, t in enumerate(tables)]
    try:
        scene = Scene(*effects)
    except ValueError as e:
        raise SceneFileError(path, "effects", str(e)) from None
    _check_indices(path, scene, effects)
    if "initial" not in data:
        raise SceneFileError(path, "initial", "missing; expected a table with q or angles")
    q, qdot = _initial(path, data["initial"], scene.n)
    integ, solver, fixed = _integrator(path, data.get("integrator"))
    if "time" not in data:
        raise SceneFileError(path, "time", "missing; expected a table with duration (s)")
    time = _fields(path, "time", data["time"], {"duration": (_scalar(0, True, " (s)"),
                                                             REQUIRED),
                                                "output_dt": (_scalar(0, True, " (s)"), None)})
    output_dt = time["output_dt"] or time["duration"] / 1000.0
    y0 = (jnp.asarray(q / np.linalg.norm(q, axis=-1, keepdims=True)), jnp.asarray(qdot))
    return SceneSpec(path, name, scene, y0, integ["method"], solver, fixed, integ["rtol"],
                     integ["atol"], integ["dt"], integ["max_steps"], time["duration"],
                     output_dt)
