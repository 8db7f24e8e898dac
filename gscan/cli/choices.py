"""The command line's choice types, whose values are the library's own lists (never a copy of them): the values a
`--format` or `--mode` accepts are those the library validates against.

A list lives in a module that loads numpy, numba and OpenCV; its choice type imports it when typer first reads the
values (parsing or `--help` of a command that has the option), so `gscan --help` and the other commands start
without it."""
from __future__ import annotations

import importlib
from collections.abc import Iterator
from enum import Enum, EnumMeta
from typing import Any

# choice type -> (module, name) of the library's tuple of its values
_SOURCES = {
    "ScanFormat": ("gscan.scanning.options", "FORMAT_CHOICES"),  # auto and gscan.io.layouts.FORMATS
    "ScanMode": ("gscan.scanning.options", "MODE_CHOICES"),  # auto, static-object, moving-object
    "ExportFormat": ("gscan.exporters", "FORMATS"),
}
_LOADED: dict[str, type[Enum]] = {}


def choice_enum(name: str, values: tuple[str, ...]) -> type[Enum]:
    """A str Enum whose values are `values`; a member is named as its value with '-' as '_'
    ("static-object": ScanMode.static_object)."""
    return Enum(name, [(v.replace("-", "_"), v) for v in values], type=str, module=__name__)  # type: ignore[return-value]


class _LibraryChoices(EnumMeta):
    """The metaclass of a choice type: its members are those of the Enum made from the library's list (`_SOURCES`),
    made on first use."""

    def _loaded(cls) -> type[Enum]:
        if cls.__name__ not in _LOADED:
            module, name = _SOURCES[cls.__name__]
            _LOADED[cls.__name__] = choice_enum(cls.__name__, getattr(importlib.import_module(module), name))
        return _LOADED[cls.__name__]

    def __iter__(cls) -> Iterator[Any]:
        return iter(cls._loaded())

    def __len__(cls) -> int:
        return len(cls._loaded())

    def __contains__(cls, value: object) -> bool:
        return value in cls._loaded().__members__.values() or value in {m.value for m in cls._loaded()}

    def __getitem__(cls, name: str) -> Any:
        return cls._loaded()[name]

    def __call__(cls, value: Any, *args: Any, **kwargs: Any) -> Any:
        return cls._loaded()(value)

    @property
    def __members__(cls) -> Any:
        return cls._loaded().__members__


class ScanFormat(str, Enum, metaclass=_LibraryChoices):
    """`scan --format`: gscan.scanning.options.FORMAT_CHOICES."""


class ScanMode(str, Enum, metaclass=_LibraryChoices):
    """`scan --mode`: gscan.scanning.options.MODE_CHOICES."""


class ExportFormat(str, Enum, metaclass=_LibraryChoices):
    """`export --format`: gscan.exporters.FORMATS."""


def format_choices() -> tuple[str, ...]:
    """The input layouts `track --format` takes (gscan.scanning.options.FORMAT_CHOICES)."""
    return tuple(f.value for f in ScanFormat)
