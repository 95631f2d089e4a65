"""The shipped YAML configuration (vehicles, missions, sessions, disturbance presets,
scenarios, campaigns) and how to find it.

The YAML files live in this package as package data, so an installed ``fasthex`` finds them
without a checkout. ``find_config("vehicles", "fasthex")`` resolves a name to the shipped file;
a path to an existing file is returned unchanged. The generic validating loader is in
:mod:`config.schema`; the typed dataclasses live with the packages that use them.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from config.schema import ConfigError

__all__ = ["ConfigError", "available", "config_root", "find_config"]

KINDS = ("vehicles", "missions", "sessions", "disturbances", "scenarios", "campaigns")


def config_root() -> Path:
    """Directory holding the shipped YAML files (inside the installed package)."""
    return Path(str(resources.files("config")))


def available(kind: str) -> list[str]:
    """Names (file stems) of the shipped configs of one kind, sorted."""
    folder = config_root() / kind
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def find_config(kind: str, name_or_path: str | Path) -> Path:
    """Resolve a shipped config name (``fasthex``) or a file path to an existing file.

    Raises :class:`ConfigError` naming what was looked for and what exists.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown config kind {kind!r}; expected one of {KINDS}")
    candidate = Path(name_or_path)
    if candidate.suffix in (".yaml", ".yml") or candidate.parent != Path("."):
        if candidate.is_file():
            return candidate
        raise ConfigError(str(candidate), None, None, "file not found")
    shipped = config_root() / kind / f"{name_or_path}.yaml"
    if shipped.is_file():
        return shipped
    names = ", ".join(available(kind)) or "none"
    raise ConfigError(
        str(name_or_path), None, None, f"no such {kind[:-1]}; shipped {kind}: {names}"
    )
