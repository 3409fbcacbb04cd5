"""davis_rig._lazy: PEP 562 lazy exports."""

from __future__ import annotations

import sys
import types

import pytest

from davis_rig._lazy import lazy_exports


@pytest.fixture()
def package(monkeypatch):
    pkg = types.ModuleType("fake_pkg")
    monkeypatch.setitem(sys.modules, "fake_pkg", pkg)
    return pkg


def test_loads_on_first_access_and_caches(package, monkeypatch):
    loaded = []
    real_import = __import__("importlib").import_module

    def spy(name):
        loaded.append(name)
        return real_import(name)

    monkeypatch.setattr("davis_rig._lazy.importlib.import_module", spy)
    package.__getattr__, package.__dir__ = lazy_exports("fake_pkg", {"json": ("dumps", "loads"), "math": ("pi",)})
    assert loaded == []
    assert package.dumps("x") == '"x"'
    assert loaded == ["json"] and "dumps" in vars(package)  # cached: a plain attribute from now on
    assert package.pi == pytest.approx(3.14159265)
    assert {"dumps", "loads", "pi"} <= set(dir(package))
    with pytest.raises(AttributeError, match="module 'fake_pkg' has no attribute 'nope'"):
        package.nope  # noqa: B018


def test_a_name_in_two_modules_is_refused():
    with pytest.raises(ValueError, match="'x' is exported by both a and b"):
        lazy_exports("fake_pkg", {"a": ("x",), "b": ("x", "y")})


def test_optional_import_returns_the_module_or_names_the_extra():
    import json

    from davis_rig._lazy import optional_import
    from davis_rig.errors import MissingDependencyError

    assert optional_import("json", "a feature") is json
    message = r"^the widget needs no_such_mod_xyz: pip install 'davis_rig\[extra1\]'$"
    with pytest.raises(MissingDependencyError, match=message):
        optional_import("no_such_mod_xyz", "the widget", "extra1")


@pytest.mark.parametrize("package", ["davis_rig.attack", "davis_rig.events", "davis_rig.models.rvt",
                                     "davis_rig.scene", "davis_rig.session", "davis_rig.training"])
def test_every_exported_name_of_the_packages_resolves(package):
    import importlib

    module = importlib.import_module(package)
    for name in module.__all__:
        assert getattr(module, name) is not None, name
        assert name in dir(module), name
    with pytest.raises(AttributeError, match="no_such_name"):
        module.no_such_name  # noqa: B018


def test_optional_dependency_names_the_missing_module_and_the_extra():
    from davis_rig._lazy import optional_dependency
    from davis_rig.errors import MissingDependencyError

    with pytest.raises(MissingDependencyError) as info:
        with optional_dependency("the thing", "report"):
            import davis_rig_no_such_module.sub  # noqa: F401
    assert str(info.value) == "the thing needs davis_rig_no_such_module: pip install 'davis_rig[report]'"
    assert isinstance(info.value, ImportError)


def test_optional_dependency_passes_other_errors_and_its_own_through():
    from davis_rig._lazy import optional_dependency
    from davis_rig.errors import MissingDependencyError

    inner = MissingDependencyError("already precise")
    with pytest.raises(MissingDependencyError) as info:
        with optional_dependency("the thing"):
            raise inner
    assert info.value is inner
    with pytest.raises(KeyError):
        with optional_dependency("the thing"):
            raise KeyError("x")
