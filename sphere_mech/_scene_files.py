"""Scene files: TOML data (never code). The schema is the effect Modules' (`type`: the class
name in snake_case; fields, defaults, kinds: the constructor's), and the Modules check the
values, so files and Python reject the same input with the same words."""

import dataclasses
import inspect
import math
import re
import tomllib
import types
import typing
from collections.abc import Callable
from pathlib import Path

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import nonfinite, off_rotation, off_tangent, off_unit
from ._geometry import hat
from ._scene import forces, kinetic, potentials, rotorcraft
from ._scene.base import MAX_MAGNITUDE, ParameterError, overflow
from ._scene.scene import Scene
from ._simulate import simulate
from ._solve import OptionError, options
from ._solvers.names import (  # noqa: F401 (DIFFRAX_SOLVERS, PLAIN_SOLVERS: the file format)
    DIFFRAX_SOLVERS,
    MAX_SOLVER_LENGTH,
    PLAIN_SOLVERS,
    parse_solver,
)
from ._spaces import ATTITUDE, BASE, chain_state


class SceneFileError(ValueError):
    """A problem in a scene file, reported as `<file>: <field>: <what was expected>`
    (a `ValueError`; the command line prints it and exits with status 2).

    **Arguments:**
    - `path`, `field`, `expected`: the scene file, where in it (e.g. `effects[0].masses` or
      `simulate.t1`) and what was expected there (or the effect's own message).
    """

    def __init__(self, path, field: str, expected: str):
        self.path, self.field, self.expected = str(path), field, expected
        super().__init__(f"{self.path}: {field}: {expected}")


def _snake(name: str) -> str:
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", name).lower()


EFFECTS = {
    _snake(c.__name__): c
    for c in (
        *(kinetic.Chain, kinetic.Particles, kinetic.SharedSphere, kinetic.Base, kinetic.RigidBase),
        *(potentials.Gravity, potentials.Spring, potentials.Bending, potentials.PairInteraction),
        *(forces.JointDamping, forces.BaseTorque, forces.TipForce, forces.VibratingSupport),
        *(forces.BaseForce, forces.BodyTorque, rotorcraft.Rotors),
    )
}
DRIVES = {
    _snake(c.__name__): c
    for c in (forces.PDTorque, forces.PDPosition, forces.Harmonic, rotorcraft.GeometricControl)
}
"""Controllers, written as inline tables where Python takes a function."""
COMMANDS = {_snake(c.__name__): c for c in (rotorcraft.Hover, rotorcraft.Line, rotorcraft.Circle)}
"""Flight commands of `GeometricControl`, written as inline tables."""


def _show(x) -> str:
    text = repr(x)
    return text if len(text) <= 40 else text[:37] + "..."


