"""Deferred imports of heavy optional dependencies (torch, smplx), so that importing a package stays light.

- :func:`optional_import`: import a dependency when a function needs it, or raise
  :class:`~davis_rig.errors.MissingDependencyError` naming the pip extra that installs it;
  :func:`optional_dependency`: the same for ``import`` statements at the top of a module::

      with optional_dependency("the attack"):
          import torch
- :func:`lazy_exports`: PEP 562 package exports loaded from their module on first access::

      __getattr__, __dir__ = lazy_exports(__name__, {"davis_rig.events.v2e_torch": ("v2e_histograms",)})
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from types import ModuleType

from davis_rig.errors import MissingDependencyError

__all__ = ["lazy_exports", "optional_dependency", "optional_import"]


def optional_import(module: str, needed_for: str, extra: str = "torch") -> ModuleType:
    """Import ``module``, or raise with the message ``"<needed_for> needs <module>: pip install 'davis_rig[<extra>]'"``.

    Args:
        module: the dependency, e.g. ``"torch"``.
        needed_for: what needs it, e.g. ``"the renderer"``.
        extra: the optional-dependency group of davis_rig that installs it.

    Raises:
        MissingDependencyError: ``module`` cannot be imported.
    """
    with optional_dependency(needed_for, extra):
        return importlib.import_module(module)


@contextmanager
def optional_dependency(needed_for: str, extra: str = "torch") -> Iterator[None]:
    """Turn an ``ImportError`` inside the block into ``"<needed_for> needs <module>: pip install 'davis_rig[<extra>]'"``.

    Args:
        needed_for: what needs the imports of the block, e.g. ``"the attack"``.
        extra: the optional-dependency group of davis_rig that installs them.

    Raises:
        MissingDependencyError: an import of the block failed (the module it could not find is named).
    """
    try:
        yield
    except MissingDependencyError:
        raise
    except ImportError as exc:
        module = (exc.name or "a dependency").split(".")[0]
        raise MissingDependencyError(f"{needed_for} needs {module}: pip install 'davis_rig[{extra}]'") from exc


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
