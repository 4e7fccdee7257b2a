"""What a build returns: one :class:`ScanStatus` per scan and the :class:`BuildResult` around them.

The command line prints from these (and ``--json`` dumps :meth:`BuildResult.to_json`), so nothing
reopens the archive to learn what a build did.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .._validate import strict_methods

#: the statuses a scan can end with
STATUSES = ("built", "recovered", "skipped", "failed")


@strict_methods
@dataclass
class ScanStatus:
    """What happened to one scan: ``built``, ``recovered`` (a finished part of an interrupted build
    merged without rebuilding), ``skipped`` (already in the archive with the same source, pose and
    parameters) or ``failed`` (with ``error``, one line).

    ``method`` is ``"in-memory"`` or ``"tiled"`` (the out-of-core path); ``exception`` keeps the
    error itself for :func:`lodbuilder.build_archive` to re-raise for a single scan."""

    name: str
    source: str
    status: str
    n_points: int | None = None
    seconds: float | None = None
    error: str | None = None
    worker_pid: int | None = None
    n_ordered: int | None = None
    encoding: str | None = None
    method: str | None = None
    phases: dict[str, float] = field(default_factory=dict)
    exception: BaseException | None = field(default=None, repr=False, compare=False)

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"name": self.name, "source": self.source, "status": self.status}
        for key in ("n_points", "n_ordered", "encoding", "method", "seconds", "worker_pid", "error"):
            value = getattr(self, key)
            if value is not None:
                out[key] = round(value, 4) if isinstance(value, float) else value
        if self.phases:
            out["phases"] = {k: round(v, 4) for k, v in self.phases.items()}
        return out


@strict_methods
@dataclass
class BuildResult:
    """The scans of one :func:`lodbuilder.build_archive` call and where they went.

    ``archive_scans`` is the number of scans the archive holds after the build (0 when no archive
    exists: nothing was built into a new one)."""

    archive: Path
    scans: list[ScanStatus] = field(default_factory=list)
    seconds: float = 0.0
    executor: str = ""
    startup_seconds: float = 0.0  # starting the pool / connecting to or starting the Dask cluster
    merge_seconds: float = 0.0  # merging finished parts into the archive (in the parent)
    archive_scans: int = 0

    def __fspath__(self) -> str:
        """A result stands for its archive where a path is expected (``open_archive(result)``)."""
        return str(self.archive)

    def by_status(self, status: str) -> list[ScanStatus]:
        return [s for s in self.scans if s.status == status]

    @property
    def failed(self) -> list[ScanStatus]:
        return self.by_status("failed")

    @property
    def built(self) -> list[ScanStatus]:
        return [s for s in self.scans if s.status in ("built", "recovered")]

    @property
    def ok(self) -> bool:
        return not self.failed

    @property
    def archive_exists(self) -> bool:
        return self.archive_scans > 0

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for s in self.scans:
            out[s.status] = out.get(s.status, 0) + 1
        return out

    def summary(self) -> dict[str, Any]:
        """Counts and times (the scans themselves are in :meth:`to_json`)."""
        return {"archive": str(self.archive), "seconds": round(self.seconds, 3), "executor": self.executor,
                "startup_seconds": round(self.startup_seconds, 3), "merge_seconds": round(self.merge_seconds, 3),
                "archive_scans": self.archive_scans, **self.counts()}

    def to_json(self) -> dict[str, Any]:
        doc = self.summary()
        doc["n_points"] = int(sum(s.n_points or 0 for s in self.built))
        doc["scans"] = [s.to_json() for s in self.scans]
        return doc

    def describe(self, shown: str | None = None) -> str:
        """The one summary line the command line prints; ``shown``: the archive's name as the user
        gave it (default: the resolved path)."""
        archive = self.archive if shown is None else shown
        counts = self.counts()
        parts = [f"{counts[k]} {k}" for k in STATUSES if counts.get(k)]
        where = f" on {self.executor}" if self.executor else ""
        if not self.archive_exists:
            return f"{', '.join(parts)} scan(s); no archive written ({archive} does not exist)"
        return (f"{', '.join(parts)} scan(s) into {archive}{where} in {self.seconds:.1f} s; "
                f"the archive holds {self.archive_scans} scan(s)")


#: the collection builder's old name for the result
CollectionResult = BuildResult

StatusCallback = Callable[[ScanStatus], None] | None
