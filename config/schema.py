"""YAML -> frozen dataclasses, validated before anything is opened.

Every config file is a YAML mapping that carries ``schema`` (what kind of file it is) and
``version`` (an integer the reader supports), then the keys of one frozen dataclass. The file is
parsed with PyYAML's ``SafeLoader`` (the loader behind ``yaml.safe_load``; its libyaml form
``CSafeLoader`` where installed); we walk its node tree
instead of the plain Python objects so that every error can name the line it comes from.

What is refused, each with one message naming file, line, key path and expectation:
unknown keys, missing keys, duplicate keys, wrong types, non-finite numbers, values outside the
range declared with :func:`spec`, and inconsistent values that a dataclass's ``__post_init__``
reports by raising :class:`ConfigValueError`.

Supported field types: ``float``, ``int``, ``bool``, ``str``, ``Literal[...]``, ``X | None``,
``tuple[X, ...]``, fixed-length ``tuple[X, Y, Z]``, ``dict[str, X]``, nested dataclasses, and a
union of dataclasses told apart by a ``Literal`` field they share (e.g. ``kind: hold``).

YAML 1.1 trap: PyYAML reads ``4e-6`` (no dot) as a *string*. A plain (unquoted) scalar that
Python's ``float()`` accepts is taken as a number for float fields; a quoted one is not.
Likewise a bare ``off``/``on``/``yes``/``no`` is read as a boolean: for a ``Literal`` of strings
the word as written is taken (``rerun: off`` is ``'off'``) if it is one of the choices; another
boolean (``rerun: true``) is refused with a hint to quote the value.

Before the YAML parser sees a file, the reader refuses what no config file needs and what could
make the parser itself fail or blow up, each as ``FILE:LINE: expectation`` (no key): files over
:data:`MAX_FILE_BYTES`, text that is not UTF-8, control characters (NUL, escape, ...), tabs in the
indentation, more than one YAML document, nesting deeper than :data:`MAX_NESTING`, more than
:data:`MAX_NODES` values, and anchors/aliases (``&a`` / ``*a``: a few lines of them expand to
billions of values). Text values may not carry control characters either (``"\\0"``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

import yaml

T = TypeVar("T")

__all__ = [
    "ConfigError",
    "ConfigValueError",
    "field_type",
    "line_of",
    "load_config",
    "load_config_text",
    "spec",
    "type_error",
]

#: largest config file read (bytes): the shipped ones are ~2 kB; this bounds parse time/memory
MAX_FILE_BYTES = 256 * 1024
#: deepest nesting of mappings/lists: the schemas need 4 (session > backend > faults > item);
#: PyYAML's composer recurses per level, so an unbounded depth ends in RecursionError
MAX_NESTING = 16
#: most scalars + collections in one file (the shipped ones have < 300)
MAX_NODES = 20000


class ConfigError(Exception):
    """A user's config file is wrong. ``str()`` is the one-line message shown to the user."""

    def __init__(self, file: str, line: int | None, key: str | None, message: str) -> None:
        self.file, self.line, self.key, self.message = file, line, key, message
        super().__init__(str(self))

    def __str__(self) -> str:
        where = self.file if self.line is None else f"{self.file}:{self.line}"
        return f"{where}: {self.key}: {self.message}" if self.key else f"{where}: {self.message}"


class ConfigValueError(ValueError):
    """Raised by a config dataclass (``__post_init__``) for an inconsistent value.

    ``key`` is the field name (or dotted path) relative to that dataclass; the loader turns it
    into the full key path and line of the file.
    """

    def __init__(self, key: str, message: str) -> None:
        self.key, self.message = key, message
        super().__init__(f"{key}: {message}")


def spec(
    default: Any = dataclasses.MISSING,
    *,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    doc: str = "",
) -> Any:
    """A dataclass field with a range (applied to a number or each number of a tuple) and a doc.

    Mutable defaults are not allowed; use tuples.
    """
    meta = {"ge": ge, "gt": gt, "le": le, "lt": lt, "doc": doc}
    return dataclasses.field(default=default, metadata=meta)


