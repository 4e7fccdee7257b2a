"""lodbuilder's one JSON convention (lodbuilder._json): the fast path of the markers gives the text
of the walk, and falls back to it where json's encoder alone would not."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lodbuilder._json import dumps, fast_dumps, jsonable


@pytest.mark.parametrize("doc", [
    {"tile": 3, "key_hist": [list(range(-40, -30)), list(range(10))], "files": {"stream.3.keys": [12, 34]}},
    {"n": np.int64(7), "r": np.float64(0.1), "a": np.arange(4, dtype=np.int32), "b": np.bool_(True), "f": 1e-300},
    {"set": {3}, "path": Path("/tmp/x"), "tuple": (1, "a", None), "nested": [{"x": [np.float32(0.5)]}], 5: "int key"},
    {"other": object.__new__(type("Thing", (), {"__str__": lambda self: "a thing"}))},
    {"inf": float("inf"), "arr": np.array([1.0, -np.inf, np.nan])},  # (non-finite: the walk's strings)
    {np.int64(2): "a NumPy key"},  # (a key json's encoder refuses: the walk's str)
])
def test_the_fast_path_writes_the_walks_text(doc):
    assert fast_dumps(doc) == dumps(doc) == json.dumps(jsonable(doc), allow_nan=False)


def test_non_finite_floats_are_strings_on_either_path():
    assert json.loads(fast_dumps({"r": np.inf, "s": [float("nan")]})) == {"r": "inf", "s": ["nan"]}
