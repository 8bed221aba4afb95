"""Design families: plain modules with a ``space`` (DesignSpace) and either ``generate(params)``
(a planar Linkage: kinematic and dynamic studies) or ``build_spec(params)`` (a whole engine world,
e.g. a walker with a floating torso: dynamic studies only).

Families are loaded by name from the working directory's designs/ folder first, then from the
built-in ones shipped in the package (morphopt/designs/, BUILTIN_DIR, found from the installed
package wherever the command runs), or from an explicit path to a .py file. A name is a plain
Python identifier ("four_bar"); anything else that is not a path ending in .py ("../x", "a/b",
"os.path") is refused, so a name can never reach outside those folders.

Whatever goes wrong while a family file is loaded (an exception or ``sys.exit`` at import, a
syntax error, a ``space`` that is no DesignSpace, a ``generate`` that cannot be called) is one
ValueError naming the file and what is wrong; KeyboardInterrupt still stops the program.
"""

from __future__ import annotations

import importlib.util
import pathlib
import traceback
from types import ModuleType

from morphopt.design_space import DesignSpace

__all__ = ["BUILTIN_DIR", "available_families", "describe_exception", "family_file", "load_family"]

FUNCTIONS = ("generate", "build_spec")  # what a study may call; each, if defined, a callable

BUILTIN_DIR = pathlib.Path(__file__).resolve().parent / "designs"  # the package's own (morphopt.designs)


def _search_dirs() -> list[pathlib.Path]:
    """designs/ of the working directory first, then the package's built-in families."""
    return [d for d in (pathlib.Path.cwd() / "designs", BUILTIN_DIR) if d.is_dir()]


def available_families() -> list[str]:
    """Names of the families found in ./designs/ and among the built-in ones."""
    return sorted({p.stem for d in _search_dirs() for p in d.glob("*.py") if not p.name.startswith("_")})


def family_file(name: str) -> pathlib.Path | None:
    """The file a family name loads (./designs/ first, then the built-in ones), None if there is none."""
    if not name.isidentifier() or name.startswith("_"):
        return None
    return next((c for c in (d / f"{name}.py" for d in _search_dirs()) if c.is_file()), None)


def load_family(name_or_path) -> ModuleType:
    """Load a family module by name (<name>.py in ./designs/ or the built-in families) or by an
    explicit .py path; checks its interface.

    Raises ValueError naming the family when the name is neither an identifier nor a .py path,
    when no such file exists, when executing it fails (see the module docstring), or when the
    module lacks a DesignSpace ``space`` or both ``generate`` and ``build_spec``, or defines one of
    FUNCTIONS as something that cannot be called. What the functions return is checked by
    morphopt.contract, for a study's mode.
    """
    if not isinstance(name_or_path, (str, pathlib.PurePath)) or not str(name_or_path):
        raise ValueError(f"design family: expected a family name or a .py path, got {name_or_path!r}")
    text = str(name_or_path)
    if isinstance(name_or_path, pathlib.PurePath) or text.endswith(".py"):
        path = pathlib.Path(name_or_path)
        if path.suffix != ".py" or not path.is_file():
            raise ValueError(f"design family '{text}': no such .py file")
    elif text.isidentifier():
        path = family_file(text)
        if path is None:
            raise ValueError(f"unknown design family '{text}': no file {text}.py in ./designs/ or among the "
                             f"built-in families; available: {', '.join(available_families())}")
    else:
        raise ValueError(f"design family '{text}': expected the name of a family (a plain identifier such as "
                         f"'four_bar', from ./designs/ or the built-in ones) or a path to a .py file")
    module = _execute(path)
    if not hasattr(module, "space"):
        raise ValueError(f"design family {path} defines no 'space'")
    if not isinstance(module.space, DesignSpace):
        raise ValueError(f"design family {path}: 'space' must be a morphopt.design_space.DesignSpace, got "
                         f"{_kind(module.space)}")
    if not (hasattr(module, "generate") or hasattr(module, "build_spec")):
        raise ValueError(f"design family {path} defines neither 'generate' (a linkage) nor 'build_spec' (a world)")
    for name in FUNCTIONS:
        if hasattr(module, name) and not callable(getattr(module, name)):
            raise ValueError(f"design family {path}: '{name}' must be a function, got {_kind(getattr(module, name))}")
    return module


def _execute(path: pathlib.Path) -> ModuleType:
    """The module of a family file, executed; any failure of the file (not KeyboardInterrupt) as
    one ValueError naming the file, the exception and the line."""
    try:
        spec = importlib.util.spec_from_file_location(f"morphopt_family_{path.stem}", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except SyntaxError as exc:
        name = pathlib.Path(exc.filename).name if exc.filename else path.name
        where = f"{name}, line {exc.lineno}" if exc.lineno else name
        raise ValueError(f"design family {path}: not valid Python: {type(exc).__name__}: {_one_line(exc.msg)} "
                         f"({where})") from None
    except SystemExit as exc:
        raise ValueError(f"design family {path} called sys.exit({exc.code!r}) at import "
                         f"({_line_in(exc, path)}); a family file must only define its space and functions") from None
    except Exception as exc:  # noqa: BLE001 - whatever the file raises is reported, by type and line
        raise ValueError(f"design family {path} failed at import: {describe_exception(exc, path)}") from None
    return module


def describe_exception(exc: BaseException, path) -> str:
    """'<Type>: <message> (<file>, line N)' on one line, the line being the last one the traceback
    passes in the family file ``path`` (else the innermost line)."""
    try:
        message = _one_line(str(exc))
    except Exception:  # noqa: BLE001 - an exception whose message itself fails
        message = "(its message cannot be shown)"
    return f"{type(exc).__name__}{': ' + message if message else ''} ({_line_in(exc, path)})"


def _line_in(exc: BaseException, path) -> str:
    frames = traceback.extract_tb(exc.__traceback__)
    target = str(pathlib.Path(path).resolve())
    inside = [f for f in frames if f.filename and _same_file(f.filename, target)]
    frame = (inside or frames or [None])[-1]
    if frame is None:
        return "no line"
    shown = pathlib.Path(frame.filename).name
    return f"{shown}, line {frame.lineno}"


def _same_file(name: str, target: str) -> bool:
    try:
        return str(pathlib.Path(name).resolve()) == target
    except (OSError, ValueError):
        return False


def _one_line(text: str) -> str:
    """Text on one line (exception messages may hold newlines), at most 300 characters."""
    text = " ".join(str(text).split())
    return text if len(text) <= 300 else text[:297] + "..."


def _kind(value) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text if len(text) <= 40 else text[:37] + '...'}"