def load_config(path: str | Path, cls: type[T], *, schema: str, versions: tuple[int, ...] = (1,),
                lines: dict[str, int] | None = None) -> T:
    """Read ``path`` and build ``cls`` from it; :class:`ConfigError` on any problem.

    ``lines``, when given, is filled with the line of every key path read (``segments[2].
    pos_w_m``), so that checks across files can point at the line of a value.
    """
    path = Path(path)
    label = str(path)
    try:
        with path.open("rb") as f:
            data = f.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise ConfigError(label, None, None, f"cannot read: {exc.strerror}") from None
    if len(data) > MAX_FILE_BYTES:
        raise ConfigError(label, 1, None, f"file too large; expected at most "
                          f"{MAX_FILE_BYTES // 1024} KiB of YAML")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise ConfigError(label, line, None, f"invalid UTF-8 (byte 0x{data[exc.start]:02x}); "
                          "expected a UTF-8 text file") from None
    return load_config_text(text, cls, schema=schema, versions=versions, file_label=label,
                            lines=lines)


def load_config_text(text: str, cls: type[T], *, schema: str, versions: tuple[int, ...] = (1,),
                     file_label: str = "<string>", lines: dict[str, int] | None = None) -> T:
    """Like :func:`load_config` for text already in memory (``file_label`` names it)."""
    try:
        return _load_text(text, cls, schema, versions, file_label, lines)
    except RecursionError:  # the limits below should make this unreachable; never a traceback
        raise ConfigError(file_label, 1, None, "nested too deeply; expected at most "
                          f"{MAX_NESTING} levels") from None


def _yaml_error(file_label: str, exc: yaml.YAMLError) -> ConfigError:
    if isinstance(exc, yaml.MarkedYAMLError):
        mark = exc.problem_mark or exc.context_mark
        problem = exc.problem or exc.context or "syntax error"
        return ConfigError(file_label, mark.line + 1 if mark is not None else 1, None,
                           f"not valid YAML: {problem}")
    return ConfigError(file_label, 1, None, f"not valid YAML: {exc}")


def _check_text(text: str, file_label: str) -> None:
    """Reader-level refusals before the parser runs (see the module docstring)."""
    if len(text) > MAX_FILE_BYTES:
        raise ConfigError(file_label, 1, None, f"file too large; expected at most "
                          f"{MAX_FILE_BYTES // 1024} KiB of YAML")
    for number, line in enumerate(text.split("\n"), 1):
        bad = _CONTROL.search(line)
        if bad is not None:
            raise ConfigError(file_label, number, None,
                              f"control character U+{ord(bad.group()):04X}; expected plain text")
        indent = line[:len(line) - len(line.lstrip(" \t"))]
        if "\t" in indent:
            raise ConfigError(file_label, number, None,
                              "tab in the indentation; YAML indents with spaces")


def _check_events(text: str, file_label: str) -> None:
    """Walk the parser's events (no recursion): documents, depth, size, aliases."""
    depth = documents = nodes = 0
    loader = _Loader(text)
    try:
        while loader.check_event():
            event = loader.get_event()
            line = event.start_mark.line + 1 if event.start_mark is not None else 1
            if isinstance(event, yaml.DocumentStartEvent):
                documents += 1
                if documents > 1:
                    raise ConfigError(file_label, line, None, "a second YAML document ('---'); "
                                      "expected one document per file")
            elif isinstance(event, yaml.AliasEvent) or (
                    isinstance(event, yaml.NodeEvent) and event.anchor is not None):
                raise ConfigError(file_label, line, None, "anchors and aliases (&name, *name) "
                                  "are not supported; expected plain values")
            elif isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_NESTING:
                    raise ConfigError(file_label, line, None, "nested too deeply; expected at "
                                      f"most {MAX_NESTING} levels")
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
            if isinstance(event, yaml.NodeEvent):
                nodes += 1
                if nodes > MAX_NODES:
                    raise ConfigError(file_label, line, None,
                                      f"too many values; expected at most {MAX_NODES}")
    except yaml.YAMLError as exc:
        raise _yaml_error(file_label, exc) from None
    finally:
        loader.dispose()