def _integer(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _numbers(x) -> bool:
    """A number or a rectangular (nested) array of them. NaN, infinities and empty arrays
    pass: the checks that read them say why not, in the words they use in Python."""
    if _integer(x):
        return abs(x) <= MAX_MAGNITUDE  # a float: TOML integers may be longer
    if isinstance(x, float):
        return True
    if not isinstance(x, list):
        return False
    return all(_numbers(a) for a in x) and len({np.shape(a) for a in x}) <= 1


def _number(x) -> bool:
    return _numbers(x) and np.ndim(x) == 0


KINDS = {
    # numbers, arrays and indices as Python gives them; anything else (a bool, a string, a
    # table, a float for an integer) too: the effect refuses it in its own words
    int: ("an integer", lambda x: x),
    jax.Array: (
        "a number or an array of numbers",
        lambda x: np.asarray(x, dtype=float) if _numbers(x) else x,
    ),
    tuple[int, ...]: ("an array of integers", lambda x: tuple(x) if isinstance(x, list) else x),
    Callable: (f"an inline table {{ type = ... }} ({', '.join(DRIVES)})", lambda x: None),
    rotorcraft.AbstractCommand: (
        f"an inline table {{ type = ... }} ({', '.join(COMMANDS)})",
        lambda x: None,
    ),
}
"""Annotation -> (what a file must give, the TOML value converted or `None`)."""


def schema(cls) -> dict[str, tuple[tuple, object]]:
    """`{field: (kinds, default)}` of a Module's constructor (`Parameter.empty`: required)."""
    fields = {f.name: f.type for f in dataclasses.fields(cls)}
    out = {}
    for name, p in inspect.signature(cls).parameters.items():
        kind = fields[name] if p.annotation in (p.empty, typing.Any) else p.annotation
        kinds = typing.get_args(kind) if isinstance(kind, types.UnionType) else (kind,)
        if rotorcraft.AbstractCommand in kinds:  # a file gives a command's table, not a drive
            kinds = (rotorcraft.AbstractCommand,)
        out[name] = (tuple(k for k in kinds if k is not types.NoneType), p.default)
    return out


def _no_unknown(path, where: str, table: dict, allowed, expected: str = "") -> None:
    extra = [k for k in table if k not in allowed]
    if extra:
        raise SceneFileError(
            path,
            f"{where}.{extra[0]}" if where else extra[0],
            f"no such field (expected {expected or 'one of ' + ', '.join(allowed)})",
        )


def _checked(path, where: str, build, effects=()):
    """`build()`; its `ValueError` a `SceneFileError` at `where` (or the effect it names)."""
    try:
        return build()
    except (ParameterError, OptionError) as e:
        if effects:
            where = f"effects[{next(k for k, effect in enumerate(effects) if effect is e.effect)}]"
        raise SceneFileError(path, where + (f".{e.field}" if e.field else ""), str(e)) from None
    except ValueError as e:
        raise SceneFileError(path, where, str(e)) from None


def _module(path, where: str, table, registry: dict, what: str):
    """Build the Module a table describes; its own checks speak for it."""
    kind = table.get("type") if isinstance(table, dict) else table
    if kind not in registry:
        expected = f"{what}, one of {', '.join(registry)}; got {_show(kind)}"
        raise SceneFileError(path, f"{where}.type", expected)
    cls, values = registry[kind], {}
    fields = schema(cls)
    summary = " ".join(cls.__doc__.split()).split(". ")[0]  # the docstring's first sentence
    expected = f"one of {', '.join(fields)}; {kind}: {summary}"
    _no_unknown(path, where, table, ["type", *fields], expected)
    for key, (kinds, default) in fields.items():
        expected, x = " or ".join(KINDS[k][0] for k in kinds), table.get(key)
        if key not in table and default is inspect.Parameter.empty:
            raise SceneFileError(path, f"{where}.{key}", f"missing; expected {expected}")
        if isinstance(x, dict) and (rotorcraft.AbstractCommand in kinds or Callable in kinds):
            wanted, other = (DRIVES, "a controller type"), (COMMANDS, "a command type")
            if rotorcraft.AbstractCommand in kinds:
                wanted, other = other, wanted
            # the other kind (a drive where a command goes): built, the effect refuses it
            registry, what = other if x.get("type") in other[0] else wanted
            values[key] = _module(path, f"{where}.{key}", x, registry, what)
        elif key in table:
            values[key] = next((v for k in kinds if (v := KINDS[k][1](x)) is not None), None)
            if values[key] is None:
                raise SceneFileError(path, f"{where}.{key}", f"expected {expected}, got {_show(x)}")
    return _checked(path, where, lambda: cls(**values))


def _scene(path, tables) -> Scene:
    if not isinstance(tables, list):  # an empty list is Scene()'s to refuse
        expected = "an array of effect tables ([[effects]] with a type field)"
        raise SceneFileError(path, "effects", expected)
    effects = [
        _module(path, f"effects[{k}]", t, EFFECTS, "an effect type") for k, t in enumerate(tables)
    ]
    return _checked(path, "effects", lambda: Scene(*effects), effects)


INITIAL = {
    "q": ((3,), "unit vectors [x, y, z]", None),
    "qdot": ((3,), "vectors [x, y, z] (1/s) tangent to the spheres", None),
    "polar_deg": ((), "angles in degrees from +z within [0, 180]", (0, 180)),
    "azimuth_deg": ((), "angles in degrees about z within [-360, 360]", (-360, 360)),
    "polar_rate_deg": ((), "rates in deg/s", None),
    "azimuth_rate_deg": ((), "rates in deg/s", None),
}
"""`[initial]` keys -> (shape of one entry (for every sphere), what is expected, range)."""
BASE_INITIAL = {
    BASE: "the base's coordinates (m), one per axis of the Base",
    f"{BASE}_velocity": "the base's velocity (m/s), one per axis of the Base",
}
"""`[initial]` keys of a scene with a base (default zeros)."""
ATTITUDE_INITIAL = {
    ATTITUDE: "the body's rotation matrix (body to world), 3 rows of 3 numbers",
    "angular_velocity": "the body angular velocity Omega (rad/s), 3 numbers",
}
"""`[initial]` keys of a scene with a `RigidBase` (default: the identity, zero)."""


def _array(path, field: str, x, shapes, expected: str, bounds=None) -> np.ndarray:
    """`x` as floats: numbers of one of `shapes` within `bounds` (default: `MAX_MAGNITUDE`);
    NaN and infinities get simulate's words, naming the key."""
    low, high = bounds or (-MAX_MAGNITUDE, MAX_MAGNITUDE)
    if _numbers(x) and np.shape(x) in shapes:
        a, name = np.asarray(x, dtype=float), field.rsplit(".", 1)[-1]
        if not np.all(np.isfinite(a)):
            raise SceneFileError(path, field, f"{nonfinite(a, name)[1]} Got {_show(x)}.")
        if message := overflow(name, a):
            raise SceneFileError(path, field, message)
    if not (_numbers(x) and np.shape(x) in shapes and low <= np.min(x) <= np.max(x) <= high):
        raise SceneFileError(path, field, f"{expected}, got {_show(x)}")
    return np.asarray(x, dtype=float)


def _per_sphere(path, table, key: str, n: int) -> np.ndarray:
    item, expected, bounds = INITIAL[key]
    at_most = "" if bounds else f" (at most {MAX_MAGNITUDE:g} in magnitude)"
    expected += f"{at_most}: one for all spheres or an array of {n} (one per sphere)"
    x = _array(path, f"initial.{key}", table[key], (item, (n, *item)), expected, bounds)
    return np.broadcast_to(x, (n, *item))


def _initial(path, table, scene: Scene):
    """The initial state `[initial]` gives: `(q0, qdot0)`, dicts with a `Base`."""
    if not isinstance(table, dict):
        expected = f"a table with q or polar_deg and azimuth_deg, got {_show(table)}"
        raise SceneFileError(path, "initial", expected)
    base = {} if scene.base is None else BASE_INITIAL
    attitude = {} if scene.rigid_body is None else ATTITUDE_INITIAL
    expected = "q and qdot, or polar_deg and azimuth_deg with optional rates" + (
        ", and base and base_velocity" if base else " (base: the scene has no Base)"
    )
    expected += ", attitude and angular_velocity" if attitude else ""
    _no_unknown(path, "initial", table, [*INITIAL, *base, *attitude], expected)
    q, qdot = _spheres_initial(path, table, scene.n)
    if scene.base is None:
        return q, qdot
    m = scene.base.m
    count = f"{m} number" + "s" * (m > 1) + f" (at most {MAX_MAGNITUDE:g} in magnitude)"
    x, v = (
        _array(path, f"initial.{key}", table.get(key, [0.0] * m), [(m,)], f"{what}: {count}")
        for key, what in BASE_INITIAL.items()
    )
    x, v = jnp.asarray(x, q.dtype), jnp.asarray(v, q.dtype)
    if not attitude:
        return chain_state(x, q), chain_state(v, qdot)
    R, Omega = _attitude_initial(path, table, q.dtype)
    return chain_state(x, q, R[None]), chain_state(v, qdot, (R @ hat(Omega))[None])


def _attitude_initial(path, table, dtype):
    """A rigid base's rotation and body angular velocity from `[initial]`."""
    magnitude = f" (at most {MAX_MAGNITUDE:g} in magnitude)"
    (key, what), (rate, rate_what) = ATTITUDE_INITIAL.items()
    R = table.get(key, np.eye(3).tolist())
    if not (_numbers(R) and np.shape(R) == (3, 3)):  # not finite or far off: simulate's words
        raise SceneFileError(path, f"initial.{key}", f"{what}, got {_show(R)}")
    R = jnp.asarray(np.asarray(R, dtype=float), dtype)
    for bad, message in (nonfinite(R, "the attitude"), off_rotation(R[None], "the attitude")):
        if bad:
            got = f" Got {np.asarray(R).tolist()}."
            raise SceneFileError(path, f"initial.{key}", message + got)
    Omega = _array(
        path, f"initial.{rate}", table.get(rate, [0.0] * 3), [(3,)], rate_what + magnitude
    )
    return R, jnp.asarray(Omega, dtype)


def _spheres_initial(path, table, n: int):
    if any(
        v in table and any(k.endswith(e) for k in table)
        for v, e in (("q", "_deg"), ("qdot", "_rate_deg"))
    ):
        raise SceneFileError(path, "initial", "either q and qdot, or angles and rates")
    if "q" in table:
        q, qdot = _per_sphere(path, table, "q", n), np.zeros((n, 3))
        off, message = off_unit(q)  # simulate's check and words
        if off:
            norms = np.linalg.norm(q, axis=-1)
            bad = int(np.argmax(np.abs(norms - 1.0)))
            message += f" Got length {norms[bad]:.6g} for q[{bad}]."
            raise SceneFileError(path, "initial.q", message)
    else:
        missing = [key for key in ("polar_deg", "azimuth_deg") if key not in table]
        if missing:
            expected = "missing; expected q (unit vectors) or polar_deg and azimuth_deg"
            raise SceneFileError(path, f"initial.{missing[0]}", expected)
        th, ph, rate_th, rate_ph = (
            np.radians(_per_sphere(path, table, k, n)) if k in table else np.zeros(n)
            for k in list(INITIAL)[2:]
        )
        st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
        q = np.stack([st * cp, st * sp, ct], axis=-1)
        e_th = np.stack([ct * cp, ct * sp, -st], axis=-1)
        e_ph = np.stack([-st * sp, st * cp, np.zeros(n)], axis=-1)
        qdot = rate_th[:, None] * e_th + rate_ph[:, None] * e_ph
    if "qdot" in table:
        qdot = _per_sphere(path, table, "qdot", n)
    off, message = off_tangent(q, qdot, "qdot")  # simulate's check and words
    if off:
        raise SceneFileError(path, "initial.qdot", message)
    return jnp.asarray(q / np.linalg.norm(q, axis=-1, keepdims=True)), jnp.asarray(qdot)


MAX_SAVED = 10**8
"""The most numbers a run may save: save points x the numbers of a state (`q` and
`qdot`), 800 MB in float64."""


SIMULATE = {
    "solver": "a solver name",
    "t0": "a time in s",
    "t1": "a time in s after t0",
    "dt0": "a step > 0 (s)",
    "rtol": "a number > 0",
    "atol": "a number > 0",
    "max_steps": "an integer from 1 to 2147483647",
}
"""The keys of `[simulate]`: keyword arguments of `sm.simulate` (defaults as there)."""
_UNITS = {"t0": " s", "t1": " s", "dt0": " s", "rtol": "", "atol": ""}
"""The `[simulate]` numbers bounded by `MAX_MAGNITUDE`, and their units."""


@dataclasses.dataclass
class SceneSpec:
    """Everything a scene file says, checked and converted (what `load_scene` returns):
    the scene, its initial state and the arguments of `sm.simulate`.

    **Attributes:**
    - `path`, `name`: the file, and the scene's `name` (default: the file's stem).
    - `scene`: the `Scene` built from `[[effects]]`.
    - `y0`: the initial state `(q0, qdot0)` from `[initial]`: `(n, 3)` arrays (with a
      `Base`, states of `sm.chain_space(m, n)`).
    - `solver`, `solver_name`: the solver named in `[simulate]` (default
      `Projected(diffrax.Tsit5())`), and as the file spells it.
    - `t0`, `t1`, `dt0`: start and end times (s), and the (initial) step (s) or `None`.
    - `rtol`, `atol`: tolerances of adaptive solvers, or `None` (`simulate`'s defaults).
    - `max_steps`: the most steps the run may take.
    - `save_dt`: the spacing of the saved trajectory (s), from `[output]` (the saved
      times: `t0` to `t1` in the whole number of equal intervals closest to it, at least
      one).
    """

    path: Path
    name: str
    scene: Scene
    y0: tuple
    solver: diffrax.AbstractSolver
    solver_name: str
    t0: float
    t1: float
    dt0: float | None
    rtol: float | None
    atol: float | None
    max_steps: int
    save_dt: float

    @property
    def fixed_steps(self) -> bool:
        """Whether the run takes fixed steps of (at most) `dt0`: a solver without an error
        estimate, as `simulate` decides."""
        opts = options(
            dtype=np.float64, solver=self.solver, dt0=self.dt0, rtol=self.rtol, atol=self.atol
        )
        return isinstance(opts.controller, diffrax.ConstantStepSize)


def _table(path, data, key: str, allowed) -> dict:
    table = data.get(key, {})
    if not isinstance(table, dict):
        raise SceneFileError(path, key, "a table")
    _no_unknown(path, key, table, allowed)
    return table


def _simulate_args(path, data, t1=None) -> dict:
    table = _table(path, data, "simulate", SIMULATE)
    if "t1" not in table:
        raise SceneFileError(path, "simulate.t1", "missing; expected the end time in s")
    defaults = inspect.signature(simulate).parameters
    out = {k: table.get(k, defaults[k].default) for k in SIMULATE if k != "t1"}
    out |= {"t1": table["t1"], "solver_name": table.get("solver", "Projected(Tsit5)")}
    if not isinstance(out["solver_name"], str):
        expected = f"expected {SIMULATE['solver']}, got {_show(out['solver_name'])}"
        raise SceneFileError(path, "simulate.solver", expected)
    out["solver"] = _checked(path, "simulate.solver", lambda: parse_solver(out["solver_name"]))
    _checked(  # the options simulate would refuse (types, values), with its words
        path, "simulate", lambda: options(dtype=np.float64, **{k: out[k] for k in SIMULATE})
    )
    if not out["t1"] > out["t0"]:
        raise SceneFileError(
            path, "simulate.t1", f"expected {SIMULATE['t1']}, got {_show(out['t1'])}"
        )
    for key, unit in _UNITS.items():
        if out[key] is not None and not abs(out[key]) <= MAX_MAGNITUDE:
            expected = f"{key} must be at most {MAX_MAGNITUDE:g}{unit} in magnitude"
            raise SceneFileError(path, f"simulate.{key}", f"{expected} (got {_show(out[key])})")
    out["file_t1"] = out["t1"]
    if t1 is not None:  # the command line's --t1
        out["t1"] = checked_end(path, out["t0"], t1, "--t1")
    return out


def checked_end(path, t0: float, t1, name: str) -> float:
    """Another end time `t1` (the command line's `--t1`, `run_scene`'s `t1`) as a float,
    checked as `[simulate] t1` is; errors name it `name`."""
    if not (isinstance(t1, int | float) and not isinstance(t1, bool) and t0 < t1 <= MAX_MAGNITUDE):
        expected = f"a time in s after t0 = {t0:g} and at most {MAX_MAGNITUDE:g}"
        raise SceneFileError(path, name, f"{name} must be {expected} (got {t1})")
    return float(t1)


def _save_dt(path, table: dict, args: dict) -> float:
    """`[output] save_dt` (default: the file's run / 1000)."""
    save_dt = table.get("save_dt", (args["file_t1"] - args["t0"]) / 1000)
    if not (_number(save_dt) and 0 < save_dt < math.inf):
        expected = f"expected a step > 0 (s), got {_show(save_dt)}"
        raise SceneFileError(path, "output.save_dt", expected)
    return save_dt


def check_extent(spec, t1: float):
    """A run of `spec` to `t1` saves at most `MAX_SAVED` numbers and, with fixed steps, takes
    at most `max_steps` steps, counted as the run takes them (each segment between saves as
    many equal steps as `dt0` fits)."""
    from ._program import fixed_steps_taken

    path, t0, save_dt = spec.path, spec.t0, spec.save_dt
    intervals = (t1 - t0) / save_dt
    numbers = 2 * sum(np.size(x) for x in jax.tree.leaves(spec.y0[0]))  # of a state
    if not (intervals + 1) * numbers <= MAX_SAVED:
        expected = f"at most {MAX_SAVED:.0e} saved numbers from t0 to t1 ((t1 - t0) / save_dt"
        expected += f" = {intervals:.3g} intervals, {numbers} numbers a state) (got {save_dt:g})"
        raise SceneFileError(path, "output.save_dt", f"save_dt must give {expected}")
    if spec.fixed_steps:
        steps, _, segments = fixed_steps_taken(t0, t1, save_dt, spec.dt0)
        if steps > spec.max_steps:
            expected = f"at most max_steps = {spec.max_steps} fixed steps from t0 to t1"
            got = f"{spec.dt0:g}: {steps} steps in {segments} segments"
            raise SceneFileError(path, "simulate.dt0", f"dt0 must give {expected} (got {got})")


def _read(path: Path) -> dict:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise SceneFileError(path, "(syntax)", f"valid TOML ({e})") from None
    except (OSError, UnicodeDecodeError) as e:
        expected = f"an existing, readable UTF-8 text file ({e})"
        raise SceneFileError(path, "(file)", expected) from None


def load_scene(path, t1=None) -> SceneSpec:
    """Read and check a scene file (TOML, data only: no code is evaluated).

    **Arguments:**
    - `path`: the file (a `str` or `Path`).
    - `t1`: another end time (the command line's `--t1`), checked as `[simulate] t1`
      (errors name `--t1`); the default `save_dt` stays the file's.

    **Returns:** a `SceneSpec`. Raises `SceneFileError` naming the file, the field and
    what was expected, with the effect's own message for a value it rejects.
    """
    path = Path(path)
    data = _read(path)
    _no_unknown(path, "", data, ("name", "effects", "initial", "simulate", "output"))
    name = data.get("name", path.stem)
    if not isinstance(name, str):
        raise SceneFileError(path, "name", f"a string, got {_show(name)}")
    scene = _scene(path, data.get("effects"))
    y0 = _initial(path, data.get("initial"), scene)
    args = _simulate_args(path, data, t1)
    save_dt = _save_dt(path, _table(path, data, "output", ("save_dt",)), args)
    del args["file_t1"]
    spec = SceneSpec(path, name, scene, y0, save_dt=save_dt, **args)
    check_extent(spec, spec.t1)
    return spec
