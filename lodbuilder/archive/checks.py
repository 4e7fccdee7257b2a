"""What a scan of an archive must hold, checked before and while it is read.

:func:`check_scan_group` reads a scan group's attributes and the shapes and dtypes of its datasets
(no data) and returns them as a :class:`ScanMeta`, or raises a one-line CorruptArchiveError
naming the scan and what is wrong. :func:`check_rows` checks the values a query has just read
(O(rows read)): finite coordinates inside the scan's bounds, radii without NaN and non-increasing,
inf radii only where the parent is -1 (seeds and component starts), indices in range and
distinct, parents earlier than their children. :func:`check_rho_prefix` checks that the prefix
found for a rho is the one the radii define. A damaged or edited archive therefore gives a clean
error instead of a traceback or a silently wrong level.

File-level checks (links, external storage, sizes, hangs) are in :mod:`.safety`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import CorruptArchiveError
from . import layout as L
from .safety import damaged

RowReader = Callable[[str, int, int], np.ndarray]


@dataclass(frozen=True)
class ScanMeta:
    """The checked header of one scan."""

    path: Any
    name: str
    n_points: int
    n_ordered: int
    encoding: str
    offset: np.ndarray | None
    scale: np.ndarray | None
    bounds_min: np.ndarray
    bounds_max: np.ndarray
    step: int
    n_seeds: int
    stop_radius: float = 0.0  # covering bound of the whole ordered prefix (layout: stop_radius)

    def error(self, detail: str) -> CorruptArchiveError:
        return damaged(self.path, f"scan {self.name!r} {detail}")


def _scalar(value: Any) -> Any:
    if isinstance(value, np.ndarray) and value.size == 1:
        return value.reshape(-1)[0]
    return value


def _int_attr(
    attrs: Any, key: str, where: Callable[[str], CorruptArchiveError], default=None
) -> int:
    value = _scalar(attrs.get(key, default))
    if value is None:
        raise where(f"has no {key} attribute")
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise where(f"attribute {key} is {_short(value)}, not an integer")
    return int(value)


def _vec3(value: Any, what: str, where: Callable[[str], CorruptArchiveError]) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise where(f"{what} is {_short(value)}, not 3 finite numbers")
    return arr


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _dataset(g: Any, rel: str, where: Callable[[str], CorruptArchiveError], required: bool = True):
    import h5py

    obj = g.get(rel)
    if obj is None:
        if required:
            raise where(f"has no dataset {rel!r}")
        return None
    if not isinstance(obj, h5py.Dataset):
        raise where(f"member {rel!r} is a group, not a dataset")
    return obj


def _expect(ds: Any, rel: str, shape: tuple[int, ...], kinds: str, where) -> None:
    if ds.shape != shape:
        raise where(f"dataset {rel!r} has shape {ds.shape}, expected {shape}")
    if ds.dtype.kind not in kinds or ds.dtype.fields is not None:
        raise where(f"dataset {rel!r} has dtype {_short(ds.dtype)}, expected {_KINDS[kinds]}")


_KINDS = {"iu": "integers", "f": "floats", "biuf": "numbers"}


def check_scan_group(obj: Any, path: Any, name: str) -> ScanMeta:
    """Check the scan group ``obj`` (attributes, dataset shapes and dtypes; no data is read)."""
    import h5py

    def where(detail: str) -> CorruptArchiveError:
        return damaged(path, f"scan {name!r} {detail}")

    if not isinstance(obj, h5py.Group):
        raise where("is a dataset, not a group")
    a = obj.attrs
    n = _int_attr(a, L.S_N_POINTS, where)
    if n < 1:
        raise where(f"has n_points={n}; it must be at least 1")
    k = _int_attr(a, L.S_N_ORDERED, where, default=n)
    if not 1 <= k <= n:
        raise where(f"has n_ordered={k}; it must be in [1, n_points={n}]")
    enc = L._attr_json(_scalar(a.get(L.S_ENCODING)))
    if enc not in L.ENCODINGS:
        raise where(f"has coordinate_encoding {_short(enc)}, not one of {', '.join(L.ENCODINGS)}")
    lo = _vec3(a.get(L.S_BOUNDS_MIN), "bounds_min", where)
    hi = _vec3(a.get(L.S_BOUNDS_MAX), "bounds_max", where)
    if (lo > hi).any():
        raise where(f"has bounds_min {lo.tolist()} above bounds_max {hi.tolist()}")
    step = _int_attr(a, L.S_RADIUS_STEP, where, default=L.RADIUS_INDEX_STEP)
    if step < 1:
        raise where(f"has radius_index_step={step}; it must be a positive integer")

    offset, scale = _check_coordinates(obj, n, enc, where)
    _expect(_dataset(obj, L.D_SOURCE_INDEX, where), L.D_SOURCE_INDEX, (n,), "iu", where)
    _expect(_dataset(obj, L.D_RADIUS, where), L.D_RADIUS, (n,), "f", where)
    _expect(_dataset(obj, L.D_PARENT, where), L.D_PARENT, (n,), "iu", where)
    _expect(_dataset(obj, L.D_RADIUS_INDEX, where), L.D_RADIUS_INDEX, (-(-n // step),), "f", where)
    seeds = _dataset(obj, L.D_SEEDS, where, required=False)
    n_seeds = 0
    if seeds is not None:
        _expect(seeds, L.D_SEEDS, seeds.shape[:1], "iu", where)
        n_seeds = min(int(seeds.shape[0]) if seeds.ndim == 1 else 0, k)
    _check_members(obj, n, where)
    stop = _stop_radius(a, n, k, where)
    return ScanMeta(path, name, n, k, enc, offset, scale, lo, hi, step, n_seeds, stop)


def _check_coordinates(obj: Any, n: int, enc: str, where: Any) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The points dataset's shape and dtype, and the offset and scale of integer coordinates."""
    pts = _dataset(obj, L.D_POINTS, where)
    if (
        pts.shape != (n, 3)
        or pts.dtype.fields is not None
        or pts.dtype.newbyteorder("=") != np.dtype(enc)
    ):
        raise where(
            f"dataset 'points' has shape {pts.shape} and dtype {_short(pts.dtype)}, expected "
            f"({n}, 3) {enc}"
        )
    offset = scale = None
    if enc in ("int32", "int64"):
        if L.P_OFFSET not in pts.attrs or L.P_SCALE not in pts.attrs:
            raise where(f"has {enc} coordinates without offset and scale attributes")
        offset = _vec3(pts.attrs[L.P_OFFSET], "the points offset", where)
        scale = _vec3(pts.attrs[L.P_SCALE], "the points scale", where)
        if (scale <= 0).any():
            raise where(f"has points scale {scale.tolist()}; scales must be > 0")
    return offset, scale


