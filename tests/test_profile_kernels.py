"""tools/profile_kernels.py: the names its perf map gives numba's compiled functions."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))

from profile_kernels import _demangle  # noqa: E402


def test_kernel_symbols_are_named_by_module_and_function():
    name = "_ZN10lodbuilder8_kernels5march12_seed_sampleB4v129B52c8tJTIeFIjxB2IKSgI4CrvSCKg1MMfAwK4LJISUWsIgmAA_3d_3dExii"
    assert _demangle(name) == "march._seed_sample"
    assert _demangle("cfunc." + name) == "(cfunc) march._seed_sample"
    wrapper = "_ZN7cpython10lodbuilder8_kernels4tail11euclid_tailB2v1B52c8tJTIeFIjxB2IKSgI4Crv"
    assert _demangle(wrapper) == "(wrapper) tail.euclid_tail"
