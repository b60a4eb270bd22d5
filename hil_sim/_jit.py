"""Just-in-time compilation of the plant's hot loops, with a plain-Python fallback.

Numba compiles the model functions and the RK4 kernel to machine code (cached on disk
next to the module), which is what makes the 120 s dual-cylinder study run far faster
than real time. Without numba the same source runs as ordinary Python and NumPy: the
results are identical, only slower.

The kernels use NumPy's error model for floats (``error_model="numpy"``): a division by
zero gives inf or NaN instead of raising ``ZeroDivisionError``. No divisor in the plant
can be zero (masses, chamber volumes, regularized roots, the pivots of the positive
definite mass matrix), and without the per-division check LLVM vectorizes the loops over
the 19 cylinders. The results stay bit for bit those of the scalar code: SIMD square
root and division are correctly rounded like the scalar ones, and nothing is reordered
(no fastmath).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any, TypeVar, cast

F = TypeVar("F", bound=Callable[..., Any])

_numba: Any
try:
    _numba = importlib.import_module("numba")
except ImportError:  # pragma: no cover - numba is the optional `sim` extra
    _numba = None

HAVE_NUMBA = _numba is not None


def jit(func: F) -> F:
    """Compile ``func`` in nopython mode (cached on disk; NumPy's float error model, see
    the module docstring); identity without numba."""
    if _numba is None:  # pragma: no cover
        return func
    return cast(F, _numba.njit(cache=True, error_model="numpy")(func))
