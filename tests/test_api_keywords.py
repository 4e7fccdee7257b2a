"""Every public function and method refuses an unknown keyword with an InputError naming the valid
ones (issue 13.4), instead of Python's bare TypeError. The list of public callables is collected
from the packages' ``__all__`` and the public classes, so a new function is checked too."""

from __future__ import annotations

import importlib
import inspect
import re

import pytest

from lodbuilder.errors import InputError

PACKAGES = [
    "lodbuilder",
    "lodbuilder.api",
    "lodbuilder.io",
    "lodbuilder.collection",
    "lodbuilder.features",
    "lodbuilder.quality",
    "lodbuilder.quality.archive",
    "lodbuilder.quality.plots",
    "lodbuilder.viewer",
    "lodbuilder.viewer.source",
    "lodbuilder.archive.reader",
    "lodbuilder.archive.scanview",
    "lodbuilder.fill",
]
NOT_HERE: set[str] = set()


def public_callables():
    seen = {}
    for pkg in PACKAGES:
        mod = importlib.import_module(pkg)
        names = getattr(mod, "__all__", None)
        if names is None:  # a module without __all__: what it defines
            names = [
                n
                for n, o in vars(mod).items()
                if not n.startswith("_") and getattr(o, "__module__", None) == pkg
            ]
        for name in names:
            obj = getattr(mod, name)
            if not getattr(obj, "__module__", "").startswith("lodbuilder"):
                continue
            if inspect.isclass(obj):
                if issubclass(obj, BaseException):
                    continue
                seen[obj.__qualname__] = (obj, False)  # the constructor
                for meth, fn in vars(obj).items():
                    if not meth.startswith("_") and inspect.isfunction(fn):
                        seen[f"{obj.__qualname__}.{meth}"] = (fn, True)
            elif inspect.isfunction(obj) and name not in NOT_HERE:
                seen[obj.__qualname__] = (obj, False)
    return seen


CALLABLES = public_callables()


def test_the_list_is_long():
    assert len(CALLABLES) > 80
    for must in ("read_scan", "ScanView.level", "fastfps", "collection_level", "ViewData.colours"):
        assert must in CALLABLES


@pytest.mark.parametrize("name", sorted(CALLABLES))
def test_unknown_keyword_is_an_input_error(name):
    fn, is_method = CALLABLES[name]
    target = inspect.unwrap(fn.__init__ if inspect.isclass(fn) else fn)
    params = [
        p.name
        for p in inspect.signature(target).parameters.values()
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY) and p.name not in ("self", "cls")
    ]
    args = (None,) if is_method else ()
    with pytest.raises(InputError) as exc:
        fn(*args, no_such_option=1)
    msg = str(exc.value)
    assert msg.startswith(f"{name}() got an unknown keyword argument 'no_such_option'"), msg
    listed = msg.split("; its keywords are: ")[1]
    shown = [p for p in params if not p.startswith("_")]
    assert listed.split(", ")[: len(shown)] == shown or listed == "none", msg


def test_message_suggests_the_closest_keyword():
    from lodbuilder.io import read_scan

    with pytest.raises(InputError) as exc:
        read_scan("x.ply", nmae="a")
    assert re.fullmatch(
        r"read_scan\(\) got an unknown keyword argument 'nmae' \(did you mean 'name'\?\); "
        r"its keywords are: path, .*name.*",
        str(exc.value),
    )


def test_forwarded_keywords_are_named(shared_data, tmp_path):
    """evaluate_archive passes **kw to evaluate_scan: those are its keywords."""
    from lodbuilder.quality.archive import evaluate_archive

    with pytest.raises(InputError) as exc:
        evaluate_archive(tmp_path / "a.h5", fractoins=[0.5])
    assert str(exc.value) == (
        "evaluate_archive() got an unknown keyword argument 'fractoins' (did you mean "
        "'fractions'?); its keywords are: path, scan, sizes, rhos, fractions, ordering, surface, "
        "k, progress"
    )


def test_feature_keyword_of_build_record():
    """The issue's example: a misspelled feature keyword."""
    from lodbuilder.api import build_record

    with pytest.raises(InputError, match=r"unknown keyword argument 'adaptiv' \(did you mean 'adaptive'\?\)"):
        build_record("x.ply", adaptiv=0.5)