def _check_members(obj: Any, n: int, where: Any) -> None:
    """The attributes and importance groups (one row per point) and the extra orderings."""
    import h5py

    for grp_name, ndim_ok in ((L.G_ATTRIBUTES, True), (L.G_IMPORTANCE, False)):
        grp = obj.get(grp_name)
        if grp is None:
            continue
        if not isinstance(grp, h5py.Group):
            raise where(f"member {grp_name!r} is a dataset, not a group")
        for key in grp:
            ds = _dataset(grp, key, where)
            rel = f"{grp_name}/{key}"
            shape = (n,) + (tuple(ds.shape[1:]) if ndim_ok else ())
            _expect(ds, rel, shape if ds.ndim >= 1 else (n,), "biuf", where)
    og = obj.get(L.G_ORDERINGS)
    if og is not None:
        if not isinstance(og, h5py.Group):
            raise where(f"member {L.G_ORDERINGS!r} is a dataset, not a group")
        for key in og:
            grp = og[key]
            rel = f"{L.G_ORDERINGS}/{key}"
            if not isinstance(grp, h5py.Group):
                raise where(f"ordering {key!r} is a dataset, not a group")
            order = _dataset(grp, L.D_ORDER, where)
            kk = order.shape[0] if order.ndim == 1 else -1
            if not 1 <= kk <= n:
                raise where(
                    f"ordering {key!r} has shape {order.shape}; it must hold 1 to {n} positions"
                )
            for rel2, kinds in ((L.D_ORDER, "iu"), (L.D_RADIUS, "f"), (L.D_PARENT, "iu")):
                _expect(_dataset(grp, rel2, where), f"{rel}/{rel2}", (kk,), kinds, where)


def _stop_radius(attrs: Any, n: int, k: int, where: Callable[[str], CorruptArchiveError]) -> float:
    value = _scalar(attrs.get(L.S_STOP_RADIUS))
    if value is not None and (
        isinstance(value, (bool, np.bool_)) or not isinstance(value, (float, int, np.floating, np.integer))
    ):
        raise where(f"attribute {L.S_STOP_RADIUS} is {_short(value)}, not a number")
    stop = L.stop_radius_of(value, n, k)
    if math.isnan(stop) or stop < 0:
        raise where(f"has {L.S_STOP_RADIUS}={stop}; it must be a number >= 0 (or inf)")
    return stop


# ---------------------------------------------------------------------------------------------
# values, as they are read


