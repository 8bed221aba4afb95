"""Warp's output in morphopt: quiet unless verbose, and one line on stderr when kernels compile.

Warp prints its init banner and a line per module it loads on stdout, and its native library warns
on stderr when there is no CUDA driver. ``quiet_warp()``, called by the command line and by
morphopt's entry points (run_study, evaluate_kinematic, evaluate_dynamic) before Warp initializes,
installs a Warp logger that drops those lines (``set_verbose(True)``, the CLI's ``--verbose``,
sends them to stderr instead) and passes Warp's warnings and errors on to stderr, and it
initializes Warp with the CUDA driver warning dropped unless verbose. A Warp logger the user
installed is left alone.

Compiling: the first time in a process that Warp compiles a module (its load line says
"(compiled)"), or before a study's first generation when ``announce_compile`` finds the study's
first module missing from Warp's kernel cache, "compiling kernels (first run only, ~N s)" goes to
stderr. ``compile_seconds()`` is the compile time so far (a progress bar leaves it out of its ETA).
"""

from __future__ import annotations

import enum
import importlib
import os
import re
import sys
import tempfile
import warnings

__all__ = ["Kernels", "announce_compile", "compile_seconds", "is_verbose", "quiet_warp", "set_verbose"]

_LOAD = re.compile(r"\s*Module (\S+) .*load on device '([^']+)' took ([0-9.]+) ms\s*\(compiled\)")
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


class Kernels(enum.Enum):
    """The kernels a study compiles: (the first module it loads, seconds to compile them all on a
    CPU, measured cold on 2 cores with the shipped studies, rounded up)."""

    KINEMATIC = ("morphopt.linkage.kinematics_warp", 5)
    DYNAMIC = ("engine.joints", 15)  # engine.pack's plans: the maximal kernels or a reduced one

    @property
    def module(self) -> str:
        """The first Warp module a study of this kind loads (its compile notice waits on it)."""
        return self.value[0]

    @property
    def seconds(self) -> int:
        """About how long its kernels take to compile on a cold cache [s] (2-core CPU)."""
        return self.value[1]


class _State:
    verbose = False
    installed = False
    initialized = False
    announced = False
    compile_s = 0.0
    expected_s = Kernels.DYNAMIC.seconds


def is_verbose() -> bool:
    """Whether morphopt was asked to be verbose (the CLI's --verbose)."""
    return _State.verbose


def set_verbose(verbose: bool) -> None:
    """Show Warp's banner, module loads and the CUDA driver warning on stderr (True) or drop them."""
    _State.verbose = bool(verbose)


def compile_seconds() -> float:
    """Seconds Warp spent compiling modules in this process so far (from its module load lines)."""
    return _State.compile_s


class _Logger:
    """A Warp logger: info and debug lines to stderr when verbose (else dropped, counting compile
    time), warnings and errors to stderr."""

    def debug(self, message: str) -> None:
        sys.stderr.write(message + "\n")  # only at wp.LOG_DEBUG, which a user asks for

    def info(self, message: str) -> None:
        match = _LOAD.match(message)
        if match:
            _State.compile_s += float(match.group(3)) / 1e3
            _announce()
        if _State.verbose:
            sys.stderr.write(message + "\n")

    def warning(self, message: str, category=None, stacklevel: int = 1) -> None:
        warnings.warn(message, category or UserWarning, stacklevel=stacklevel + 1)  # Python's filters apply

    def error(self, message: str) -> None:
        sys.stderr.write("Warp Error: " + message + "\n")


def quiet_warp():
    """Import Warp, route its output (see the module docstring) and initialize it; returns ``warp``.
    Cheap after the first call."""
    import warp as wp

    if not _State.installed:
        if type(wp.get_logger()).__name__ == "LoggerBasic":  # Warp's own: not one the user installed
            wp.set_logger(_Logger())
        _State.installed = True
    if not _State.initialized:
        _init(wp)
        _State.initialized = True
    return wp


def _init(wp) -> None:
    """wp.init() with what the native library writes to stderr captured, and written back without
    the CUDA driver warning unless verbose."""
    if _State.verbose:
        wp.init()
        return
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no usable stderr descriptor
        wp.init()
        return
    with tempfile.TemporaryFile() as capture:
        os.dup2(capture.fileno(), 2)
        try:
            wp.init()
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        text = capture.read().decode(errors="replace")
    kept = [line for line in text.splitlines() if _NO_DRIVER not in line]
    if kept:
        sys.stderr.write("\n".join(kept) + "\n")


def _announce(seconds: float | None = None) -> None:
    if _State.announced:
        return
    _State.announced = True
    print(f"compiling kernels (first run only, ~{seconds or _State.expected_s:.0f} s)", file=sys.stderr, flush=True)


def announce_compile(kernels: Kernels, device: str) -> None:
    """Before a study's first generation: say "compiling kernels" when Warp's kernel cache lacks the
    first module ``kernels`` loads on ``device`` (later modules are announced by their load line)."""
    _State.expected_s = kernels.seconds
    importlib.import_module(kernels.module)
    if _module_cached(kernels.module, device) is False:
        _announce(kernels.seconds)


def _module_cached(name: str, device: str) -> bool | None:
    """Whether Warp's kernel cache holds module ``name`` built for ``device`` (the file Warp looks
    for before compiling); None when it cannot tell (not imported, or another Warp's internals)."""
    wp = quiet_warp()
    try:
        from warp._src.context import user_modules

        module = user_modules.get(name)
        if module is None:
            return None
        target = wp.get_device(device)
        block_dim = 1 if target.is_cpu else module.options["block_dim"]
        folder = os.path.join(wp.config.kernel_cache_dir, module.get_module_identifier(block_dim))
        files = (module._get_compile_output_name(target, block_dim=block_dim), module._get_meta_name(block_dim))
        return all(os.path.exists(os.path.join(folder, f)) for f in files)
    except Exception:  # noqa: BLE001 - Warp internals of another version: the load lines still announce
        return None
