"""mkdocs hooks of the sphere_mech site (mkdocs' built-in `hooks:`, no plugin to install).

- The notebooks and the benchmark figures join the site under their repository paths:
  pages link to `../notebooks/...` and `../benchmarks/results/...`, which works on a
  plain checkout, and the site resolves the same links.
- MathJax is copied into the site from the installed `django-static-mathjax` package
  (no CDN: the site displays without network access).
- The scene-file reference is generated from the schema that `sphere_mech._scene_files`
  derives from the effect Modules, so it cannot drift from what a file accepts.
- Checks, reported as warnings (so `mkdocs build --strict` fails on them): every name in
  `sphere_mech.__all__` has a `::: sphere_mech.NAME` entry in `docs/api.md` and a
  docstring that documents its arguments and return value; no page loads anything from
  the network.
"""

import functools
import importlib.util
import inspect
import logging
import re
import shutil
from pathlib import Path

import griffe
import markdown
import markdown.preprocessors
import mkdocs.plugins
import mkdocs.structure.files
import yaml

ROOT = Path(__file__).resolve().parent.parent
API_PAGE = ROOT / "docs" / "api.md"
MARKER = "<!-- scene-file-reference -->"
SHARED = ("notebooks", "benchmarks/results")  # repository folders the site serves
MATHJAX = ("tex-svg.js", "input", "ui", "a11y", "adaptors")  # from its es5/ (SVG: no fonts)

log = logging.getLogger("mkdocs.hooks.sphere_mech")


# --- Markdown: a list may follow its heading line directly ------------------------------


class _ListAfterLine(markdown.preprocessors.Preprocessor):
    """Docstrings write `**Arguments:**` with the list on the next line; Python-Markdown
    needs a blank line before a list, so insert one (outside fenced code)."""

    def run(self, lines):
        out, verbatim = [], False
        for line in lines:
            if line.lstrip().startswith(("```", "~~~", "$$")):  # code or display math
                verbatim = line.count("$$") != 2 and not verbatim
            heading = out and re.fullmatch(r"\S.*:(\*\*)?\s*", out[-1])  # "**Arguments:**"
            if not verbatim and heading and re.match(r"\s*- ", line):
                out.append("")
            out.append(line)
        return out


class ListAfterLine(markdown.Extension):
    def extendMarkdown(self, md):
        md.preprocessors.register(_ListAfterLine(md), "list_after_line", 25)


@mkdocs.plugins.event_priority(100)  # before mkdocstrings builds its Markdown converter
def on_config(config):
    config.markdown_extensions.append(ListAfterLine())
    config.mdx_configs.setdefault("pymdownx.snippets", {})["base_path"] = [str(ROOT)]
    return config


# --- Files: notebooks and benchmark figures ---------------------------------------------


@mkdocs.plugins.event_priority(100)  # before mkdocs-jupyter turns notebooks into pages
def on_files(files, config):
    for folder in SHARED:
        for path in sorted((ROOT / folder).glob("*")):
            if path.suffix in (".ipynb", ".png", ".md"):
                files.append(
                    mkdocs.structure.files.File(
                        f"{folder}/{path.name}",
                        src_dir=str(ROOT),
                        dest_dir=config.site_dir,
                        use_directory_urls=config.use_directory_urls,
                    )
                )
    return files


def on_page_markdown(markdown_text, page, config, files):
    for folder in SHARED:  # ../notebooks/x.ipynb (checkout) -> notebooks/x.ipynb (site)
        markdown_text = markdown_text.replace(f"](../{folder}/", f"]({folder}/")
    if MARKER in markdown_text:
        markdown_text = markdown_text.replace(MARKER, scene_file_reference())
    if page.file.src_uri == "api.md":
        for problem in undocumented(markdown_text):
            log.warning(problem)
    return markdown_text


def on_post_page(html, page, config):
    for url in re.findall(r'<(?:script|link|img)\b[^>]*(?:src|href)="(https?://[^"]+)"', html):
        log.warning(f"{page.file.src_uri}: loads {url} from the network")
    return html


def on_post_build(config):
    spec = importlib.util.find_spec("mathjax")
    es5 = Path(spec.origin).parent / "static" / "mathjax" / "es5"
    target = Path(config.site_dir) / "assets" / "mathjax"
    for name in MATHJAX:
        if (es5 / name).is_dir():
            shutil.copytree(es5 / name, target / name, dirs_exist_ok=True)
        else:
            target.mkdir(parents=True, exist_ok=True)
            shutil.copy2(es5 / name, target / name)


# --- Docstrings: what a public name must document ---------------------------------------


