"""The documentation site: `mkdocs build --strict` passes (no broken link, missing API
entry, undocumented argument, notebook that does not render, network resource), and
what it builds holds every public name, every notebook and the scene-file reference."""

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

import sphere_mech as sm
from sphere_mech import _scene_files

ROOT = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("docs_hooks", ROOT / "docs" / "hooks.py")
hooks = importlib.util.module_from_spec(spec)
spec.loader.exec_module(hooks)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """Build the site once, strictly, into a temporary directory, from another working
    directory (the build does not depend on it)."""
    out = tmp_path_factory.mktemp("site")
    env = os.environ | {
        "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])]),
        "NO_MKDOCS_2_WARNING": "1",
    }
    run = subprocess.run(
        [
            sys.executable,
            "-m",
            "mkdocs",
            "build",
            "--strict",
            "--config-file",
            str(ROOT / "mkdocs.yml"),
            "--site-dir",
            str(out / "site"),
        ],
        cwd=out,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    warnings = [line for line in run.stderr.splitlines() if "WARNING" in line or "ERROR" in line]
    assert run.returncode == 0 and not warnings, run.stderr[-5000:]
    return out / "site"


def test_every_public_name_is_in_the_api_reference(site):
    html = (site / "api" / "index.html").read_text()
    missing = [name for name in sm.__all__ if f'id="sphere_mech.{name}"' not in html]
    assert not missing
    assert len(sm.__all__) >= 60  # the reference is not vacuous


def test_docstrings_document_arguments_and_returns():
    assert hooks.undocumented() == []


def test_the_api_check_finds_what_is_missing():
    # An API page without entries: every public name is reported.
    found = hooks.undocumented("# API\n")
    assert {
        f"docs/api.md: {n} (in sphere_mech.__all__) has no '::: sphere_mech.{n}' entry"
        for n in sm.__all__
    } <= set(found)

    # A function whose docstring misses an argument and the return value.
    def f(x, y):
        """Does something.

        **Arguments:**
        - `x`: the first one.
        """

    assert hooks.problems("f", f, None) == [
        "arguments not documented: y",
        "no **Returns:** section",
    ]

    # A method the API reference shows, without its argument and return value.
    class C:
        def method(self, x):
            """Does something with `x`."""

        def _private(self, x):
            """Not shown."""

    assert list(hooks._members(C)) == ["method"]
    assert hooks.problems("method", C.method, None) == [
        "no **Arguments:** section",
        "arguments not documented: x",
        "no **Returns:** section",
    ]
    assert hooks.listed("- `a`, `b`: two\n  more\n- `c`:\n") == {
        "a": "two more",
        "b": "two more",
        "c": "",
    }


def test_notebooks_render_with_their_outputs(site):
    for notebook in sorted((ROOT / "notebooks").glob("*.ipynb")):
        html = (site / "notebooks" / notebook.stem / "index.html").read_text()
        assert "jp-OutputArea-output" in html and "<img" in html, notebook.name


def test_scene_file_reference_lists_every_effect_and_field(site):
    html = (site / "scenes" / "index.html").read_text()
    for kind, cls in (_scene_files.EFFECTS | _scene_files.DRIVES | _scene_files.COMMANDS).items():
        assert f"<code>{kind}</code>" in html, kind
        for field in _scene_files.schema(cls):
            assert f"<td><code>{field}</code></td>" in html, (kind, field)
    initial = [*_scene_files.INITIAL, *_scene_files.BASE_INITIAL, *_scene_files.ATTITUDE_INITIAL]
    for key in [*initial, *_scene_files.SIMULATE]:
        assert f"<td><code>{key}</code></td>" in html, key


def test_math_is_served_by_the_site(site):
    assert (site / "assets" / "mathjax" / "tex-svg.js").stat().st_size > 100_000
    html = (site / "concepts" / "index.html").read_text()
    assert 'class="arithmatex"' in html and "assets/mathjax/tex-svg.js" in html


def test_readme_quick_example_runs():
    """The README's quick example (its one Python block, at most 15 lines) runs as shown
    and gives what its comments say."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    blocks = text.split("```python\n")[1:]
    assert len(blocks) == 1
    code = blocks[0].split("```")[0]
    assert len(code.strip().splitlines()) <= 15
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    assert namespace["qddot"].shape == (2, 3)
    sol = namespace["sol"]
    assert sol.result == sm.RESULTS.successful
    assert float(sol.ts[-1]) == 10.0
    assert float(sm.constraint_error(sol.ys[0][-1])) < 1e-12
