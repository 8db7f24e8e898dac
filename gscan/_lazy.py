"""Lazy re-exports of a package's public names (PEP 562): a name's module is imported on first use, so that
importing the package (and the command line) stays fast while `package.name` and `from package import name`
work as with eager imports.
"""
from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(package: str, exports: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """(__getattr__, __dir__) for the package `package` whose public names live in other modules.

    exports: {name: module that defines it}. The first access imports the module and caches the value in the
    package's namespace; an unknown name raises AttributeError.
    """
    def __getattr__(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(exports) | set(vars(sys.modules[package])))

    return __getattr__, __dir__