def read(meta: ScanMeta, ds: Any, sel: Any = (), before: Callable[[Any, Any], Any] | None = None):
    """``ds[sel]``; a dataset HDF5 cannot read (a checksum fails) is a one-line error.
    ``before(ds, sel)`` runs first (a remote archive's prefetch)."""
    try:
        if before is not None:
            before(ds, sel)
        return ds[sel]
    except OSError as exc:
        raise CorruptArchiveError(
            f"archive {meta.path}: scan {meta.name!r} dataset {ds.name} fails its "
            f"checksum or cannot be read ({str(exc).splitlines()[0]}); the file is damaged, "
            "rebuild it from the source scan"
        ) from None


def rows_of(sel: Any, length: int) -> tuple[int, int] | None:
    """(lo, hi) of a contiguous row selection, None for anything else."""
    if isinstance(sel, slice) and sel.step in (None, 1):
        lo, hi, _ = sel.indices(length)
        return lo, max(lo, hi)
    if sel is Ellipsis or (isinstance(sel, tuple) and sel == ()):
        return 0, length
    return None


def check_rows(meta: ScanMeta, rel: str, arr: np.ndarray, lo: int, read: RowReader) -> None:
    """Check the rows ``lo .. lo + len(arr)`` of dataset ``rel`` of the scan just read."""
    if arr.ndim == 0 or arr.shape[0] == 0:
        return
    hi = lo + arr.shape[0]
    parts = rel.split("/")
    if rel == L.D_POINTS:
        _check_points(meta, arr, lo)
    elif rel == L.D_RADIUS:
        _check_radius(meta, rel, arr, lo, meta.n_ordered)
        _check_inf_roots(meta, arr, lo, read)
        tail = arr[max(0, meta.n_ordered - lo) :]
        if tail.size and (tail != 0).any():
            raise meta.error(f"has radius != 0 beyond n_ordered={meta.n_ordered}")
    elif rel == L.D_RADIUS_INDEX:
        _check_radius(meta, rel, arr, lo, hi)
    elif rel in (L.D_PARENT,):
        _check_parent(meta, rel, arr, lo, meta.n_ordered)
    elif rel in (L.D_SOURCE_INDEX, L.D_SEEDS):
        _check_index(meta, rel, arr, distinct=rel == L.D_SOURCE_INDEX)
    elif len(parts) == 3 and parts[0] == L.G_ORDERINGS:
        if parts[2] == L.D_ORDER:
            _check_index(meta, rel, arr, distinct=True)
        elif parts[2] == L.D_RADIUS:
            _check_radius(meta, rel, arr, lo, hi)
        elif parts[2] == L.D_PARENT:
            _check_parent(meta, rel, arr, lo, hi)


def _check_points(meta: ScanMeta, raw: np.ndarray, lo: int) -> None:
    # decoding is exact and increasing per axis (scale > 0), so the decoded extremes are the
    # extremes decoded; a NaN makes min/max NaN, which fails the comparisons
    cols = [raw[:, j] for j in range(3)]  # column reductions: min(axis=0) is 25x slower
    ext = np.array([[c.min() for c in cols], [c.max() for c in cols]], dtype=raw.dtype)
    ext = L.decode_points(ext, meta.encoding, meta.offset, meta.scale)
    if (ext[0] >= meta.bounds_min).all() and (ext[1] <= meta.bounds_max).all():
        return
    pts = L.decode_points(raw, meta.encoding, meta.offset, meta.scale)
    # one pass: NaN fails both comparisons, inf lies outside the (finite) bounds
    bad = ~((pts >= meta.bounds_min) & (pts <= meta.bounds_max)).all(axis=1)
    if not bad.any():
        return
    i = int(np.argmax(bad))
    if not np.isfinite(pts[i]).all():
        raise meta.error(f"has a NaN or inf coordinate at stored position {lo + i}")
    raise meta.error(
        f"has point {lo + i} at {pts[i].tolist()}, outside its bounds "
        f"{meta.bounds_min.tolist()} .. {meta.bounds_max.tolist()}"
    )


def _check_radius(meta: ScanMeta, rel: str, arr: np.ndarray, lo: int, ordered_end: int) -> None:
    nan = np.isnan(arr)
    if nan.any():
        raise meta.error(f"dataset {rel!r} holds NaN at row {lo + int(np.argmax(nan))}")
    if (arr < 0).any():
        raise meta.error(
            f"dataset {rel!r} holds a negative radius at row {lo + int(np.argmax(arr < 0))}"
        )
    head = arr[: max(0, ordered_end - lo)]
    if head.size > 1:
        inc = head[1:] > head[:-1]
        if inc.any():
            i = int(np.argmax(inc)) + 1
            raise meta.error(
                f"dataset {rel!r} increases at row {lo + i} ({float(head[i - 1])!r} -> {float(head[i])!r}); "
                "radii must be non-increasing"
            )


