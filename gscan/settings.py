"""The one convention every stage's settings follow, and the YAML file they are read from.

A stage's settings class is the one place its defaults and choices live: a frozen dataclass (or a pydantic
model) whose fields read `name: Annotated[type, Field(description=..., bounds)] = default`, with
`__pydantic_config__ = SETTINGS`. Python code builds and `dataclasses.replace`s them as plain values; the YAML
configuration (`gscan config dump`, `--config`) is a pydantic model whose sections are those classes, so the
file is validated against the stages' own bounds and choices, and its comments are the fields' descriptions.

- `read_yaml(path) -> dict`: a configuration file's sections (InputError naming the file)
- `validate(model, data, path)`: the sections as `model` (InputError naming the file and the key)
- `dump_yaml(settings, header) -> str`: commented YAML of a settings value, a section per nested class
- `setting_fields(settings) -> [(name, value, description)]`: a settings value's fields in declaration order
"""
from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, TypeAdapter, ValidationError
from pydantic.fields import FieldInfo

from gscan.errors import InputError, not_a_file

#: the pydantic configuration of every settings class: unknown keys and non-finite numbers are refused
SETTINGS = ConfigDict(extra="forbid", allow_inf_nan=False)

M = TypeVar("M")


def read_yaml(path: str | Path) -> dict[str, Any]:
    """The mapping a YAML configuration file holds (an empty file: {}); InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise not_a_file(path, "configuration file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8-sig")) or {}
    except OSError as e:
        raise InputError(path, f"cannot read config ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise InputError(path, "cannot read config (not UTF-8 text)") from None
    except RecursionError:
        raise InputError(path, "malformed YAML: nested too deeply") from None
    except yaml.YAMLError as e:
        raise InputError(path, f"malformed YAML: {str(e).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise InputError(path, "config must be a mapping of sections")
    return data


def validate(model: type[M], data: dict[str, Any], path: str | Path | None, what: str = "config key") -> M:
    """`data` validated as `model` (a settings class or a model of sections); InputError naming `path` and the
    first offending key (`section.key`), called `what` ("ROS parameter" for the ROS 2 node's)."""
    try:
        return TypeAdapter(model).validate_python(data)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        raise InputError(path, f"invalid {what} {where}: {msg}" if where else f"invalid config: {msg}") from None


def to_data(settings: Any) -> Any:
    """A settings value as plain JSON-like data (what `dump_yaml` writes and `validate` reads back)."""
    return TypeAdapter(type(settings)).dump_python(settings, mode="json")


def setting_fields(settings: Any) -> list[tuple[str, Any, str]]:
    """(name, value, description) of each field of a settings value, in declaration order."""
    if isinstance(settings, BaseModel):
        return [(k, getattr(settings, k), f.description or "") for k, f in type(settings).model_fields.items()]
    hints = typing.get_type_hints(type(settings), include_extras=True)
    out = []
    for f in dataclasses.fields(settings):
        info = next((m for m in getattr(hints[f.name], "__metadata__", ()) if isinstance(m, FieldInfo)), None)
        out.append((f.name, getattr(settings, f.name), (info.description if info is not None else None) or ""))
    return out


def _is_section(value: Any) -> bool:
    return isinstance(value, BaseModel) or (dataclasses.is_dataclass(value) and not isinstance(value, type))


def dump_yaml(settings: Any, header: str = "") -> str:
    """Commented YAML of a settings value: a section per nested settings class, a `# description` per key.
    Loaded back (`read_yaml`, `validate`) it gives the same value."""
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]

    def walk(value: Any, indent: str) -> None:
        for name, v, about in setting_fields(value):
            if _is_section(v):
                lines.append(f"{indent}{name}:{f'  # {about}' if about else ''}")
                walk(v, indent + "  ")
                continue
            text = yaml.safe_dump(to_data(v) if not isinstance(v, (int, float, str, bool, type(None))) else v,
                                  default_flow_style=True).strip()
            text = text.removesuffix("...").strip()
            lines.append(f"{indent}{name}: {text}{f'  # {about}' if about else ''}")

    walk(settings, "")
    return "\n".join(lines) + "\n"
