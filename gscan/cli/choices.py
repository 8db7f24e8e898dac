"""The command line's choice types, made from the library's own lists (never a copy of them): the values a
`--format` or `--mode` accepts are those the library validates against."""
from __future__ import annotations

from collections.abc import Sequence
from enum import Enum
from typing import TYPE_CHECKING, Any

from gscan.exporters import FORMATS as EXPORT_FORMATS
from gscan.scanning.options import FORMAT_CHOICES, MODE_CHOICES

__all__ = ["FORMAT_CHOICES", "ExportFormat", "ScanFormat", "ScanMode", "choice_enum"]


def choice_enum(name: str, values: Sequence[str]) -> Any:
    """A str Enum whose values are `values` (typer's choice type); a member is named as its value with '-' as
    '_' ("static-object": ScanMode.static_object)."""
    return Enum(name, [(v.replace("-", "_"), v) for v in values], type=str, module=__name__)


if TYPE_CHECKING:  # what the type checker sees: str enums (their members come from the lists below)
    class ScanFormat(str, Enum): ...

    class ScanMode(str, Enum): ...

    class ExportFormat(str, Enum): ...
else:
    ScanFormat = choice_enum("ScanFormat", FORMAT_CHOICES)  # `scan --format`: auto and gscan.io.layouts.FORMATS
    ScanMode = choice_enum("ScanMode", MODE_CHOICES)  # `scan --mode`: auto, static-object, moving-object
    ExportFormat = choice_enum("ExportFormat", EXPORT_FORMATS)  # `export --format`: gscan.exporters.FORMATS
