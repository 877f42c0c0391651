"""MkDocs hook: the command and config reference pages, generated from the code.

``reference/cli.md`` walks the argparse parser of :func:`relloc.cli.build_parser` (every command,
every option, its default); ``reference/config.md`` walks the config dataclasses from
:class:`relloc.config.TeamConfig` down (every field, its TOML section, type, default, unit and
docstring); ``reference/api.md`` has one mkdocstrings block for every public module of
``src/relloc`` (none of whose names starts with ``_``), one section per package. Nothing is
written to the tree: the pages exist only in the build, so they cannot go stale. Run as a
script, it prints the pages (``python docs/gen_reference.py``).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import re
import sys
import textwrap
import typing
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

UNIT = re.compile(
    r"\(((?:m|s|ms|rad|deg|Hz|m/s|rad/s|m per sqrt\(s\)|rad per sqrt\(s\)|s\^-1|1/s|"
    r"m\^2|rad\^2|bytes|MiB|particles|robots|dimensionless)(?:[ ,;)][^)]*)?)\)"
)

SUFFIX_UNITS = {"_deg": "deg", "_s": "s", "_m": "m"}


# ---------------------------------------------------------------- command line


def _option_row(action: argparse.Action) -> str:
    names = ", ".join(f"`{o}`" for o in action.option_strings) or f"`{action.dest}`"
    if action.metavar and action.option_strings and action.nargs != 0:
        names += f" `{action.metavar}`"
    elif action.choices and action.nargs != 0:
        names += " `{" + ",".join(map(str, action.choices)) + "}`"
    default = action.default
    if action.nargs == 0 or default in (None, argparse.SUPPRESS) or not action.option_strings:
        shown = ""
    else:
        shown = f"`{default}`"
    help_text = (action.help or "").replace("|", "\\|").replace("\n", " ")
    if action.required and action.option_strings:
        help_text = "**required**; " + help_text
    return f"| {names} | {shown} | {help_text} |"


def _command_section(parser: argparse.ArgumentParser, name: str, level: int) -> list[str]:
    out = [f"{'#' * level} `{name}`", ""]
    if parser.description:
        out += [parser.description, ""]
    out += ["```text", parser.format_usage().strip().removeprefix("usage: "), "```", ""]
    rows = [
        _option_row(a)
        for a in parser._actions
        if not isinstance(a, argparse._SubParsersAction | argparse._HelpAction)
    ]
    if rows:
        out += ["| option | default | meaning |", "| --- | --- | --- |", *rows, ""]
    if parser.epilog:
        out += [parser.epilog, ""]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                out += _command_section(sub, f"{name} {sub_name}", min(level + 1, 4))
    return out


def cli_page() -> str:
    from relloc.cli import build_parser

    parser = build_parser()
    lines = [
        "# Command line",
        "",
        "Generated from the argparse parser of `relloc.cli` at build time: every command and",
        "option, with its default. `relloc COMMAND --help` prints the same.",
        "",
    ]
    lines += _command_section(parser, "relloc", 2)
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- config


def _field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings (the string literal after a field) of a dataclass."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs: dict[str, str] = {}
    for stmt, nxt in zip(body, [*body[1:], None], strict=True):
        if (
            isinstance(stmt, ast.AnnAssign)
            and isinstance(stmt.target, ast.Name)
            and isinstance(nxt, ast.Expr)
            and isinstance(nxt.value, ast.Constant)
            and isinstance(nxt.value.value, str)
        ):
            docs[stmt.target.id] = inspect.cleandoc(nxt.value.value)
    return docs


def _is_config(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _type_name(tp: Any) -> str:
    text = getattr(tp, "__name__", None) if isinstance(tp, type) else None
    return text or str(tp).replace("typing.", "")


def _default(f: dataclasses.Field[Any]) -> str:
    if f.default is not dataclasses.MISSING:
        return f"`{f.default!r}`"
    if f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
        return "" if _is_config(type(value)) else f"`{value!r}`"
    return "**required**"


def _unit(name: str, doc: str) -> str:
    """The first unit the docstring names in parentheses, else the one the name ends in."""
    m = UNIT.search(doc)
    if m:
        return m.group(1).split(",")[0].split(";")[0]
    return next((u for suffix, u in SUFFIX_UNITS.items() if name.endswith(suffix)), "")


def _config_section(cls: type, section: str, seen: set[type]) -> list[str]:
    hints = typing.get_type_hints(cls)
    docs = _field_docs(cls)
    title = f"`[{section}]`" if section else "top level"
    if section == "robots":
        title = "`[[robots]]` (one table per robot)"
    out = [f"## {title}: `{cls.__name__}`", ""]
    if cls.__doc__:
        out += [inspect.cleandoc(cls.__doc__), ""]
    out += ["| field | type | default | unit | meaning |", "| --- | --- | --- | --- | --- |"]
    nested: list[tuple[type, str]] = []
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        inner = next((a for a in typing.get_args(tp) if _is_config(a)), tp)
        key = f"{section}.{f.name}" if section else f.name
        if _is_config(inner):
            nested.append((inner, key))
        doc = docs.get(f.name, "")
        meaning = " ".join(doc.split()).replace("|", "\\|")
        if _is_config(inner):
            meaning = (meaning + " " if meaning else "") + f"See `{key}` below."
        out.append(
            f"| `{f.name}` | `{_type_name(tp)}` | {_default(f)} | {_unit(f.name, doc)} | {meaning} |"
        )
    out.append("")
    for sub, key in nested:
        if sub not in seen:
            seen.add(sub)
            out += _config_section(sub, key, seen)
    return out


def config_page() -> str:
    from relloc.config import TeamConfig

    lines = [
        "# Team config (TOML)",
        "",
        "Generated from the config dataclasses of `relloc.config` at build time: every field",
        "with its TOML section, type, default and unit (where the field's docstring names one).",
        "A key the dataclasses do not know is an error when the config is loaded.",
        "",
    ]
    lines += _config_section(TeamConfig, "", {TeamConfig})
    return "\n".join(lines) + "\n"


def kinds_page() -> str:
    from relloc import estimators
    from relloc.estimators.registry import capability_table

    lines = [
        "# Estimator kinds",
        "",
        "Generated from the registry of `relloc.estimators` at build time: every kind a config's",
        "`[filter] kind` may name, with what it can do. `auto` picks among them in the order of",
        "their priority, keeping those that can run the config's modes (which: [Which filter",
        "kind](../explanation/filter-kinds.md)); adding a kind: [Extending](../howto/extending.md).",
        "",
        capability_table(),
        "Priorities (lowest first): "
        + ", ".join(
            f"`{k.name}` {k.priority}"
            for k in sorted(estimators.KINDS.values(), key=lambda k: k.priority)
        )
        + ".",
        "",
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------- Python API

SRC = Path(__file__).resolve().parents[1] / "src"


def public_modules(root: Path = SRC / "relloc") -> list[str]:
    """Every module and package below ``root`` none of whose name parts starts with ``_``."""
    names = []
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if not any(part.startswith("_") for part in parts):
            names.append(".".join(parts))
    return sorted(names)


def api_page() -> str:
    """mkdocstrings reads the modules statically (griffe): nothing is imported, so the modules
    that need an extra (PyTorch for ``relloc.ranging``, Zenoh for the live engine) render too."""
    lines = [
        "# Python API",
        "",
        "Generated from the docstrings by mkdocstrings, one section per package with every public",
        "module of `relloc` in it. `examples/quickstart.py` shows the pieces together: a source, a",
        "pipeline of localizers, the engine, the evaluation. Longer derivations behind a module are",
        "in [Internals](../explanation/internals.md).",
        "",
    ]
    modules = public_modules()
    packages = [m for m in modules if (SRC / m.replace(".", "/") / "__init__.py").exists()]
    for package in packages:
        lines += [f"## `{package}`", ""]
        for module in modules:
            parent = module.rpartition(".")[0]
            if module == package or (parent == package and module not in packages):
                lines += [f"::: {module}", "    options:", "      heading_level: 3", ""]
    return "\n".join(lines) + "\n"


PAGES = {
    "reference/cli.md": cli_page,
    "reference/config.md": config_page,
    "reference/kinds.md": kinds_page,
    "reference/api.md": api_page,
}


def on_files(files: Any, config: Any) -> Any:
    from mkdocs.structure.files import File

    for uri, make in PAGES.items():
        files.append(File.generated(config, uri, content=make()))
    return files


if __name__ == "__main__":
    for make in PAGES.values():
        print(make())
