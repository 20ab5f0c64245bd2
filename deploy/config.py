"""Typed run configuration: dataclass defaults, then a TOML file, then `key=value` overrides.

Every value is checked against the dataclass field's type before anything runs, because a misspelt key or a
wrong type found after a GPU job has started costs hours, and a silently ignored key is worse. Errors are
`ConfigError`s whose message is written for the person at the terminal: the full dotted key, where the value
came from, what was expected, and the closest valid keys.

Supported field types: int, float (an int is accepted; NaN and infinities are refused), bool, str, `Literal[...]`,
`X | None`, `tuple[...]` and `list[...]` of those, and nested dataclasses (TOML tables). A table whose class names a
`SHORTHAND` field may be given a plain value, meaning that field (`curriculum=sfl` is `curriculum.method=sfl`). An
integral float such as `1e9` is accepted for an int. A key that moved to another section (the root class's
`MOVED_KEYS`, old dotted name -> new) is still read under its old name, in a file or an override, with one warning
line saying the new one. TOML has no null, so an optional field is set to None with the
word `none` (the string "none" in a file), and `config_to_toml` writes None the same way; a resolved config
therefore reads back to an equal instance.

Input is read defensively, since a config file or an override is whatever a person typed or pointed at: a file must
be a regular file (a directory, a FIFO or a device such as /dev/zero is refused before it is opened) of at most
`MAX_CONFIG_BYTES`, read as bytes and decoded as UTF-8; an override at most `MAX_OVERRIDE_BYTES` of UTF-8 text.
Every such problem, a NUL character in a value included, is a one-line `ConfigError` that names the file (with the
byte offset, or the line and column) or the override, never a traceback.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import logging
import math
import os
import stat
import tomllib
import types
import typing
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar, Union

import tomli_w

T = TypeVar("T")

log = logging.getLogger("impulse.config")

NONE_WORD = "none"
CONFIG_FILENAME = "config.toml"

MAX_CONFIG_BYTES = 1 << 20
"""A config file larger than this (1 MiB; the shipped ones are a few KiB) is refused: at most this many bytes and
one more are read, so a path such as /dev/zero that slips past the regular-file check still ends at once."""
MAX_OVERRIDE_BYTES = 1 << 16
"""The longest `key=value` override accepted, in bytes of UTF-8 (64 KiB; the kernel caps one argument at 128 KiB)."""
_SHOWN_CHARS = 100
"""How much of a long key, value or override an error message quotes."""
_SHOWN_PATH_CHARS = 400
"""How much of a long path an error message quotes."""


class ConfigError(ValueError):
    """A configuration that cannot be applied. The message is complete and meant to be shown as it is."""


@dataclass(frozen=True)
class _Value:
    """A leaf value waiting to be type-checked, with where it came from for the error message."""

    value: Any
    source: str
    raw: str | None = None
    """The override text as typed: used as is where a string is expected (`name=123` means "123")."""


class _Mismatch(Exception):
    """A value does not fit a type; turned into a ConfigError by the caller that knows the key."""


def resolve_config(cls: type[T], toml_path: Path | None = None, overrides: Iterable[str] = ()) -> T:
    """Build a `cls` instance from its defaults, the TOML file (if any), then the overrides, in that order."""
    tree: dict[str, Any] = {}
    if toml_path is not None:
        source = f"from {_shown_path(toml_path)}"
        _merge(cls, cls, tree, _moved_tables(cls, _read_toml(Path(toml_path)), source), "", source=source)
    for item in overrides:
        key, raw = _split_override(item)
        source = f"from override '{_shown(item)}'"
        _merge_dotted(cls, tree, _moved_key(cls, key, source), _parse_value(raw), source=source, raw=raw)
    return _build(cls, tree, "", base=None)


def apply_overrides(instance: T, overrides: Iterable[str], source: str = "override") -> T:
    """`instance` with `key=value` overrides applied (keys relative to its type), checked exactly as
    `resolve_config` checks them: how a live service validates a change to its settings."""
    cls = type(instance)
    tree: dict[str, Any] = {}
    for item in overrides:
        key, raw = _split_override(item)
        shown = f"from {source} '{_shown(item)}'"
        _merge_dotted(cls, tree, _moved_key(cls, key, shown), _parse_value(raw), source=shown, raw=raw)
    return _build(cls, tree, "", base=instance)


def config_from_dict(cls: type[T], data: dict[str, Any], source: str) -> T:
    """A `cls` instance from TOML-shaped data (as `config_to_dict` or a dataset's attributes hold a section),
    checked as a TOML file is; `source` names where the data came from in errors."""
    tree: dict[str, Any] = {}
    _merge(cls, cls, tree, _moved_tables(cls, data, source), "", source=source)
    return _build(cls, tree, "", base=None)


def load_run_config(cls: type[T], run_dir: Path | str, overrides: Iterable[str] = ()) -> T:
    """The config a run directory was started with (its config.toml), then the overrides: how a run is resumed
    and how `impulse launch` hands its config to the processes it starts."""
    saved = Path(run_dir) / CONFIG_FILENAME
    if not saved.is_file():
        raise ConfigError(f"{run_dir} has no {CONFIG_FILENAME}; is it a run directory?")
    return resolve_config(cls, saved, overrides)


def config_to_dict(instance: Any) -> dict[str, Any]:
    """The instance as plain TOML-ready data: tables for dataclasses, lists for sequences, "none" for None."""
    return {f.name: _plain(getattr(instance, f.name)) for f in dataclasses.fields(instance) if f.init}


def config_to_toml(instance: Any) -> str:
    """The instance as TOML text that `resolve_config` reads back to an equal instance."""
    return tomli_w.dumps(config_to_dict(instance))


def write_resolved_config(instance: Any, run_dir: Path | str) -> Path:
    """Write `config.toml` into the run directory (created if needed), so a run's outputs say what made them.

    Written to a temporary file and renamed, so a crash never leaves a half-written config beside checkpoints.
    """
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / CONFIG_FILENAME
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(config_to_toml(instance), encoding="utf-8")
    os.replace(tmp, path)
    return path


# ---- reading sources -------------------------------------------------------------------------------------------


def read_config_bytes(path: Path, limit: int = MAX_CONFIG_BYTES) -> bytes:
    """The bytes of the config file `path`, or a ConfigError saying why it cannot be one.

    The path is checked with `stat` before it is opened, so that a directory, a FIFO (which would block the open) or
    a device such as /dev/zero (which never ends) is refused by name; it is then opened without blocking, checked
    again on the open file (the path may have changed in between), and at most `limit` + 1 bytes are read, so that
    nothing can make this read forever or fill the memory.
    """
    shown = _shown_path(path)
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise ConfigError(f"config file not found: {shown}") from None
    except NotADirectoryError:
        raise ConfigError(f"config file not found: {shown} (a part of the path is a file)") from None
    except ValueError:  # os.stat refuses a path with a NUL character
        raise ConfigError(f"config file '{shown}': a path cannot hold a NUL character") from None
    except OSError as e:
        raise ConfigError(f"cannot read config file {shown}: {e.strerror or e}") from None
    _check_regular(info, shown, limit)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as e:
        raise ConfigError(f"cannot read config file {shown}: {e.strerror or e}") from None
    with os.fdopen(fd, "rb") as f:
        _check_regular(os.fstat(fd), shown, limit)
        try:
            data = f.read(limit + 1)
        except OSError as e:
            raise ConfigError(f"cannot read config file {shown}: {e.strerror or e}") from None
    if len(data) > limit:
        raise ConfigError(f"config file {shown} is larger than {limit:,} bytes: is it a TOML config file?")
    return data


def _check_regular(info: os.stat_result, shown: str, limit: int) -> None:
    """Refuse what `info` describes unless it is a regular file of at most `limit` bytes (as its size reads)."""
    if stat.S_ISDIR(info.st_mode):
        raise ConfigError(f"config file {shown} is a directory: give a TOML file")
    if not stat.S_ISREG(info.st_mode):
        raise ConfigError(f"config file {shown} is not a regular file (a device, pipe or socket): give a TOML file")
    if info.st_size > limit:
        raise ConfigError(f"config file {shown} is {info.st_size:,} bytes, larger than {limit:,}: is it a TOML "
                          "config file?")


def read_config_text(path: Path, limit: int = MAX_CONFIG_BYTES) -> str:
    """The text of the config file `path` (`read_config_bytes`) decoded as UTF-8; a ConfigError names the first byte
    that is not UTF-8 by its offset and line."""
    data = read_config_bytes(path, limit)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise ConfigError(f"config file {_shown_path(path)} is not UTF-8 text: byte 0x{data[e.start]:02x} at offset "
                          f"{e.start} (line {line}): {e.reason}") from None


def _read_toml(path: Path) -> dict[str, Any]:
    text = read_config_text(path)
    shown = _shown_path(path)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:  # its message ends with "(at line L, column C)"
        raise ConfigError(f"{shown}: invalid TOML: {e}") from None
    except RecursionError:
        raise ConfigError(f"{shown}: invalid TOML: arrays or inline tables nested too deeply") from None
    except ValueError as e:  # an integer of more digits than Python converts from text
        raise ConfigError(f"{shown}: invalid TOML: {_shown(str(e))}") from None


def _moved_key(root: type, key: str, source: str) -> str:
    """The key an override names now: its new name if it is one of `root.MOVED_KEYS`' old ones (said once)."""
    new = getattr(root, "MOVED_KEYS", {}).get(key)
    if new is None:
        return key
    log.warning("config key '%s' (%s) is now '%s': read as that; write '%s'", key, source, new, new)
    return new


def _moved_tables(root: type, data: dict[str, Any], source: str) -> dict[str, Any]:
    """TOML-shaped `data` with each of `root.MOVED_KEYS`' old keys moved to its new place (said once each); a key
    given under both names is refused."""
    moved = getattr(root, "MOVED_KEYS", {})
    if not moved:
        return data
    data = {name: dict(value) if isinstance(value, dict) else value for name, value in data.items()}
    for old, new in moved.items():
        old_table, _, old_name = old.rpartition(".")
        table = data.get(old_table)
        if not isinstance(table, dict) or old_name not in table:
            continue
        new_table, _, new_name = new.rpartition(".")
        target = data.setdefault(new_table, {})
        if not isinstance(target, dict) or new_name in target:
            raise ConfigError(f"config key '{old}' ({source}) is now '{new}', which is set too: keep only '{new}'")
        target[new_name] = table.pop(old_name)
        log.warning("config key '%s' (%s) is now '%s': read as that; write '%s'", old, source, new, new)
    return data


def _split_override(item: str) -> tuple[str, str]:
    _check_override_text(item)
    key, sep, raw = item.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError(f"override '{_shown(item)}' is not of the form key=value")
    return key, raw.strip()


def _check_override_text(item: str) -> None:
    """Refuse an override that is not UTF-8 text (the command line gives undecodable bytes as lone surrogates), that
    holds a NUL character, or that is longer than MAX_OVERRIDE_BYTES."""
    if not isinstance(item, str):
        raise ConfigError(f"override {item!r} is not text")
    try:
        data = item.encode("utf-8", "surrogateescape")
        data.decode("utf-8")
    except UnicodeEncodeError as e:
        raise ConfigError(f"override '{_shown(item)}' is not UTF-8 text (character {e.start})") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"override '{_shown(item)}' is not UTF-8 text: byte 0x{data[e.start]:02x} at offset "
                          f"{e.start}") from None
    if len(data) > MAX_OVERRIDE_BYTES:
        raise ConfigError(f"override '{_shown(item)}' is {len(data):,} bytes long; at most {MAX_OVERRIDE_BYTES:,}")
    if "\x00" in item:
        raise ConfigError(f"override '{_shown(item)}' holds a NUL character")