def _load_text(text: str, cls: type[T], schema: str, versions: tuple[int, ...],
               file_label: str, lines: dict[str, int] | None) -> T:
    text = text.removeprefix("\ufeff")  # a UTF-8 byte-order mark is harmless
    _check_text(text, file_label)
    _check_events(text, file_label)
    loader = _Loader(text)
    try:
        root = loader.get_single_node()
    except yaml.YAMLError as exc:
        raise _yaml_error(file_label, exc) from None
    finally:
        loader.dispose()
    walker = _Walker(file_label, loader, lines)
    if root is None:
        raise ConfigError(file_label, 1, None, "empty file; expected a mapping with "
                          f"'schema: {schema}' and 'version'")
    if not isinstance(root, yaml.MappingNode):
        raise walker.error(root, "", "expected a mapping at the top of the file")
    entries = walker.mapping(root, "")
    if "schema" not in entries:
        raise walker.error(root, "schema", f"missing key; expected 'schema: {schema}'")
    got_schema = walker.scalar(entries["schema"][1], "schema")
    if got_schema != schema:
        raise walker.error(entries["schema"][1], "schema",
                           f"expected {schema!r}, got {got_schema!r} (wrong kind of file?)")
    if "version" not in entries:
        raise walker.error(root, "version", f"missing key; expected one of {list(versions)}")
    got_version = walker.scalar(entries["version"][1], "version")
    if isinstance(got_version, bool) or got_version not in versions:
        raise walker.error(entries["version"][1], "version",
                           f"unsupported version {got_version!r}; this fasthex reads "
                           f"{' or '.join(map(str, versions))}")
    body = {k: v for k, v in entries.items() if k not in ("schema", "version")}
    return walker.dataclass_from(cls, root, body, "")


Entries = dict[str, tuple[yaml.Node, yaml.Node]]

#: libyaml's parser when PyYAML was built with it (14x faster, same nodes and resolver)
_Loader: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

#: C0 controls but tab and CR, DEL, C1 controls, and the non-characters a text file never holds
_CONTROL = re.compile("[\x00-\x08\x0b-\x0c\x0e-\x1f\x7f-\x9f\ufffe\uffff]")


