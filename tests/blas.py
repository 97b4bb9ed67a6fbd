"""Which BLAS kernels numpy runs, for the tests that hold recorded figures to the last bit.

OpenBLAS picks its dot-product and matrix kernels by CPU (or by ``OPENBLAS_CORETYPE``, which some
machines set for older OpenBLAS builds: this project's hosts with AMD EPYC set ``Haswell``), and the
kernels differ in the last bits (a fused multiply-add or not, another summation order).  Every
energy figure goes through ``x.dot(x)``, so a session's bits are one kernel's: the goldens hold a
set of figures per kernel they were recorded on, and skip where numpy runs another.  Why not pin
the kernel in the tests: the machine sets it because other kernels compute wrong results or crash
on that CPU with older builds.
"""

from __future__ import annotations

import pytest

#: The kernels the goldens hold figures for: Intel hosts (OpenBLAS's own choice, every figure
#: recorded first there) and hosts that set ``OPENBLAS_CORETYPE=Haswell``.
RECORDED = ("SkylakeX", "Haswell")


def blas_kernel() -> str | None:
    """OpenBLAS's kernel family in this process (``SkylakeX``, ``Haswell``, ...), or None where
    numpy runs another BLAS (threadpoolctl reads it from the loaded library)."""
    import numpy  # noqa: F401  (loads its BLAS)
    from threadpoolctl import threadpool_info

    for info in threadpool_info():
        if info.get("internal_api") == "openblas":
            return str(info.get("architecture"))
    return None


def golden_kernel() -> str:
    """The kernel this process runs, if the goldens hold figures for it; else the test skips."""
    kernel = blas_kernel()
    if kernel not in RECORDED:
        pytest.skip(
            f"golden figures are recorded for OpenBLAS kernels {', '.join(RECORDED)}; numpy runs"
            f" {kernel or 'another BLAS'} here, whose dot products differ in the last bits (tests/blas.py)"
        )
    return kernel