def listed(doc: str) -> dict[str, str]:
    """The entries of a docstring's markdown lists that start with code names:
    `- \\`a\\`, \\`b\\`: text` gives `{"a": "text", "b": "text"}` (continuation lines
    joined)."""
    out, names = {}, []
    for line in doc.splitlines():
        entry = re.match(r"\s*- ((?:`\w+`(?:,\s*|\s+and\s+)?)+):?\s*(.*)", line)
        more = re.match(r"\s+((?:`\w+`(?:,\s*)?)+):\s*(.*)", line)
        if entry or (more and names and not out[names[0]]):  # names may span two lines
            names = [*([] if entry else names), *re.findall(r"`(\w+)`", (entry or more)[1])]
            out.update(dict.fromkeys(names, (entry or more)[2]))
        elif names and line.startswith(" ") and line.strip():
            out.update({n: f"{out[n]} {line.strip()}" for n in names})
        else:
            names = []
    return out


def _documentation(obj) -> str:
    """The class docstring and its `__init__`'s (rendered together), or the docstring."""
    own = inspect.getdoc(obj) or ""
    init = obj.__dict__.get("__init__") if inspect.isclass(obj) else None
    return own + "\n" + (inspect.getdoc(init) or "" if inspect.isfunction(init) else "")


def _parameters(obj) -> list[str]:
    return [
        p.name
        for p in inspect.signature(obj).parameters.values()
        if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD) and p.name != "self"
    ]


@functools.cache
def _hidden_names() -> tuple[str, ...]:
    """The patterns of member names the API reference hides (mkdocs.yml's `filters`)."""
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    plugin = next(p["mkdocstrings"] for p in config["plugins"] if "mkdocstrings" in p)
    return tuple(f.removeprefix("!") for f in plugin["handlers"]["python"]["options"]["filters"])


def _members(cls) -> dict[str, object]:
    """The methods a class's API entry shows: defined in the class itself, public by the
    `filters` of mkdocs.yml, with a docstring of their own (mkdocstrings hides members
    without one)."""
    hidden = _hidden_names()
    return {
        name: value
        for name, value in vars(cls).items()
        if inspect.isfunction(value)
        and value.__doc__
        and not any(re.search(pattern, name) for pattern in hidden)
    }


def problems(name: str, obj, module: griffe.Module) -> list[str]:
    """What the docstring of public name `name` lacks: a description (data, abstract
    classes, enumerations); constructor arguments (classes); arguments and return value
    (functions). Every parameter must be a list entry under `**Arguments:**` (or, for a
    record such as `FitResult`, `**Attributes:**`)."""
    if not (inspect.isclass(obj) or inspect.isfunction(obj)):
        doc = module[name].docstring
        return (
            []
            if doc and doc.value.strip()
            else ["no description (an attribute docstring after the assignment)"]
        )
    doc = _documentation(obj)
    if not doc.strip():
        return ["no docstring"]
    if inspect.isclass(obj) and (name.startswith("Abstract") or not _parameters(obj)):
        return []
    out = []
    missing = [p for p in _parameters(obj) if p not in listed(doc)]
    heading = (
        ("**Arguments:**", "**Attributes:**") if inspect.isclass(obj) else ("**Arguments:**",)
    )  # a record (FitResult, ...) lists its attributes
    if _parameters(obj) and not any(h in doc for h in heading):
        out.append(f"no {' or '.join(heading)} section")
    if missing:
        out.append(f"arguments not documented: {', '.join(missing)}")
    if inspect.isfunction(obj) and "**Returns:**" not in doc:
        out.append("no **Returns:** section")
    return out


def undocumented(api_markdown: str | None = None) -> list[str]:
    """Every problem of the API reference: names of `sphere_mech.__all__` without an
    entry in docs/api.md, and public names (and the methods their entries show) whose
    docstrings lack something."""
    import sphere_mech

    api_markdown = API_PAGE.read_text() if api_markdown is None else api_markdown
    entries = set(re.findall(r"^::: sphere_mech\.(\w+)\s*$", api_markdown, re.M))
    module = griffe.load("sphere_mech", search_paths=[str(ROOT)], resolve_aliases=True)
    out = [
        f"docs/api.md: {name} (in sphere_mech.__all__) has no '::: sphere_mech.{name}' entry"
        for name in sphere_mech.__all__
        if name not in entries
    ]
    out += [
        f"docs/api.md: '::: sphere_mech.{name}' is not in sphere_mech.__all__"
        for name in sorted(entries - set(sphere_mech.__all__))
    ]
    for name in sphere_mech.__all__:
        obj = getattr(sphere_mech, name)
        out += [f"sphere_mech.{name}: {p}" for p in problems(name, obj, module)]
        for method, function in _members(obj).items() if inspect.isclass(obj) else ():
            out += [f"sphere_mech.{name}.{method}: {p}" for p in problems(method, function, module)]
    return out


