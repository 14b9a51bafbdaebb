"""One set of numeric kernels on every x86-64 machine, so a step log recorded on one replays to the bit on another.

numpy's matrix products (``W @ x`` in the fuzzy MRC, the EKF's ``dot``) go to its bundled OpenBLAS, which picks
its kernels by the CPU it finds: an AVX-512 machine runs the ``SkylakeX`` kernels, an AVX2 one ``Haswell``, and
the two round some products differently (seen: a fuzzy leader's ``v`` off by 5.6e-17 at its third step, a log
recorded on a Zen 3 machine replayed on a Zen 4 one). :func:`pin` asks OpenBLAS for the ``Haswell`` kernels on
every x86-64 CPU that has AVX2 and FMA (every one since 2013), before numpy loads it; ``OPENBLAS_CORETYPE`` set
by the user wins. Across instruction sets (a log from an aarch64 robot replayed on an x86-64 laptop) the bits
may differ: the libraries' kernels are not the same code.
"""

from __future__ import annotations

import ctypes
import glob
import os
import platform
import sys

PINNED_CORE = "Haswell"
"""The OpenBLAS kernels every x86-64 machine with AVX2 and FMA runs the stack's numpy with."""


def _has_avx2_fma() -> bool:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return {"avx2", "fma"} <= flags
    except OSError:
        pass
    return False


def pin() -> None:
    """Set ``OPENBLAS_CORETYPE`` before numpy loads OpenBLAS (no effect once it has: :func:`blas_core` tells)."""
    if "OPENBLAS_CORETYPE" in os.environ or "numpy" in sys.modules:
        return
    if platform.machine() in ("x86_64", "AMD64") and _has_avx2_fma():
        os.environ["OPENBLAS_CORETYPE"] = PINNED_CORE


def blas_core() -> str | None:
    """The kernels numpy's bundled OpenBLAS runs in this process (``Haswell``, ``SkylakeX``, ...), None if unknown."""
    import numpy as np

    libs = glob.glob(os.path.join(os.path.dirname(np.__file__) + ".libs", "libscipy_openblas*.so*"))
    for path in libs:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for name in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename", "openblas_get_corename"):
            fn = getattr(lib, name, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                return fn().decode().strip() or None
    return None
