"""The layers of DESIGN.md section 5: a module of sphere_mech imports only from its own
layer or lower ones (function-level imports included), so that, e.g., no module below
`_solvers/` imports from `_solvers/`, `_scene/`, `_fit/` or `_cli/`."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "sphere_mech"
LAYERS = (  # lowest first; a package (`_solvers`, `_scene`, ...) is one entry
    ("_custom_types", "_misc", "_linalg"),
    ("_geometry", "_lie", "_checks"),
    ("_spaces",),
    ("_system", "_lagrangian", "_hamiltonian", "_inertia", "_momentum", "_legendre", "_anderson"),
    ("_term", "_results", "_solvers"),
    ("_adjoint", "_solve"),
    ("_simulate", "_batch"),
    ("_scene",),
    ("_scene_files", "_fit", "_program", "_report", "_drawing", "_animation"),
    ("_cli", "__init__"),
)
LAYER = {name: i for i, names in enumerate(LAYERS) for name in names}


def imports(path: Path) -> set[str]:
    """The top-level sphere_mech modules (or packages) `path` imports from."""
    package = path.relative_to(ROOT).parent.parts
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = list(package)[: len(package) - (node.level - 1)]
            parts = base + (node.module.split(".") if node.module else [])
            found.add(parts[0] if parts else node.names[0].name)
    return found


MODULES = sorted(ROOT.rglob("*.py"))


def test_every_module_has_a_layer():
    tops = {p.relative_to(ROOT).parts[0].removesuffix(".py") for p in MODULES}
    assert tops == set(LAYER)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(ROOT)))
def test_imports_only_from_its_layer_or_below(path):
    own = path.relative_to(ROOT).parts[0].removesuffix(".py")
    above = {m for m in imports(path) - {own} if LAYER[m] > LAYER[own]}
    assert not above, f"{own} (layer {LAYER[own]}) imports from higher layers: {above}"
