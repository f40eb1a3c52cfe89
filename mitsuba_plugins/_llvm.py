"""Find a libLLVM that Dr.Jit's LLVM backend can use, before Dr.Jit loads.

Dr.Jit opens libLLVM once, when ``drjit`` is first imported, and reads the
``DRJIT_LIBLLVM_PATH`` environment variable to choose which one. Dr.Jit 1.5 aborts the
whole process while compiling kernels with LLVM 15 ("Cannot select ... fminimum"), and
Debian 12 ships LLVM 14 and 15 beside 19, so the default search can pick a broken one.

This module is deliberately free of Dr.Jit and Mitsuba imports: it must run first.
"""
from __future__ import annotations

import glob
import os
import re
import sys
from dataclasses import dataclass

#: Oldest LLVM major version Dr.Jit 1.5 is known to work with. 15 aborts in codegen;
#: 16-18 were not tested here but carry the intrinsic that 15 lacks.
MIN_LLVM_MAJOR = 16

ENV_VAR = "DRJIT_LIBLLVM_PATH"

FIX_MESSAGE = (
    "mitsuba_plugins: no usable libLLVM (version >= {min}) was found for Dr.Jit's LLVM "
    "backend{found}. Fix: `apt-get install -y libllvm19` (Debian/Ubuntu), or set "
    "DRJIT_LIBLLVM_PATH=/path/to/libLLVM.so (LLVM >= {min}) before starting Python."
)

# Where distributions put a shared libLLVM.
DEFAULT_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib/llvm-*/lib",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/usr/local/opt/llvm/lib",
    "/opt/homebrew/opt/llvm/lib",
)

# libLLVM-19.so, libLLVM-19.so.1, libLLVM.so.19.1, libLLVM-14.0.6.so, libLLVM.19.dylib
_NAME_PATTERNS = (
    re.compile(r"^libLLVM-(\d+)(?:\.\d+)*\.so(?:\.\d+)*$"),
    re.compile(r"^libLLVM\.so\.(\d+)(?:\.\d+)*$"),
    re.compile(r"^libLLVM\.(\d+)(?:\.\d+)*\.dylib$"),
)
_DIR_PATTERN = re.compile(r"/llvm-(\d+)/lib/libLLVM\.(?:so|dylib)$")


@dataclass(frozen=True)
class Candidate:
    path: str
    major: int


class LLVMNotFoundError(RuntimeError):
    """No libLLVM usable by Dr.Jit's LLVM backend exists on this machine."""


def llvm_major_from_path(path: str) -> int | None:
    """LLVM major version encoded in a library file name, or ``None``."""
    name = os.path.basename(path)
    for pattern in _NAME_PATTERNS:
        m = pattern.match(name)
        if m:
            return int(m.group(1))
    m = _DIR_PATTERN.search(path)
    return int(m.group(1)) if m else None


def find_candidates(search_dirs=DEFAULT_SEARCH_DIRS) -> list[Candidate]:
    """Every libLLVM shared library in ``search_dirs`` (globs allowed), newest first.

    Files that resolve to the same real file are listed once, under the first name seen.
    """
    seen: set[str] = set()
    found: list[Candidate] = []
    for pattern in search_dirs:
        for directory in sorted(glob.glob(pattern)):
            for path in sorted(glob.glob(os.path.join(directory, "libLLVM*"))):
                major = llvm_major_from_path(path)
                if major is None or not os.path.isfile(path):
                    continue
                real = os.path.realpath(path)
                if real in seen:
                    continue
                seen.add(real)
                found.append(Candidate(path, major))
    found.sort(key=lambda c: c.major, reverse=True)  # stable: search order breaks ties
    return found


def choose_llvm(search_dirs=DEFAULT_SEARCH_DIRS, min_major: int = MIN_LLVM_MAJOR) -> Candidate:
    """The newest libLLVM with major version >= ``min_major``.

    Raises :class:`LLVMNotFoundError` naming the fix when there is none.
    """
    candidates = find_candidates(search_dirs)
    for c in candidates:
        if c.major >= min_major:
            return c
    found = ""
    if candidates:
        found = " (found only: " + ", ".join(f"{c.path} = LLVM {c.major}" for c in candidates) + ")"
    raise LLVMNotFoundError(FIX_MESSAGE.format(min=min_major, found=found))


def configure_environment(environ=os.environ, search_dirs=DEFAULT_SEARCH_DIRS) -> str | None:
    """Point Dr.Jit at a working libLLVM unless the user already chose one.

    Returns the path in effect, or ``None`` when none was found (the error is raised
    later, only if an LLVM variant is used: CUDA variants need no libLLVM).
    Has no effect on a Dr.Jit that is already imported: see :func:`check_loaded_llvm`.
    """
    if environ.get(ENV_VAR):
        return environ[ENV_VAR]
    try:
        chosen = choose_llvm(search_dirs)
    except LLVMNotFoundError:
        return None
    environ[ENV_VAR] = chosen.path
    return chosen.path


def check_loaded_llvm(version: tuple[int, ...] | None) -> None:
    """Refuse a libLLVM that Dr.Jit already loaded if it is known to crash."""
    if version is None or version[0] >= MIN_LLVM_MAJOR:
        return
    already = "drjit" in sys.modules
    raise LLVMNotFoundError(
        FIX_MESSAGE.format(min=MIN_LLVM_MAJOR,
                           found=f" (Dr.Jit loaded LLVM {'.'.join(map(str, version))})")
        + (" Dr.Jit was imported before mitsuba_plugins, so the library could not be "
           "chosen for you: import mitsuba_plugins first, or set the variable."
           if already else "")
    )