def _parse_value(raw: str) -> Any:
    """TOML value syntax where it parses (numbers, booleans, arrays, quoted strings), else the text itself."""
    if "\n" in raw:
        return raw
    try:
        return tomllib.loads(f"v = {raw}")["v"]
    except (ValueError, RecursionError):  # not TOML (TOMLDecodeError), too many digits, nested too deeply
        return raw


# ---- merging sources into one tree, checking keys --------------------------------------------------------------


def _merge(
    root: type, cls: type, tree: dict[str, Any], data: dict[str, Any], prefix: str, source: str,
    raw: str | None = None,
) -> None:
    """Merge TOML-shaped data into the tree for `cls`; unknown keys fail here, where the source is known."""
    types_ = _field_types(cls)
    for key, value in data.items():
        dotted = prefix + key
        if key not in types_:
            raise ConfigError(_unknown_key_message(root, cls, dotted, source))
        sub = _dataclass_in(types_[key])
        shorthand = getattr(sub, "SHORTHAND", None)
        if sub is not None and shorthand and not isinstance(value, dict):
            value = {shorthand: value}  # `curriculum=sfl` means `curriculum.method=sfl`
        if sub is not None and isinstance(value, dict):
            node = tree.get(key)
            if not isinstance(node, dict):
                node = tree[key] = {}
            _merge(root, sub, node, value, dotted + ".", source)
        else:
            if _holds_nul(value):
                raise ConfigError(f"config key '{_shown(dotted)}' holds a NUL character ({source})")
            tree[key] = _Value(value, source, raw)


