"""What the viewer shows, as plain arrays (no PyVista here).

:class:`ViewData` holds one or more scans in farthest-point order: the points, their insertion
radii and parents (stored positions), attributes and importance maps. Several scans are merged
into one ordering by insertion radius, so the prefix of the merged ordering that the slider picks
is exactly the union of every scan's level at the same rho.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError

BASE_MODES = ("rgb", "radius", "rank", "scan", "voronoi")
#: modes whose colours depend on the level (recomputed when it changes); ``gaps`` is asked for by
#: name (``--colour gaps``), not cycled through: it searches the level for holes
LEVEL_MODES = ("voronoi", "gaps")
GAP_COLOURS = np.array([[200, 200, 200], [220, 30, 30], [240, 150, 0]], dtype=np.uint8)


@dataclass
class ViewData:
    """Points in farthest-point order and what can colour them.

    Attributes:
        points: (N, 3) float64, stored order (a level is a prefix).
        radius: (N,) non-increasing insertion radii (inf for seeds).
        parent: (N,) stored position of each point's parent, -1 for roots; parent[i] < i.
        attributes: per-point arrays in the same order (``red``/``green``/``blue`` give RGB).
        importance: per-point importance maps in the same order.
        scan_id: (N,) int32 index into ``scan_names``.
        scan_names: the names of the scans shown.
    """

    points: np.ndarray
    radius: np.ndarray
    parent: np.ndarray
    attributes: dict[str, np.ndarray] = field(default_factory=dict)
    importance: dict[str, np.ndarray] = field(default_factory=dict)
    scan_id: np.ndarray | None = None
    scan_names: tuple[str, ...] = ("scan",)

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        n = self.points.shape[0]
        if self.points.ndim != 2 or self.points.shape[1] != 3 or n == 0:
            raise InputError(f"points must have shape (N, 3) with N >= 1, got {self.points.shape}")
        self.radius = np.asarray(self.radius, dtype=np.float64)
        self.parent = np.asarray(self.parent, dtype=np.int64)
        for name, arr in (("radius", self.radius), ("parent", self.parent)):
            if arr.shape != (n,):
                raise InputError(f"{name} must have shape ({n},) like the points, got {arr.shape}")
        for group in (self.attributes, self.importance):
            for name, arr in group.items():
                if np.shape(arr)[0] != n:
                    raise InputError(
                        f"per-point array {name!r} has {np.shape(arr)[0]} rows, expected {n}"
                    )
        if self.scan_id is None:
            self.scan_id = np.zeros(n, dtype=np.int32)
        self._rep_cache: tuple[int, np.ndarray] | None = None
        self._gap_cache: tuple[int, np.ndarray] | None = None
        finite = self.radius[np.isfinite(self.radius) & (self.radius > 0)]
        self._rmax = float(finite.max()) if finite.size else 1.0
        self._rmin = float(finite.min()) if finite.size else 1.0
        lo, hi = self.points.min(axis=0), self.points.max(axis=0)
        self.diagonal = float(np.linalg.norm(hi - lo)) or 1.0

    def __len__(self) -> int:
        return int(self.points.shape[0])

    # ---- levels -------------------------------------------------------------------------------

    def size_for_rho(self, rho: float) -> int:
        """Shortest prefix whose next insertion radius is <= rho (at least 1 point)."""
        return max(1, int(np.searchsorted(-self.radius, -float(rho), side="left")))

    def rho_for_size(self, k: int) -> float:
        """The density a prefix of ``k`` points guarantees: the next insertion radius (0 at N)."""
        k = int(k)
        if k >= len(self):
            return 0.0
        r = float(self.radius[k])
        return r if math.isfinite(r) else self._rmax

    def clamp_size(self, k: float) -> int:
        return int(min(len(self), max(1, int(round(k)))))

    def selective(self, k: int, lo, hi, factor: float = 4.0) -> np.ndarray:
        """Stored positions of a level finer inside the box [lo, hi], as the archive's
        ``refine_box``: the prefix of ``k`` points (density rho = ``rho_for_size(k)``) plus every
        point of the prefix at rho / ``factor`` that lies in the box grown by rho / ``factor``.

        Every point inside the box is then within rho / factor of a shown point. Sorted positions.
        """
        from ..archive.levels import check_box, in_box

        k = self.clamp_size(k)
        box = check_box(np.concatenate([np.ravel(lo), np.ravel(hi)]))
        rho_in = self.rho_for_size(k) / float(factor)
        k_in = self.size_for_rho(rho_in) if rho_in > 0 else len(self)
        inside = in_box(self.points[k:k_in], box, rho_in)
        return np.concatenate([np.arange(k, dtype=np.int64), k + np.flatnonzero(inside)])

    # ---- representatives (Voronoi cells at a level) -------------------------------------------

    def representatives(self, k: int) -> np.ndarray:
        """(N,) stored position of every point's representative at level ``k`` (the archive's
        rule: the first ancestor along the parent links of rank < k; -1 when a chain ends at a
        root of rank >= k)."""
        from ..archive.levels import representatives

        k = self.clamp_size(k)
        if self._rep_cache is not None and self._rep_cache[0] == k:
            return self._rep_cache[1]
        rep = representatives(self.parent, k)
        self._rep_cache = (k, rep)
        return rep

    def gap_codes(self, k: int) -> np.ndarray:
        """(N,) 0 / 1 / 2: away from gaps / near a fillable gap / near a rough one, at level k
        (see :func:`lodbuilder.sampling.fill.near_gaps`)."""
        from ..sampling.fill import SAMPLE_FRACTION, near_gaps

        k = self.clamp_size(k)
        if self._gap_cache is None or self._gap_cache[0] != k:
            rho = self.rho_for_size(k)
            codes = np.zeros(len(self), dtype=np.uint8)
            if rho > 0:
                k_s = self.size_for_rho(SAMPLE_FRACTION * rho)
                codes = near_gaps(self.points, k, k_s, rho)
            self._gap_cache = (k, codes)
        return self._gap_cache[1]

    # ---- colour modes -------------------------------------------------------------------------

    def colour_modes(self) -> list[str]:
        """The modes this data supports, in cycling order."""
        modes = []
        if all(c in self.attributes for c in ("red", "green", "blue")):
            modes.append("rgb")
        modes += ["radius", "rank"]
        modes += [f"importance:{name}" for name in self.importance]
        if len(self.scan_names) > 1:
            modes.append("scan")
        modes.append("voronoi")
        return modes

    def check_mode(self, mode: str) -> str:
        if mode == "gaps":
            return mode
        modes = self.colour_modes()
        if mode == "importance" and any(m.startswith("importance:") for m in modes):
            mode = next(m for m in modes if m.startswith("importance:"))
        if mode not in modes:
            raise InputError(
                f"colour mode {mode!r} is not available here; choose one of {', '.join(modes)}"
            )
        return mode

    def colours(self, mode: str, k: int, positions: np.ndarray | None = None) -> np.ndarray:
        """(M, 3) uint8 colours of the points at ``positions`` (default: the whole scan) at level k.

        ``voronoi`` colours a point by its representative's cell at level ``k``, so the full scan
        shows the level's Voronoi diagram; the other modes do not depend on ``k``.
        """
        mode = self.check_mode(mode)
        sel = slice(None) if positions is None else positions
        if mode == "rgb":
            rgb = np.column_stack(
                [np.asarray(self.attributes[c])[sel] for c in ("red", "green", "blue")]
            )
            return _to_uint8_rgb(rgb)
        if mode == "radius":
            r = self.radius[sel]
            r = np.where(np.isfinite(r) & (r > 0), r, np.where(np.isinf(r), self._rmax, self._rmin))
            lo, hi = math.log(self._rmin), math.log(self._rmax)
            t = (np.log(r) - lo) / ((hi - lo) or 1.0)
            return colormap(t)
        if mode == "rank":
            pos = np.arange(len(self))[sel]
            t = np.log1p(pos) / math.log1p(max(len(self) - 1, 1))
            return colormap(t)
        if mode == "scan":
            return categorical(np.asarray(self.scan_id)[sel])
        if mode == "voronoi":
            return categorical(self.representatives(k)[sel])
        if mode == "gaps":
            return GAP_COLOURS[self.gap_codes(k)[sel]]
        name = mode.split(":", 1)[1]
        v = np.asarray(self.importance[name], dtype=np.float64)
        lo, hi = np.nanpercentile(v, [1, 99]) if v.size > 1 else (0.0, 1.0)
        t = (v[sel] - lo) / ((hi - lo) or 1.0)
        return colormap(t)

    # ---- building -----------------------------------------------------------------------------

    @classmethod
    def merge(cls, parts: Sequence[ViewData], names: Sequence[str] | None = None) -> ViewData:
        """One ViewData of several scans, merged by insertion radius (stable, descending).

        Attributes and importance maps present in every part are kept.
        """
        if len(parts) == 1:
            return parts[0]
        radius = np.concatenate([p.radius for p in parts])
        offsets = np.cumsum([0] + [len(p) for p in parts])
        perm = np.argsort(-radius, kind="stable")
        inv = np.empty_like(perm)
        inv[perm] = np.arange(perm.size)
        parent = np.concatenate(
            [np.where(p.parent >= 0, p.parent + offsets[i], -1) for i, p in enumerate(parts)]
        )
        parent = np.where(parent >= 0, inv[np.maximum(parent, 0)], -1)[perm]
        scan_id = np.concatenate([np.full(len(p), i, dtype=np.int32) for i, p in enumerate(parts)])

        def common(getter) -> dict[str, np.ndarray]:
            keys = set(getter(parts[0]))
            for p in parts[1:]:
                keys &= set(getter(p))
            return {
                k: np.concatenate([np.asarray(getter(p)[k]) for p in parts])[perm]
                for k in sorted(keys)
            }

        return cls(
            points=np.concatenate([p.points for p in parts])[perm],
            radius=radius[perm],
            parent=parent,
            attributes=common(lambda p: p.attributes),
            importance=common(lambda p: p.importance),
            scan_id=scan_id[perm],
            scan_names=tuple(names) if names else tuple(n for p in parts for n in p.scan_names),
        )


def _to_uint8_rgb(rgb: np.ndarray) -> np.ndarray:
    if rgb.dtype == np.uint8:
        return np.ascontiguousarray(rgb)
    rgb = rgb.astype(np.float64)
    top = float(np.nanmax(rgb)) if rgb.size else 1.0
    if np.issubdtype(rgb.dtype, np.floating) and top <= 1.0:
        scale = 255.0
    elif top <= 255:
        scale = 1.0
    else:
        scale = 255.0 / 65535.0  # 16-bit colours (LAS)
    return np.clip(rgb * scale, 0, 255).astype(np.uint8)


_LUT: np.ndarray | None = None


def _viridis() -> np.ndarray:
    global _LUT
    if _LUT is None:
        try:
            import matplotlib

            lut = matplotlib.colormaps["viridis"](np.linspace(0, 1, 256))[:, :3]
        except ImportError:  # a two-stop fallback: dark blue to yellow
            t = np.linspace(0, 1, 256)[:, None]
            lut = (1 - t) * np.array([0.27, 0.0, 0.33]) + t * np.array([0.99, 0.91, 0.14])
        _LUT = np.round(lut * 255).astype(np.uint8)
    return _LUT


def colormap(t: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 viridis colours of values ``t`` in [0, 1] (clipped; NaN -> 0)."""
    t = np.nan_to_num(np.asarray(t, dtype=np.float64), nan=0.0)
    idx = np.clip((t * 255.0).astype(np.int64), 0, 255)
    return _viridis()[idx]


def categorical(labels: np.ndarray) -> np.ndarray:
    """(M, 3) uint8 well-spread colours of integer labels (a hash, so equal labels match)."""
    x = np.asarray(labels).astype(np.int64).astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    x ^= x >> np.uint64(29)
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    x ^= x >> np.uint64(32)
    rgb = np.column_stack([(x >> np.uint64(s)) & np.uint64(0xFF) for s in (0, 8, 16)]).astype(
        np.int64
    )
    return (48 + rgb * 207 // 255).astype(np.uint8)  # avoid near-black cells


def from_arrays(
    points,
    radius,
    parent,
    *,
    attributes: Mapping[str, np.ndarray] | None = None,
    importance: Mapping[str, np.ndarray] | None = None,
    name: str = "scan",
) -> ViewData:
    """ViewData of one scan whose arrays are already in stored (farthest-point) order."""
    return ViewData(
        points=points,
        radius=radius,
        parent=parent,
        attributes=dict(attributes or {}),
        importance=dict(importance or {}),
        scan_names=(name,),
    )
