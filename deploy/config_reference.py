"""The configuration reference: every key of the run configuration with its type, default and meaning, read from the
config dataclasses themselves (a field's meaning is the string written under it), so there is one source.

`impulse config describe [KEY]` prints it (one key, or a section's keys); docs/config.md is this module's Markdown
rendering, and a test fails when the file is stale (regenerate it with
`python -m impulse.deploy.config_reference > docs/config.md`).
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import textwrap
import typing
from dataclasses import dataclass
from typing import Any

from impulse.deploy.run_config import RunConfig


@dataclass(frozen=True)
class Key:
    """One configuration key."""

    name: str
    """Dotted, as overrides spell it (`ppo.num_envs`)."""
    type: str
    default: str
    meaning: str
    """The field's own docstring, whitespace normalised; empty where it has none."""


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The strings written directly under the fields of dataclass `cls` (attribute docstrings), by field name."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs = {}
    for field, following in zip(body, body[1:] + [None], strict=True):
        if (isinstance(field, ast.AnnAssign) and isinstance(field.target, ast.Name)
                and isinstance(following, ast.Expr) and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)):
            docs[field.target.id] = " ".join(following.value.value.split())
    return docs


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is typing.Literal:
        return " | ".join(repr(option) for option in typing.get_args(tp))
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        return " | ".join("None" if arg is type(None) else _type_name(arg) for arg in typing.get_args(tp))
    if origin is tuple:
        return f"list of {_type_name(typing.get_args(tp)[0])}" if typing.get_args(tp) else "list"
    return getattr(tp, "__name__", str(tp))


def _default(field: dataclasses.Field) -> Any:
    if field.default is not dataclasses.MISSING:
        return field.default
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return None


def _show(value: Any) -> str:
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, tuple):
        return repr(list(value))
    return repr(value)


def keys(root: type = RunConfig, prefix: str = "") -> list[Key]:
    """Every leaf key under `root`, in declaration order, sections after the root's own keys."""
    hints = typing.get_type_hints(root)
    docs = field_docs(root)
    leaves, sections = [], []
    for field in dataclasses.fields(root):
        tp = hints[field.name]
        if dataclasses.is_dataclass(tp):
            sections += keys(tp, f"{prefix}{field.name}.")
        else:
            leaves.append(Key(f"{prefix}{field.name}", _type_name(tp), _show(_default(field)),
                              docs.get(field.name, "")))
    return leaves + sections


def section_meanings(root: type = RunConfig) -> dict[str, str]:
    """A section's meaning: the docstring of its field in the root, else its dataclass's docstring."""
    hints = typing.get_type_hints(root)
    docs = field_docs(root)
    return {field.name: docs.get(field.name) or " ".join((inspect.getdoc(hints[field.name]) or "").split())
            for field in dataclasses.fields(root) if dataclasses.is_dataclass(hints[field.name])}


def matching(key: str | None, root: type = RunConfig) -> list[Key]:
    """The keys `key` names: itself, or every key under it when it is a section (`ppo`); all when None."""
    every = keys(root)
    if not key:
        return every
    return [k for k in every if k.name == key or k.name.startswith(key.rstrip(".") + ".")]


def as_text(selected: list[Key], width: int = 100) -> str:
    """The keys for a terminal: name, type and default on one line, the meaning wrapped under it."""
    lines = []
    for k in selected:
        lines.append(f"{k.name} ({k.type}) = {k.default}")
        if k.meaning:
            lines += textwrap.wrap(k.meaning, width, initial_indent="    ", subsequent_indent="    ")
    return "\n".join(lines)


def as_markdown(root: type = RunConfig) -> str:
    """docs/config.md: one table per section."""
    out = ["# Configuration reference", "",
           "Every key of a run's configuration (`config.toml`, `--config FILE.toml`, `key=value` overrides), with its",
           "type, default and meaning. Generated from the config dataclasses by `python -m",
           "impulse.deploy.config_reference > docs/config.md` (a test fails when this file is stale);",
           "`impulse config describe [KEY]` prints the same in a terminal.", ""]
    every = keys(root)
    groups: dict[str, list[Key]] = {}
    for k in every:
        groups.setdefault(k.name.split(".")[0] if "." in k.name else "", []).append(k)
    meanings = section_meanings(root)
    for section, members in groups.items():
        out += [f"## {'`' + section + '`' if section else 'Top level'}", ""]
        if section and meanings.get(section):
            out += [meanings[section], ""]
        out += ["| key | type | default | meaning |", "|---|---|---|---|"]
        for k in members:
            cell = lambda text: text.replace("|", "\\|")  # noqa: E731
            out.append(f"| `{k.name}` | {cell(k.type)} | `{cell(k.default)}` | {cell(k.meaning)} |")
        out.append("")
    moved = getattr(root, "MOVED_KEYS", {})
    if moved:
        out += ["## Moved keys", "",
                "Still read under their old names (in a file or an override), with a warning line naming the new one.",
                "", "| old key | now |", "|---|---|"]
        out += [f"| `{old}` | `{new}` |" for old, new in moved.items()]
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    print(as_markdown(), end="")