class _Walker:
    def __init__(self, file_label: str, loader: Any,
                 lines: dict[str, int] | None = None) -> None:
        self.file = file_label
        self.loader = loader
        self.lines: dict[str, int] = {} if lines is None else lines

    # -- errors and primitives -------------------------------------------------------------
    def error(self, node: yaml.Node, key: str, message: str) -> ConfigError:
        return ConfigError(self.file, node.start_mark.line + 1, key or None, message)

    def construct(self, node: yaml.Node, key: str) -> Any:
        """PyYAML's value for a node; its own errors (unknown tags, ``2020-13-45`` read as a
        date, ``!!int abc``) become located config errors."""
        try:
            return self.loader.construct_object(node, deep=True)
        except (yaml.YAMLError, ValueError, TypeError, OverflowError) as exc:
            problem = getattr(exc, "problem", None) or str(exc)
            raise self.error(node, key, f"cannot read this value ({problem})") from None

    def scalar(self, node: yaml.Node, key: str) -> Any:
        if not isinstance(node, yaml.ScalarNode):
            kind = "a mapping" if isinstance(node, yaml.MappingNode) else "a list"
            raise self.error(node, key, f"expected a single value, got {kind}")
        return self.construct(node, key)

    def mapping(self, node: yaml.Node, key: str) -> Entries:
        if not isinstance(node, yaml.MappingNode):
            raise self.error(node, key, "expected a mapping (key: value lines)")
        entries: Entries = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                raise self.error(key_node, key, "keys must be names, got a "
                                 + ("mapping" if isinstance(key_node, yaml.MappingNode)
                                    else "list"))
            name = self.construct(key_node, key)
            if not isinstance(name, str):
                raise self.error(key_node, key, f"keys must be names, got {_short(name)}")
            if not name.strip() or _CONTROL.search(name) or "\n" in name or "\r" in name:
                # an empty or multi-line key would make a message that names it unreadable
                raise self.error(key_node, key, f"keys must be names, got {name!r}")
            if name in entries:
                raise self.error(key_node, _join(key, name), "duplicate key")
            entries[name] = (key_node, value_node)
        return entries

    # -- typed conversion -----------------------------------------------------------------
    def convert(self, tp: Any, node: yaml.Node, key: str, meta: dict[str, Any]) -> Any:
        origin = get_origin(tp)
        if key:
            self.lines.setdefault(key, node.start_mark.line + 1)
        if tp is Any:
            return self.construct(node, key)
        if dataclasses.is_dataclass(tp) and isinstance(tp, type):
            return self.dataclass_from(tp, node, self.mapping(node, key), key)
        if origin in (typing.Union, types.UnionType):
            return self.union(tp, node, key, meta)
        if origin is Literal:
            value = self.scalar(node, key)
            choices = get_args(tp)
            if isinstance(value, bool) and isinstance(choices[0], str):
                # YAML 1.1 reads a bare off/on/yes/no as a boolean: the word written is meant
                written = str(node.value)
                if written.lower() in choices:
                    return written.lower()
                raise self.error(node, key, f"expected one of {', '.join(map(repr, choices))}; "
                                 f"got {written} (YAML reads a bare {written} as {value!r}: "
                                 "write the value in quotes)")
            if value not in choices or isinstance(value, bool) != isinstance(choices[0], bool):
                raise self.error(node, key, f"expected one of {', '.join(map(repr, choices))}; "
                                 f"got {value!r}")
            return value
        if origin is tuple:
            return self.sequence(tp, node, key, meta)
        if origin is dict:
            key_tp, value_tp = get_args(tp)
            if key_tp is not str:
                raise TypeError(f"config dict keys must be str, not {key_tp}")
            entries = self.mapping(node, key)
            return types.MappingProxyType({
                name: self.convert(value_tp, vnode, _join(key, name), meta)
                for name, (_, vnode) in entries.items()
            })
        if tp is float:
            return self.number(node, key, meta)
        if tp is int:
            value = self.scalar(node, key)
            if isinstance(value, bool) or not isinstance(value, int):
                raise self.error(node, key, f"expected an integer{_range_text(meta)}, "
                                 f"got {value!r}")
            self.check_range(node, key, value, meta)
            return value
        if tp is bool:
            value = self.scalar(node, key)
            if not isinstance(value, bool):
                raise self.error(node, key, f"expected true or false, got {value!r}")
            return value
        if tp is str:
            value = self.scalar(node, key)
            if not isinstance(value, str):
                raise self.error(node, key, f"expected a text value, got {value!r}")
            bad = _CONTROL.search(value)
            if bad is not None or "\n" in value.rstrip("\n"):
                char = "a line break" if bad is None else f"U+{ord(bad.group()):04X}"
                raise self.error(node, key, f"expected one line of plain text, got {char}")
            return value
        raise TypeError(f"unsupported config field type {tp!r} at {key}")

    def number(self, node: yaml.Node, key: str, meta: dict[str, Any]) -> float:
        value = self.scalar(node, key)
        if isinstance(value, str) and not getattr(node, "style", None):  # plain: None or ""
            # YAML 1.1 reads 4e-6 as text: accept a plain scalar Python can read.
            with contextlib.suppress(ValueError):
                value = float(value)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(node, key, f"expected a number{_range_text(meta)}, "
                             f"got {_short(value)}")
        try:
            number = float(value)  # an integer beyond 1e308 overflows: not a sane number either
        except OverflowError:
            number = math.inf
        if not math.isfinite(number):
            raise self.error(node, key, f"expected a finite number, got {_short(value)}")
        self.check_range(node, key, value, meta)
        return number

    def check_range(self, node: yaml.Node, key: str, value: float, meta: dict[str, Any]) -> None:
        ge, gt, le, lt = (meta.get(k) for k in ("ge", "gt", "le", "lt"))
        if ((ge is not None and value < ge) or (gt is not None and value <= gt)
                or (le is not None and value > le) or (lt is not None and value >= lt)):
            raise self.error(node, key, f"expected a number{_range_text(meta)}, "
                             f"got {_short(value)}")

    def sequence(self, tp: Any, node: yaml.Node, key: str, meta: dict[str, Any]) -> tuple[Any, ...]:
        args = get_args(tp)
        if not isinstance(node, yaml.SequenceNode):
            shape = "a list" if len(args) == 2 and args[1] is Ellipsis else f"a list of {len(args)}"
            raise self.error(node, key, f"expected {shape} (e.g. [1, 2, 3])")
        items = node.value
        if len(args) == 2 and args[1] is Ellipsis:
            item_types = [args[0]] * len(items)
        else:
            if len(items) != len(args):
                raise self.error(node, key, f"expected a list of {len(args)} values, "
                                 f"got {len(items)}")
            item_types = list(args)
        return tuple(self.convert(t, n, f"{key}[{i}]", meta)
                     for i, (t, n) in enumerate(zip(item_types, items, strict=True)))

    def union(self, tp: Any, node: yaml.Node, key: str, meta: dict[str, Any]) -> Any:
        members = [a for a in get_args(tp) if a is not type(None)]
        if type(None) in get_args(tp) and isinstance(node, yaml.ScalarNode) and \
                self.construct(node, key) is None:
            return None
        if len(members) == 1:
            return self.convert(members[0], node, key, meta)
        if not all(dataclasses.is_dataclass(m) for m in members):
            raise TypeError(f"config unions must be of dataclasses, got {tp!r} at {key}")
        tag = _discriminator(members)
        entries = self.mapping(node, key)
        options = {v: m for m in members for v in get_args(_hints(m)[tag])}
        if tag not in entries:
            raise self.error(node, _join(key, tag), "missing key; expected one of "
                             + ", ".join(map(repr, options)))
        tag_node = entries[tag][1]
        value = self.scalar(tag_node, _join(key, tag))
        if value not in options:
            raise self.error(tag_node, _join(key, tag), "expected one of "
                             + ", ".join(map(repr, options)) + f"; got {value!r}")
        return self.dataclass_from(options[value], node, entries, key)

    def dataclass_from(self, cls: type[T], node: yaml.Node, entries: Entries, key: str) -> T:
        hints = _hints(cls)
        field_list = [f for f in dataclasses.fields(cls) if f.init]  # type: ignore[arg-type]
        known = {f.name for f in field_list}
        for name, (key_node, _) in entries.items():
            if name not in known:
                raise self.error(key_node, _join(key, name),
                                 f"unknown key; expected one of: {', '.join(sorted(known))}")
        kwargs: dict[str, Any] = {}
        for f in field_list:
            if f.name in entries:
                kwargs[f.name] = self.convert(hints[f.name], entries[f.name][1],
                                              _join(key, f.name), dict(f.metadata))
            elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise self.error(node, _join(key, f.name),
                                 f"missing key; expected {_describe(hints[f.name], f.metadata)}")
        try:
            return cls(**kwargs)
        except ConfigValueError as exc:
            full = _join(key, exc.key)
            line = _line_of(self.lines, full)
            if line is None:
                first = exc.key.split(".")[0].split("[")[0]
                line = (entries[first][1] if first in entries else node).start_mark.line + 1
            raise ConfigError(self.file, line, full, exc.message) from None


