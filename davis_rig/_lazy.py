"""Lazy package exports (PEP 562): names loaded from their module on first access.

A package whose modules need a heavy optional dependency (torch) lists their public names here instead of
importing them, so that importing the package stays light::

    __getattr__, __dir__ = lazy_exports(__name__, {"davis_rig.events.v2e_torch": ("v2e_histograms",)})
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Iterable, Mapping

__all__ = ["lazy_exports"]


def lazy_exports(
    package: str, modules: Mapping[str, Iterable[str]]
) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """Module-level ``__getattr__`` and ``__dir__`` that load ``name`` from its module on first access.

    Args:
        package: the package's ``__name__``.
        modules: module path -> the public names to take from it.

    Returns:
        ``(__getattr__, __dir__)`` to assign in the package's ``__init__``. A loaded name is stored in the
        package's namespace, so later accesses are ordinary attribute lookups.

    Raises:
        ValueError: a name listed for two modules.
    """
    where: dict[str, str] = {}
    for module, names in modules.items():
        for name in names:
            if name in where:
                raise ValueError(f"{package}: {name!r} is exported by both {where[name]} and {module}")
            where[name] = module

    def __getattr__(name: str) -> object:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(where))

    return __getattr__, __dir__