def _merge_dotted(root: type, tree: dict[str, Any], key: str, value: Any, source: str, raw: str) -> None:
    parts = key.split(".")
    if any(not p.strip() for p in parts):
        raise ConfigError(f"malformed config key '{_shown(key)}' in {source}")
    cls, prefix = root, ""
    for part in parts[:-1]:
        types_ = _field_types(cls)
        dotted = prefix + part
        if part not in types_:
            raise ConfigError(_unknown_key_message(root, cls, dotted, source))
        sub = _dataclass_in(types_[part])
        if sub is None:
            raise ConfigError(f"unknown config key '{_shown(key)}' ({source}): '{_shown(dotted)}' is a value, not a "
                              "table")
        node = tree.get(part)
        if not isinstance(node, dict):
            node = tree[part] = {}
        tree, cls, prefix = node, sub, dotted + "."
    _merge(root, cls, tree, {parts[-1]: value}, prefix, source, raw)


def _unknown_key_message(root: type, cls: type, dotted: str, source: str) -> str:
    prefix, _, name = dotted.rpartition(".")
    prefix = prefix + "." if prefix else ""
    level_keys = list(_field_types(cls))
    paths = _all_paths(root)
    leaves: dict[str, list[str]] = {}
    for path in paths:
        leaves.setdefault(path.rpartition(".")[2], []).append(path)
    suggestions = [prefix + k for k in difflib.get_close_matches(name, level_keys, n=3, cutoff=0.6)]
    if not suggestions:
        # Whole-path matching catches a key in the wrong section or a mistyped separator; paths in the key's own
        # section are left out of it, since their shared prefix alone makes them look close. Only when the key's
        # own section has nothing close: `ppo.learning_rat` means `ppo.learning_rate`, not `bc.learning_rate`.
        elsewhere = [p for p in paths if not (prefix and p.startswith(prefix)) and p + "." != prefix]
        suggestions += difflib.get_close_matches(dotted, elsewhere, n=3, cutoff=0.75)
        for leaf in difflib.get_close_matches(name, list(leaves), n=3, cutoff=0.8):
            suggestions += leaves[leaf]
    suggestions = list(dict.fromkeys(suggestions))[:5]
    message = f"unknown config key '{_shown(dotted)}' ({source})"
    if suggestions:
        return message + "; did you mean " + " or ".join(f"'{s}'" for s in suggestions) + "?"
    where = f" in [{prefix[:-1]}]" if prefix else ""
    return message + f"; valid keys{where}: " + ", ".join(level_keys)


