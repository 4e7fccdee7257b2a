"""The lodbuilder exception hierarchy.

Every error a user can cause is one of these. Each subclasses the matching built-in, so
``except ValueError`` keeps working, and each message names the input, what was wrong with it
and what to do about it, on one line.
"""

from __future__ import annotations


class LodbuilderError(Exception):
    """Base class of every error lodbuilder raises on purpose."""


class InputError(LodbuilderError, ValueError):
    """An argument (array, option, parameter) is not acceptable."""


class LevelBeyondOrderingError(InputError):
    """A level finer than a partial build (``--size``/``--rho``) ordered: rebuild further."""


class PrecisionError(InputError):
    """The coordinates' spread or the voxel/band size leaves no radius float arithmetic can
    promise (a stored radius must never be below the true covering radius)."""


class FormatError(LodbuilderError, ValueError):
    """A scan file is malformed, truncated or lacks what lodbuilder needs (e.g. x/y/z)."""


class EmptyScanError(FormatError):
    """A scan file holds no points (a joint build keeps it as a member with none)."""


class UnsupportedFormatError(LodbuilderError, ValueError):
    """No reader or writer is registered for a file's suffix."""


class MissingDependencyError(LodbuilderError, ImportError):
    """An optional dependency needed for this feature is not installed."""


class ScanFileError(LodbuilderError, OSError):
    """A scan file is missing or cannot be read."""


class ArchiveError(LodbuilderError, OSError):
    """An archive cannot be opened, read or written."""


class WorkStoreError(LodbuilderError, OSError):
    """The work store of a tiled build (``--work-dir URL``) cannot be written or read."""


class NotAnArchiveError(ArchiveError):
    """The file exists but is not an lodbuilder archive."""


class SchemaVersionError(ArchiveError):
    """The archive was written by a newer lodbuilder with a schema this version cannot read."""


class CorruptArchiveError(ArchiveError):
    """The archive's data fails a checksum or an invariant."""


class ScanNotFoundError(LodbuilderError, LookupError):
    """A scan name is not in the archive."""

    def __str__(self) -> str:  # LookupError would otherwise quote the message like a key
        return str(self.args[0]) if self.args else ""


class MemoryBudgetError(LodbuilderError, MemoryError):
    """The requested grid would need more memory than the stated budget."""


class BuildError(LodbuilderError, RuntimeError):
    """One or more scans of a collection failed to build."""


class EngineError(LodbuilderError, RuntimeError):
    """An ordering failed the engine's own check of its result: a bug in lodbuilder, not in the
    input. Please report it with the input that caused it."""


class UnsafeArchiveError(ArchiveError):
    """The archive points outside itself (external links, external raw storage, virtual
    datasets): refused before anything is read."""


class ArchiveBusyError(ArchiveError):
    """Another process is writing the archive (a build, or an update) and did not finish within
    the time the caller agreed to wait."""
