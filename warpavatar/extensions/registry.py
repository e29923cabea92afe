"""The registry of extensions: names to classes, in the order their hooks run."""

from __future__ import annotations

import dataclasses
import importlib.metadata
import warnings

from warpavatar.extensions.base import Extension
from warpavatar.model.parts import EXTENSION_ENTRY_POINT_GROUP

__all__ = ["register", "unregister", "registered", "get_extension", "load_entry_points", "ENTRY_POINT_GROUP"]

ENTRY_POINT_GROUP = EXTENSION_ENTRY_POINT_GROUP
"""Entry-point group through which installed packages add extensions (each entry an Extension subclass)."""

_REGISTRY: dict[str, type[Extension]] = {}


def _fields(cls: type[Extension]) -> dict[str, dataclasses.Field]:
    """The option fields of an extension (its switch's field, with :attr:`Extension.switch_modes`, is not one)."""
    if not dataclasses.is_dataclass(cls.options_type):
        raise TypeError(f"{cls.__name__}.options_type must be a dataclass")
    return {f.name: f for f in dataclasses.fields(cls.options_type)
            if not (cls.switch_modes and f.name == cls.switch_name())}


def register(cls: type[Extension]) -> type[Extension]:
    """Add an extension class (after those already registered: its hooks run after theirs).

    Its name must be new and its option names must not clash with another extension's, unless both inherit the
    same field from a shared options base class (one flag then sets both).

    Raises:
        ValueError: a name or an option already taken.
    """
    if not (isinstance(cls, type) and issubclass(cls, Extension)) or not cls.name.isidentifier():
        raise ValueError(f"{cls!r} is not an Extension subclass with an identifier for a name")
    if cls.name in _REGISTRY:
        raise ValueError(f"an extension called {cls.name!r} is registered already ({_REGISTRY[cls.name].__name__})")
    own = _fields(cls)
    switch = cls.switch_name()
    if cls.switch_modes:
        if cls.default_mode not in cls.switch_modes or "off" not in cls.switch_modes:
            raise ValueError(f"{cls.__name__}: switch_modes must hold 'off' and its default_mode")
        if switch not in {f.name for f in dataclasses.fields(cls.options_type)}:
            raise ValueError(f"{cls.__name__}: its options need a field {switch!r} for the switch's word")
    for other in _REGISTRY.values():
        if switch == other.switch_name():
            raise ValueError(f"{cls.__name__} is switched on by {switch!r}, as {other.__name__} is")
        if other.switch_name() in own:
            raise ValueError(f"{cls.__name__} has an option named like the switch {other.switch_name()!r}")
        for name, field in _fields(other).items():
            if name == switch:
                raise ValueError(f"{other.__name__} has an option named like the switch {switch!r}")
            if name in own and own[name] is not field and not _same_field(own[name], field):
                raise ValueError(f"option {name!r} of {cls.__name__} clashes with {other.__name__}'s")
    _REGISTRY[cls.name] = cls
    return cls


def _same_field(a: dataclasses.Field, b: dataclasses.Field) -> bool:
    """Two dataclass fields that are one option inherited by two options classes."""
    return a.name == b.name and a.default == b.default and a.type == b.type and a.metadata == b.metadata


def unregister(name: str) -> None:
    """Remove an extension (tests, plugins that were only tried)."""
    _REGISTRY.pop(name, None)


def registered() -> list[type[Extension]]:
    """Every registered extension class, in hook order."""
    return list(_REGISTRY.values())


def get_extension(name: str) -> type[Extension]:
    """The extension class called ``name``.

    Raises:
        ValueError: no such extension (the message lists the known ones).
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown extension {name!r}; known: {', '.join(_REGISTRY) or 'none'}")
    return _REGISTRY[name]


def load_entry_points() -> list[str]:
    """Register the extensions installed packages declare in :data:`ENTRY_POINT_GROUP`; returns their names.

    An entry that cannot be loaded, is not an :class:`Extension` subclass, or clashes with a registered one is
    skipped with a warning naming it (one broken plugin does not stop the others, or the built-in ones).
    """
    names = []
    for entry in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            cls = entry.load()
            if isinstance(cls, type) and issubclass(cls, Extension) and _REGISTRY.get(cls.name) is cls:
                continue  # registered already (by its own module, or an earlier call)
            register(cls)
            names.append(cls.name)
        except Exception as error:  # noqa: BLE001 - report any broken plugin, keep the others
            warnings.warn(f"warpavatar extension entry point {entry.name!r} ({entry.value}) was not loaded: {error}",
                          stacklevel=2)
    return names
