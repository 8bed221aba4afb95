"""Design families: plain modules with a ``space`` (DesignSpace) and either ``generate(params)``
(a planar Linkage: kinematic and dynamic studies) or ``build_spec(params)`` (a whole engine world,
e.g. a walker with a floating torso: dynamic studies only).

Families are loaded by name from a designs/ folder (the working directory's first, then the
project's), or from an explicit path to a .py file. A name is a plain Python identifier
("four_bar"); anything else that is not a path ending in .py ("../x", "a/b", "os.path") is
refused, so a name can never reach outside designs/.
"""

from __future__ import annotations

import importlib.util
import pathlib
from types import ModuleType

__all__ = ["DESIGNS_DIR", "available_families", "load_family"]

DESIGNS_DIR = pathlib.Path(__file__).resolve().parents[1] / "designs"


def _search_dirs() -> list[pathlib.Path]:
    """designs/ of the working directory first, then the one beside the package (source tree)."""
    return [d for d in (pathlib.Path.cwd() / "designs", DESIGNS_DIR) if d.is_dir()]


def available_families() -> list[str]:
    """Names of the families found in designs/."""
    return sorted({p.stem for d in _search_dirs() for p in d.glob("*.py") if not p.name.startswith("_")})


def load_family(name_or_path) -> ModuleType:
    """Load a family module by name (designs/<name>.py) or by an explicit .py path; checks its interface.

    Raises ValueError naming the family when the name is neither an identifier nor a .py path,
    when no such file exists, or when the module lacks ``space`` or both ``generate`` and
    ``build_spec``.
    """
    if not isinstance(name_or_path, (str, pathlib.PurePath)) or not str(name_or_path):
        raise ValueError(f"design family: expected a family name or a .py path, got {name_or_path!r}")
    text = str(name_or_path)
    if isinstance(name_or_path, pathlib.PurePath) or text.endswith(".py"):
        path = pathlib.Path(name_or_path)
        if path.suffix != ".py" or not path.is_file():
            raise ValueError(f"design family '{text}': no such .py file")
    elif text.isidentifier():
        candidates = [d / f"{text}.py" for d in _search_dirs()]
        path = next((c for c in candidates if c.is_file()), None)
        if path is None:
            raise ValueError(f"unknown design family '{text}': no file {text}.py in designs/; "
                             f"available: {', '.join(available_families())}")
    else:
        raise ValueError(f"design family '{text}': expected the name of a module in designs/ (a plain identifier "
                         f"such as 'four_bar') or a path to a .py file")
    spec = importlib.util.spec_from_file_location(f"morphopt_family_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not hasattr(module, "space"):
        raise ValueError(f"design family {path} defines no 'space'")
    if not (hasattr(module, "generate") or hasattr(module, "build_spec")):
        raise ValueError(f"design family {path} defines neither 'generate' (a linkage) nor 'build_spec' (a world)")
    return module