def field_type(cls: Any, data: Any, keys: typing.Sequence[str]) -> Any:
    """The type of the field at ``keys`` below config class ``cls`` (list items by their
    index); ``data``, the file's parsed YAML, tells the members of a union apart. ``Any`` where
    the type depends on a value the file does not have. A key the schema does not have raises
    :class:`ConfigValueError` (its key: the dotted path up to that key)."""
    tp: Any = cls
    for n, key in enumerate(keys):
        here = ".".join(keys[:n + 1])
        tp = _member(tp, data)
        if tp is Any:
            return Any
        origin = get_origin(tp)
        if dataclasses.is_dataclass(tp):
            known = {f.name for f in dataclasses.fields(tp) if f.init}
            if key not in known:
                raise ConfigValueError(here, "unknown key; expected one of: "
                                       + ", ".join(sorted(known)))
            tp = _hints(tp)[key]
            data = data.get(key) if isinstance(data, dict) else None
        elif origin is tuple:
            if not isinstance(data, list):  # its default: no item to set
                raise ConfigValueError(here, "the file has no list here to take an item of")
            if not key.isdigit() or int(key) >= len(data):
                raise ConfigValueError(here, f"expected an item number below {len(data)}")
            args = get_args(tp)
            tp = args[0] if args[-1] is Ellipsis else args[int(key)]
            data = data[int(key)]
        elif origin is dict:
            tp = get_args(tp)[1]
            data = data.get(key) if isinstance(data, dict) else None
        else:
            raise ConfigValueError(here, f"{key!r} goes into a single value "
                                   f"({_describe(tp, {})})")
    return tp


