"""Numba kernels. Private: they take contiguous arrays of fixed dtypes and do no validation.

Importing this package imports numba; ``import lodbuilder`` never does.
"""

from typing import Any

JIT: dict[str, Any] = dict(cache=True, nogil=True)  # one place for JIT options; no fastmath: kernels rely on inf
# No inline="always" on the helpers: numba's IR-level inlining copies a helper into every call site
# and its passes (type inference, SSA) grow faster than linearly with a function's size, so it cost
# more first-run compile time than it saved; LLVM still inlines the small helpers when it links them.
# For the same reason the large loops are split into a few functions of moderate size.
# ... except the few small helpers that take arrays and run in hot loops (hash probes, binary
# searches, heap operations): a call passes its arrays with atomic reference counting (increments
# and decrements that LLVM cannot remove even after it inlines the helper); copied into the caller
# at numba's IR level they cost none
INLINE: dict[str, Any] = dict(JIT, inline="always")
# numba's np.sort, np.argsort and np.unique are closures of one factory (numba.misc.quicksort):
# with cache=True, two of them over the same array type compiled in two processes can carry one
# symbol name, and a process that loads both runs one in place of the other (2026-11-29: the
# march's np.sort ran as the tiled covering's np.argsort and the covering pass crashed). At most
# one kernel calls them (tests/test_accuracy.py, test_at_most_one_kernel_uses_numbas_sorts);
# the others sort with tiled.stable_argsort.
