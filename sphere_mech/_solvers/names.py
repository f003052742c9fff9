"""Solvers named as in Python (`"Projected(Tsit5)"`, in scene files and `solver=`), and the one
check that turns `solver=` into a solver instance."""

import contextlib
import re

import diffrax

from .liegroup import LieRK, LieRK4
from .projected import Projected
from .rk4 import RK4
from .variational import Variational

DIFFRAX_SOLVERS = tuple(
    "Euler Heun Midpoint Ralston Bosh3 Tsit5 Dopri5 Dopri8 "
    "ImplicitEuler Kvaerno3 Kvaerno4 Kvaerno5".split()
)
"""diffrax's ODE solvers a file may name (bare: unprojected, as in Python)."""
PLAIN_SOLVERS = {"RK4": RK4, "LieRK4": LieRK4} | {n: getattr(diffrax, n) for n in DIFFRAX_SOLVERS}
MAX_SOLVER_LENGTH = 200
"""The longest solver a file may spell (`Projected(...)` nests)."""


def parse_solver(text: str) -> diffrax.AbstractSolver:
    """`"Projected(Tsit5)"` -> `Projected(diffrax.Tsit5())`, parsed over a whitelist (never
    evaluated); `ValueError` for anything else or over `MAX_SOLVER_LENGTH` characters."""
    if len(text) > MAX_SOLVER_LENGTH:
        raise ValueError(
            f"solver must be at most {MAX_SOLVER_LENGTH} characters (got "
            f"{len(text)}: {repr(text if len(text) <= 40 else text[:37] + '...')})"
        )
    match = re.fullmatch(r"\s*(\w+)\s*(?:\((.*)\))?\s*", text)
    name, inner = match.groups("") if match else ("", "")
    order = re.fullmatch(r"\s*(?:order\s*=\s*(\d+)\s*)?", inner)
    if name == "Projected" and inner:
        return Projected(parse_solver(inner))
    if name == "LieRK" and inner:
        solver, *options = inner.split(",")
        return LieRK(parse_solver(solver), **dict(map(_lie_option, options)))
    if name == "Variational" and order:
        return Variational(order=int(order[1] or 2))
    if name in PLAIN_SOLVERS and not inner.strip():
        return PLAIN_SOLVERS[name]()
    raise ValueError(
        f"a solver spelled as in Python: Projected(<solver>), "
        f"LieRK(<solver>[, action='SE3'|'SO3xR3'][, error='state'|'algebra']), "
        f"RK4, LieRK4, Variational, Variational(order=4) or a diffrax ODE solver "
        f"({', '.join(DIFFRAX_SOLVERS)}); got {text!r}"
    )


def _lie_option(text: str) -> tuple[str, str]:
    """`action='SE3'` -> `("action", "SE3")`."""
    match = re.fullmatch(r"""\s*(action|error)\s*=\s*(['"])(\w+)\2\s*""", text)
    if match is None:
        raise ValueError(
            f"LieRK's options are action='SE3'|'SO3xR3' and "
            f"error='state'|'algebra'; got {text.strip()!r}"
        )
    return match[1], match[3]


def solver_name(solver: diffrax.AbstractSolver) -> str:
    """A solver as scene files spell it, for messages: `Projected(RK4)`, `Tsit5`."""
    if isinstance(solver, diffrax.AbstractWrappedSolver):
        return f"{type(solver).__name__}({solver_name(solver.solver)})"
    return type(solver).__name__


def as_solver(solver) -> diffrax.AbstractSolver:
    """`simulate`'s `solver=` as an instance: an instance as it is, a name as in scene files
    (`parse_solver`), a solver class needing no arguments instantiated; else `ValueError`."""
    if isinstance(solver, diffrax.AbstractSolver):
        return solver
    if isinstance(solver, str):
        try:
            return parse_solver(solver)
        except ValueError as e:
            text = str(e)
            raise ValueError(
                text if text.startswith("solver") else f"solver must be a diffrax solver or {text}"
            ) from None
    if isinstance(solver, type) and issubclass(solver, diffrax.AbstractSolver):
        with contextlib.suppress(TypeError):
            return solver()
    raise ValueError(
        f"solver must be a diffrax solver instance, e.g. "
        f"sm.Projected(diffrax.Tsit5()), or its name, e.g. 'Projected(Tsit5)' "
        f"(got {solver!r})"
    )
