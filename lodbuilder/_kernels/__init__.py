"""Numba kernels. Private: they take contiguous arrays of fixed dtypes and do no validation.

Importing this package imports numba; ``import lodbuilder`` never does.
"""

from typing import Any

JIT: dict[str, Any] = dict(cache=True, nogil=True)  # one place for JIT options; no fastmath: kernels rely on inf