def _member(tp: Any, data: Any) -> Any:
    """``tp`` without its ``None``; of a union of dataclasses, the one ``data`` names."""
    if get_origin(tp) not in (typing.Union, types.UnionType):
        return tp
    members = [a for a in get_args(tp) if a is not type(None)]
    if len(members) == 1:
        return members[0]
    tag = _discriminator(members)
    options = {v: m for m in members for v in get_args(_hints(m)[tag])}
    named = data.get(tag) if isinstance(data, dict) else None
    return options.get(named, Any) if isinstance(named, str) else Any


def type_error(tp: Any, value: Any) -> str | None:
    """Why ``value`` (plain YAML data) cannot be a ``tp`` whatever the field's range, as the
    loader says it; None when it can."""
    loader = _Loader(yaml.safe_dump(value))
    try:
        node = loader.get_single_node()
    finally:
        loader.dispose()
    try:
        _Walker("<value>", loader).convert(tp, node, "", {})  # no range: the type alone
    except ConfigError as exc:
        return exc.message
    return None


_HINTS: dict[Any, dict[str, Any]] = {}


def _hints(cls: Any) -> dict[str, Any]:
    """The resolved field types of a config class (resolving string annotations is slow)."""
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def _line_of(lines: dict[str, int], key: str) -> int | None:
    """Line of ``key`` or of its nearest enclosing key path that was read."""
    while key:
        if key in lines:
            return lines[key]
        cut = max(key.rfind("."), key.rfind("["))
        key = key[:cut] if cut > 0 else ""
    return None


def line_of(lines: dict[str, int], key: str, default: int = 1) -> int:
    """Public form of the lookup for checks across files (a line is always given)."""
    found = _line_of(lines, key)
    return default if found is None else found


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _discriminator(members: list[Any]) -> str:
    common: set[str] | None = None
    for m in members:
        names = {n for n, t in _hints(m).items() if get_origin(t) is Literal}
        common = names if common is None else common & names
    if not common:
        raise TypeError(f"dataclass union {members} has no shared Literal field")
    return sorted(common)[0]


def _range_text(meta: dict[str, Any]) -> str:
    parts = [f"{op} {meta[k]:g}" for k, op in (("ge", ">="), ("gt", ">"), ("le", "<="),
                                                ("lt", "<")) if meta.get(k) is not None]
    return " " + " and ".join(parts) if parts else ""


def _describe(tp: Any, meta: Any) -> str:
    """What a value of type ``tp`` looks like in a file, as the loader's other messages say
    it (never a Python type name: the reader of the message writes YAML)."""
    origin = get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        members = [a for a in get_args(tp) if a is not type(None)]
        if len(members) > 1 and all(dataclasses.is_dataclass(m) for m in members):
            tag = _discriminator(members)  # e.g. "a mapping with kind: hold or kind: go_to"
            return "a mapping with " + " or ".join(
                f"{tag}: {v}" for m in members for v in get_args(_hints(m)[tag]))
        return " or ".join(_describe(m, meta) for m in members)
    if origin is Literal:
        return "one of " + ", ".join(map(repr, get_args(tp)))
    if tp is bool:
        return "true or false"
    if tp is str:
        return "a text value"
    if origin is dict:
        return "a mapping"
    if tp is float:
        return "a number" + _range_text(dict(meta))
    if tp is int:
        return "an integer" + _range_text(dict(meta))
    if origin is tuple:
        args = get_args(tp)
        return "a list" if args[-1] is Ellipsis else f"a list of {len(args)} values"
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    return getattr(tp, "__name__", str(tp))