def _check_inf_roots(meta: ScanMeta, arr: np.ndarray, lo: int, read: RowReader) -> None:
    """Radius inf marks a root (a seed or the first point of a component): its parent is -1."""
    inf = np.flatnonzero(np.isinf(arr[: max(0, meta.n_ordered - lo)])) + lo
    inf = inf[inf >= meta.n_seeds]  # seeds are roots by construction
    if not inf.size:
        return
    a, b = int(inf[0]), int(inf[-1]) + 1
    parent = np.asarray(read(L.D_PARENT, a, b))[inf - a]
    bad = np.flatnonzero(parent != -1)
    if bad.size:
        i = int(inf[bad[0]])
        raise meta.error(
            f"dataset 'radius' is inf at row {i} but its parent is {int(parent[bad[0]])}; only "
            "roots (parent -1) have radius inf"
        )


def _check_parent(meta: ScanMeta, rel: str, arr: np.ndarray, lo: int, ordered_end: int) -> None:
    rows = np.arange(lo, lo + arr.shape[0])
    head = slice(0, max(0, ordered_end - lo))
    bad = (arr[head] < -1) | (arr[head] >= rows[head])
    if bad.any():
        i = int(np.argmax(bad))
        raise meta.error(
            f"dataset {rel!r} gives row {lo + i} the parent {int(arr[i])}; parents come earlier"
        )
    tail = arr[max(0, ordered_end - lo) :]
    if tail.size and (tail != -1).any():
        raise meta.error(f"dataset {rel!r} has parents beyond n_ordered={meta.n_ordered}")


def _check_index(meta: ScanMeta, rel: str, arr: np.ndarray, distinct: bool) -> None:
    n = meta.n_points
    bad = (arr < 0) | (arr >= n)
    if bad.any():
        raise meta.error(f"dataset {rel!r} holds {int(arr[int(np.argmax(bad))])}, outside [0, {n})")
    if distinct and not _distinct(arr, n):
        raise meta.error(f"dataset {rel!r} holds the same position twice")


def _distinct(arr: np.ndarray, n: int) -> bool:
    """No value twice in ``arr`` (values in [0, n)): a mask of n flags (O(n) bytes, no sort)
    unless ``arr`` is tiny next to n (then sorting it is cheaper)."""
    if arr.size * 64 >= n:
        seen = np.zeros(n, dtype=bool)
        seen[arr] = True
        return int(np.count_nonzero(seen)) == arr.size
    return bool(np.unique(arr).size == arr.size)


def check_rho_prefix(meta: ScanMeta, k: int, rho: float, read: RowReader) -> None:
    """The prefix of length ``k`` found for ``rho`` is the shortest whose bound is <= rho:
    radius[k - 1] > rho >= radius[k] (the ends excepted)."""
    lo = max(0, k - 1)
    hi = min(k + 1, meta.n_ordered)
    r = np.asarray(read(L.D_RADIUS, lo, hi), dtype=np.float64)
    before = r[0] if k >= 2 else math.inf
    after = r[-1] if k < meta.n_ordered else 0.0
    if not (before > rho >= after):
        raise meta.error(
            f"dataset 'radius_index' does not match 'radius': the level for rho={rho} came out "
            f"with {k} points"
        )


# ---------------------------------------------------------------------------------------------
# datasets handed out by the reader


class CheckedDataset:
    """A dataset of a scan whose reads go through the scan's checked read."""

    def __init__(self, ds: Any, read: Callable[[Any, Any], np.ndarray]) -> None:
        self._ds, self._read = ds, read

    def __getitem__(self, sel: Any) -> np.ndarray:
        return self._read(self._ds, sel)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        arr = self._read(self._ds, ())
        return arr if dtype is None else arr.astype(dtype)

    def __len__(self) -> int:
        return len(self._ds)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ds, name)


def json_attr(meta: ScanMeta, attrs: Any, key: str) -> dict[str, Any]:
    """The JSON object stored in attribute ``key`` ({} when absent)."""
    try:
        value = L.from_json(_scalar(attrs.get(key, "")))
    except (ValueError, TypeError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise meta.error(f"attribute {key!r} is not valid JSON ({str(exc)[:80]})") from None
    if not isinstance(value, dict):
        raise meta.error(f"attribute {key!r} is not a JSON object")
    return value
