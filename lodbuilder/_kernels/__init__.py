"""Numba kernels. Private: they take contiguous arrays of fixed dtypes and do no validation.

Importing this package imports numba; ``import lodbuilder`` never does.
"""

from typing import Any

JIT: dict[str, Any] = dict(cache=True, nogil=True)  # one place for JIT options; no fastmath: kernels rely on inf
# small scalar helpers are inlined into their callers at numba's IR level: each separately compiled
# function costs a fixed part of the first-run compile time (helpers that take arrays stay separate:
# inlined they bring atomic reference counting into the hot loops)
INLINE: dict[str, Any] = dict(JIT, inline="always")