# --- The scene-file reference -----------------------------------------------------------


def _toml(value, files) -> str:
    if value is inspect.Parameter.empty:
        return "required"
    if value is None:
        return "optional"
    kind = next((k for k, cls in files.COMMANDS.items() if type(value) is cls), None)
    if kind is not None:  # a default command: its table with its own defaults
        return f'`{{ type = "{kind}" }}`'
    return f"`{_plain(value)}`"


def _plain(value) -> str:
    """A default as TOML writes it: tuples (nested too) as arrays."""
    if isinstance(value, tuple | list):
        return "[" + ", ".join(map(_plain, value)) + "]"
    return str(value)


def _summary(doc: str) -> str:
    return " ".join(doc.split("\n\n")[0].split())


def _effect_table(kind: str, cls, files) -> str:
    schema_of = files.schema(cls)
    fields = listed(_documentation(cls))
    cell = lambda text: text.replace("|", "\\|")
    rows = [
        f"| `{field}` | {' or '.join(files.KINDS[k][0] for k in kinds)} | "
        f"{_toml(default, files)} | {cell(fields.get(field, ''))} |"
        for field, (kinds, default) in schema_of.items()
    ]
    return "\n".join(
        [
            f"### `{kind}`",
            "",
            f"[`sm.{cls.__name__}`][sphere_mech.{cls.__name__}]: {_summary(inspect.getdoc(cls))}",
            "",
            "| field | a file gives | default | meaning |",
            "|---|---|---|---|",
            *rows,
            "",
        ]
    )


def scene_file_reference() -> str:
    """Markdown for every table and field a scene file may hold, from the schema that
    `sphere_mech._scene_files` derives from the effect Modules."""
    from sphere_mech import _scene_files as files

    initial = [f"| `{key}` | {what} |" for key, (_, what, _) in files.INITIAL.items()]
    initial += [
        f"| `{key}` | {what}, with a `base` effect (default zeros) |"
        for key, what in files.BASE_INITIAL.items()
    ]
    initial += [
        f"| `{key}` | {what}, with a `rigid_base` effect (default: the identity, zero) |"
        for key, what in files.ATTITUDE_INITIAL.items()
    ]
    simulate = [f"| `{key}` | {what} |" for key, what in files.SIMULATE.items()]
    return "\n".join(
        [
            "### Effects (`[[effects]]`)",
            "",
            "One table per effect; `type` names it (the class name in snake_case). Effect "
            "types: " + ", ".join(f"`{k}`" for k in files.EFFECTS) + ". Controllers (inline "
            "tables where Python takes a function): "
            + ", ".join(f"`{k}`" for k in files.DRIVES)
            + ". Flight commands (inline tables in `geometric_control`'s `command`): "
            + ", ".join(f"`{k}`" for k in files.COMMANDS)
            + ".",
            "",
            *(_effect_table(kind, cls, files) for kind, cls in files.EFFECTS.items()),
            *(_effect_table(kind, cls, files) for kind, cls in files.DRIVES.items()),
            *(_effect_table(kind, cls, files) for kind, cls in files.COMMANDS.items()),
            "### Initial state (`[initial]`)",
            "",
            "Either `q` (and optionally `qdot`), or `polar_deg` and `azimuth_deg` with optional "
            "rates; each one value for every sphere or a list with one per sphere. With a "
            "`base` effect, also `base` and `base_velocity`, one number per axis of the base "
            '(the state is then `{"base": (m,), "spheres": (n, 3)}`); with a `rigid_base`, '
            "`base` and `base_velocity` (3 numbers) and `attitude` and `angular_velocity` "
            '(the state is then `{"attitude": (1, 3, 3), "base": (3,), "spheres": (n, 3)}`).',
            "",
            "| key | expected |",
            "|---|---|",
            *initial,
            "",
            "### Integration (`[simulate]`)",
            "",
            "Keyword arguments of [`sm.simulate`][sphere_mech.simulate], with its defaults.",
            "",
            "| key | expected |",
            "|---|---|",
            *simulate,
            "",
            "Solver names: `Projected(<solver>)`, "
            "`LieRK(<solver>[, action='SE3'|'SO3xR3'][, error='state'|'algebra'])`, "
            "`Variational`, `Variational(order=4)`, "
            + ", ".join(f"`{k}`" for k in files.PLAIN_SOLVERS)
            + " (parentheses optional).",
            "",
        ]
    )
