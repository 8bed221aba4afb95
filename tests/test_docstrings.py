"""Every public name of the two packages has a docstring: modules, classes, functions, methods,
properties, Warp kernels and Warp functions (a method may inherit its docstring from the class
it overrides)."""

import importlib
import inspect
import pkgutil

import pytest

PACKAGES = ("engine", "morphopt")


def _modules(package: str) -> list[str]:
    root = importlib.import_module(package)
    names = [package]
    for info in pkgutil.walk_packages(root.__path__, package + "."):
        if not info.name.rsplit(".", 1)[-1].startswith("_"):
            names.append(info.name)
    return names


def _doc_of_warp(obj) -> str | None:
    """Docstring of a Warp kernel or function (its Python function's), None when obj is neither."""
    if type(obj).__name__ not in ("Kernel", "Function"):
        return None
    return getattr(getattr(obj, "func", None), "__doc__", None) or ""


def _undocumented(module_name: str) -> list[str]:
    module = importlib.import_module(module_name)
    missing = [] if (module.__doc__ or "").strip() else ["<module>"]
    for name, obj in vars(module).items():
        if name.startswith("_"):
            continue
        warp_doc = _doc_of_warp(obj)
        if warp_doc is not None:
            if getattr(getattr(obj, "func", None), "__module__", None) == module_name and not warp_doc.strip():
                missing.append(name)
            continue
        if not (inspect.isclass(obj) or inspect.isfunction(obj)) or getattr(obj, "__module__", None) != module_name:
            continue
        if not (inspect.getdoc(obj) or "").strip():
            missing.append(name)
        if inspect.isclass(obj):
            for member_name, member in vars(obj).items():
                if member_name.startswith("_"):
                    continue
                if isinstance(member, (staticmethod, classmethod)):
                    member = member.__func__
                if not (inspect.isfunction(member) or isinstance(member, property)):
                    continue
                if not (inspect.getdoc(getattr(obj, member_name)) or inspect.getdoc(member) or "").strip():
                    missing.append(f"{name}.{member_name}")
    return missing


@pytest.mark.parametrize("package", PACKAGES)
def test_every_public_name_has_a_docstring(package):
    modules = _modules(package)
    assert len(modules) > 5, modules  # the walk found the package's modules
    missing = {m: names for m in modules if (names := _undocumented(m))}
    assert not missing, f"public names without a docstring: {missing}"


def test_the_check_sees_a_missing_docstring(tmp_path, monkeypatch):
    """The check itself: a module with one undocumented function and one undocumented method."""
    (tmp_path / "docless_probe.py").write_text(
        '"""Probe."""\n\ndef shown():\n    """Documented."""\n\n\ndef hidden():\n    return 1\n\n\n'
        'class Box:\n    """Documented."""\n\n    def open(self):\n        return 2\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    assert _undocumented("docless_probe") == ["hidden", "Box.open"]
