"""The floating-point arithmetic of this machine as a recording names it (its "fluxcal.arithmetic" metadata
record): numpy's and scipy's versions, the CPU features numpy dispatches to, the BLAS each links and the kernel
set it chose. Two machines with the same record compute the same bits from the same samples; replay says which
entries differ when they do not."""

from __future__ import annotations

import ctypes
import functools
import os
import platform
from pathlib import Path

#: the metadata record's name
ARITHMETIC_RECORD = "fluxcal.arithmetic"
#: the entries that decide the bits (python's version does not: the numerics are numpy's and BLAS's)
KEYS = ("machine", "numpy", "numpy_simd", "numpy_blas", "numpy_blas_core", "scipy", "scipy_blas", "scipy_blas_core")
#: the entries that name the instruction set (the rest name library versions)
INSTRUCTION_SET = ("machine", "numpy_simd", "numpy_blas_core", "scipy_blas_core")


def _blas_core(package_dir: Path) -> str:
    """The kernel set OpenBLAS chose at load time ("Haswell", "SkylakeX", ...; OPENBLAS_CORETYPE forces one),
    asked of the OpenBLAS the package bundles, if it is loaded; "" where that cannot be asked."""
    libs = package_dir.parent / f"{package_dir.name}.libs"
    for lib in sorted(libs.glob("*openblas*.so*")) if libs.is_dir() else []:
        try:
            handle = ctypes.CDLL(str(lib), mode=getattr(os, "RTLD_NOLOAD", 0) | os.RTLD_LAZY)
        except OSError:
            continue
        for name in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename", "openblas_get_corename64_",
                     "openblas_get_corename"):
            fn = getattr(handle, name, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                return (fn() or b"").decode(errors="replace").strip()
    return ""


def _blas(config: dict) -> str:
    blas = (config.get("Build Dependencies") or {}).get("blas") or {}
    return " ".join(str(blas.get(k, "")) for k in ("name", "version")).strip()


@functools.lru_cache(maxsize=1)
def _machine_arithmetic() -> tuple[tuple[str, str], ...]:
    import numpy as np
    import scipy
    import scipy.linalg  # noqa: F401 - loads scipy's BLAS, whose kernel set is asked for

    npc = np.show_config(mode="dicts")
    spc = scipy.show_config(mode="dicts")
    simd = npc.get("SIMD Extensions") or {}
    found = list(simd.get("baseline") or []) + list(simd.get("found") or [])
    return (("machine", platform.machine()), ("numpy", np.__version__), ("numpy_simd", " ".join(found)),
            ("numpy_blas", _blas(npc)), ("numpy_blas_core", _blas_core(Path(np.__file__).parent)),
            ("scipy", scipy.__version__), ("scipy_blas", _blas(spc)),
            ("scipy_blas_core", _blas_core(Path(scipy.__file__).parent)), ("python", platform.python_version()))


def machine_arithmetic() -> dict[str, str]:
    """This machine's arithmetic, as strings (the metadata record's values)."""
    try:
        return dict(_machine_arithmetic())
    except Exception as e:                     # noqa: BLE001 - a build that does not say: the record says so
        return {"unknown": f"{type(e).__name__}: {e}"}


def arithmetic_differences(recorded: dict[str, str], here: dict[str, str]) -> list[str]:
    """The entries in which a recording's arithmetic differs from this machine's ("numpy_simd: X86_V2 X86_V3 there,
    X86_V2 X86_V3 X86_V4 AVX512_ICL here"); [] when they agree. A recording without the record: one entry."""
    if not recorded:
        return ["unknown: the recording does not name the arithmetic it was made with (recorded before fluxcal "
                "wrote it)"]
    return [f"{k}: {recorded.get(k) or '?'} there, {here.get(k) or '?'} here" for k in KEYS
            if recorded.get(k, "") != here.get(k, "")]


def another_instruction_set(recorded: dict[str, str], here: dict[str, str]) -> bool:
    return bool(recorded) and any(recorded.get(k, "") != here.get(k, "") for k in INSTRUCTION_SET)