# ---- building and type checking --------------------------------------------------------------------------------


def _build(cls: type[T], tree: dict[str, Any], prefix: str, base: Any) -> T:
    """Instantiate `cls` from the merged tree, taking unset fields from `base` (or the class defaults)."""
    types_ = _field_types(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        key = prefix + f.name
        default = getattr(base, f.name) if base is not None else _field_default(f)
        node = tree.get(f.name, _ABSENT)
        if isinstance(node, dict):
            sub = _dataclass_in(types_[f.name])
            assert sub is not None  # _merge only makes tables for dataclass fields
            kwargs[f.name] = _build(sub, node, key + ".", default if isinstance(default, sub) else None)
        elif isinstance(node, _Value):
            kwargs[f.name] = _check(types_[f.name], node, key)
        elif default is dataclasses.MISSING:
            raise ConfigError(f"config key '{key}' has no default and must be set")
        else:
            kwargs[f.name] = default
    try:
        return cls(**kwargs)
    except (TypeError, ValueError, ArithmeticError) as e:
        raise ConfigError(f"invalid config [{prefix[:-1] or cls.__name__}]: {e}") from None


_ABSENT = object()


def _field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def _check(tp: Any, node: _Value, key: str) -> Any:
    try:
        return _convert(tp, node.value, node.raw)
    except _Mismatch:
        pass
    message = f"config key '{key}' expects {_describe(tp)}, got {_shown(repr(node.value))} ({node.source})"
    options = [o for o in _literal_options(tp) if isinstance(o, str)]
    if isinstance(node.value, str) and options:
        close = difflib.get_close_matches(node.value, options, n=1, cutoff=0.5)
        if close:
            message += f"; did you mean '{close[0]}'?"
    raise ConfigError(message)


def _convert(tp: Any, value: Any, raw: str | None) -> Any:
    """Return `value` as type `tp`, or raise _Mismatch. Only lossless conversions are made."""
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin is Union or origin is types.UnionType:
        members = typing.get_args(tp)
        if type(None) in members and isinstance(value, str) and value.lower() == NONE_WORD:
            return None
        for member in members:
            if member is type(None):
                continue
            try:
                return _convert(member, value, raw)
            except _Mismatch:
                continue
        raise _Mismatch
    if origin is Literal:
        for option in typing.get_args(tp):
            if type(value) is type(option) and value == option:
                return option
            if raw is not None and isinstance(option, str) and raw == option:
                return option
        raise _Mismatch
    if dataclasses.is_dataclass(tp):
        raise _Mismatch  # a single value where a table is needed
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false"):
            return value.lower() == "true"
        raise _Mismatch
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise _Mismatch
    if tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            try:
                number = float(value)
            except OverflowError:  # an int too large for a float
                raise _Mismatch from None
            if not math.isfinite(number):  # no setting means NaN or infinity; `nan` / `inf` are typos or tests
                raise _Mismatch
            return number
        raise _Mismatch
    if tp is str:
        if isinstance(value, str):
            return value
        if raw is not None:
            return raw
        raise _Mismatch
    if tp in (tuple, list) or origin in (tuple, list):
        return _convert_sequence(tp, value)
    raise TypeError(f"config field type {tp!r} is not supported by deploy.config")


def _convert_sequence(tp: Any, value: Any) -> Any:
    if not isinstance(value, list | tuple):
        raise _Mismatch
    origin = typing.get_origin(tp) or tp
    args = typing.get_args(tp)
    if origin is list:
        item = args[0] if args else Any
        return [_convert(item, v, None) for v in value]
    if not args:
        return tuple(value)
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(_convert(args[0], v, None) for v in value)
    if len(args) != len(value):
        raise _Mismatch
    return tuple(_convert(a, v, None) for a, v in zip(args, value, strict=True))


def _describe(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(o) for o in typing.get_args(tp))
    if origin is Union or origin is types.UnionType:
        return " or ".join(NONE_WORD if a is type(None) else _describe(a) for a in typing.get_args(tp))
    if dataclasses.is_dataclass(tp):
        return f"a table of {tp.__name__} keys"
    if tp is float:
        return "a finite float"
    if isinstance(tp, type) and origin is None:
        return tp.__name__
    return repr(tp).replace("typing.", "")


def _literal_options(tp: Any) -> list[Any]:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return list(typing.get_args(tp))
    if origin is Union or origin is types.UnionType:
        return [o for a in typing.get_args(tp) for o in _literal_options(a)]
    return []


# ---- schema helpers --------------------------------------------------------------------------------------------


@functools.cache
def _field_types(cls: type) -> dict[str, Any]:
    """Resolved field types of a config dataclass (annotations may be strings under `from __future__`)."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls) if f.init}


def _dataclass_in(tp: Any) -> type | None:
    """The dataclass a field holds (directly or as `X | None`), or None for a plain value field."""
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return tp
    origin = typing.get_origin(tp)
    if origin is Union or origin is types.UnionType:
        for member in typing.get_args(tp):
            if isinstance(member, type) and dataclasses.is_dataclass(member):
                return member
    return None


@functools.cache
def _all_paths(cls: type) -> tuple[str, ...]:
    """Every valid dotted key of a config class, tables included."""
    paths: list[str] = []
    for name, tp in _field_types(cls).items():
        paths.append(name)
        sub = _dataclass_in(tp)
        if sub is not None:
            paths += [f"{name}.{p}" for p in _all_paths(sub)]
    return tuple(paths)


def _holds_nul(value: Any) -> bool:
    """Whether a leaf value (or a list of them) holds a string with a NUL character, which no path, name or key
    expression may hold and which TOML can only give as the escape \\u0000."""
    if isinstance(value, str):
        return "\x00" in value
    if isinstance(value, list | tuple):
        return any(_holds_nul(v) for v in value)
    return False


def _shown(text: str, limit: int = _SHOWN_CHARS) -> str:
    """`text` as an error message may quote it: on one line (unprintable characters, newlines and NULs among them,
    written as escapes) and clipped to about `limit` characters."""
    if not text.isprintable():
        text = "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in text)
    if len(text) > limit:
        text = f"{text[:limit]}... ({len(text):,} characters)"
    return text


def _shown_path(path: Path | str) -> str:
    return _shown(str(path), _SHOWN_PATH_CHARS)


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return config_to_dict(value)
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if value is None:
        return NONE_WORD
    return value
