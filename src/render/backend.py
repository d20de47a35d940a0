"""Choose the Mitsuba variant for this machine: ``cuda_ad_rgb`` on an NVIDIA GPU, else ``llvm_ad_rgb``.

Dr.Jit's LLVM backend needs a system ``libLLVM`` >= 16 (LLVM 15 fails to compile its kernels, see
docs/architecture.md). Debian 12 ships several versions side by side, so we point Dr.Jit at the newest
suitable one through ``DRJIT_LIBLLVM_PATH`` instead of trusting its default search order.
"""

from __future__ import annotations

import ctypes
import glob
import os
import re

from src.errors import ConfigError, EnvironmentSetupError

MIN_LLVM_MAJOR = 16
LLVM_SEARCH_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)
INSTALL_HINT = (
    "install an LLVM >= 16 shared library (Debian/Ubuntu: apt-get install libllvm19; Fedora: dnf install "
    "llvm-libs) or set DRJIT_LIBLLVM_PATH to one"
)


def llvm_major(path: str) -> int | None:
    """The LLVM major version encoded in a library file name (libLLVM-19.so, libLLVM.so.19.1)."""
    m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
    return int(m.group(1)) if m else None


def find_llvm_library(min_major: int = MIN_LLVM_MAJOR) -> str | None:
    """Path of the newest libLLVM with major version >= ``min_major``, or None."""
    candidates = []
    for pattern in LLVM_SEARCH_GLOBS:
        for path in glob.glob(pattern):
            major = llvm_major(path)
            if major is not None and major >= min_major:
                candidates.append((major, path))
    return max(candidates)[1] if candidates else None


def has_cuda_device() -> bool:
    """True when the NVIDIA driver library loads and reports at least one device."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    count = ctypes.c_int(0)
    return cuda.cuInit(0) == 0 and cuda.cuDeviceGetCount(ctypes.byref(count)) == 0 and count.value > 0


def resolve_variant(requested: str = "auto") -> str:
    """The variant to use for ``requested`` (auto | cuda_ad_rgb | llvm_ad_rgb), checking its needs."""
    if requested not in ("auto", "cuda_ad_rgb", "llvm_ad_rgb"):
        raise ConfigError(
            f"render.variant: unknown variant '{requested}'; expected auto, cuda_ad_rgb or llvm_ad_rgb"
        )
    if requested in ("auto", "cuda_ad_rgb") and has_cuda_device():
        return "cuda_ad_rgb"
    if requested == "cuda_ad_rgb":
        raise EnvironmentSetupError("render.variant=cuda_ad_rgb: no NVIDIA GPU/driver found (libcuda.so.1)")
    configured = os.environ.get("DRJIT_LIBLLVM_PATH")
    if configured and os.path.exists(configured):
        return "llvm_ad_rgb"
    library = find_llvm_library()
    if library is None:
        raise EnvironmentSetupError(
            f"no NVIDIA GPU for cuda_ad_rgb and no LLVM >= 16 for llvm_ad_rgb: {INSTALL_HINT}"
        )
    os.environ["DRJIT_LIBLLVM_PATH"] = library
    return "llvm_ad_rgb"


def set_mitsuba_variant(requested: str = "auto") -> str:
    """Select and activate the Mitsuba variant; registers the AOV integrator. Returns the variant name."""
    variant = resolve_variant(requested)
    import mitsuba as mi  # imported late: DRJIT_LIBLLVM_PATH must be set before Dr.Jit loads LLVM

    mi.set_variant(variant)
    from src.render.aov_integrator import register

    register()
    return variant
