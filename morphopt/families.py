"""Design families: plain modules with a ``space`` (DesignSpace) and either ``generate(params)``
(a planar Linkage: kinematic and dynamic studies) or ``build_spec(params)`` (a whole engine world,
e.g. a walker with a floating torso: dynamic studies only).

Families live in the project's designs/ folder and are loaded by name, or from any .py path.
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


def load_family(name_or_path: str) -> ModuleType:
    """Load a family module by name (designs/<name>.py) or by path; checks its interface."""
    path = pathlib.Path(name_or_path)
    if path.suffix != ".py":
        candidates = [d / f"{name_or_path}.py" for d in _search_dirs()]
        path = next((c for c in candidates if c.is_file()), DESIGNS_DIR / f"{name_or_path}.py")
    if not path.is_file():
        raise ValueError(f"unknown design family '{name_or_path}': no file {path}; "
                         f"available: {', '.join(available_families())}")
    spec = importlib.util.spec_from_file_location(f"morphopt_family_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if not hasattr(module, "space"):
        raise ValueError(f"design family {path} defines no 'space'")
    if not (hasattr(module, "generate") or hasattr(module, "build_spec")):
        raise ValueError(f"design family {path} defines neither 'generate' (a linkage) nor 'build_spec' (a world)")
    return module
