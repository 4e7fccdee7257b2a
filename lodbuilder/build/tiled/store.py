"""Where a tiled build keeps its work files: a local directory (beside the archive, the default)
or an object store reached through fsspec (``s3://bucket/prefix``, ``gs://...``, ``memory://...``),
so that the parent and the workers of a cluster need no shared file system.

The one interface, :class:`Store`, is what the tasks and the parent use: a file (an *object*) is
written whole (:meth:`Store.writer`, :meth:`Store.put`: it appears under its name only when it is
complete, with the size and CRC-32 of its bytes, :mod:`.sums`), read whole or by byte ranges
(:meth:`Store.read_array`, :meth:`Store.read_ranges`), listed and deleted. There are no memory maps
and no writes into the middle of an object: a task writes whole objects (several per task), and
the marker of a finished piece is the last object its task (or the parent) writes, so the resume
rules of :mod:`.sums` hold on both stores alike.

* :class:`LocalStore`: a directory; objects are written to a temporary and renamed into place,
  not flushed to the device (:mod:`lodbuilder._atomic`, work files: their checksums stand in).
  The bytes are those the tiled build always wrote.
* :class:`FsspecStore`: a prefix of an fsspec file system. An object is written to a temporary
  file of the worker (``$TMPDIR``) and uploaded on commit (``put_file``: an S3 object appears only
  when its upload completes); byte ranges are ranged GETs, several at once where the file system
  is asynchronous (``cat_ranges``). Credentials and endpoints come from fsspec's usual
  configuration (environment variables such as ``AWS_ACCESS_KEY_ID`` / ``AWS_ENDPOINT_URL``, or
  ``FSSPEC_S3_ENDPOINT_URL``, or ``~/.config/fsspec``), read by the parent: the store carries the
  resolved options to the workers when it is pickled.

A task's first argument is its store (or a local directory's path, which :func:`as_store` turns
into a :class:`LocalStore`).
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
import threading
import zlib
from pathlib import Path
from typing import Any, cast

import numpy as np

from .urls import is_remote, url_to_fs

#: bytes of the gap between two wanted ranges below which one ranged read takes both (object store)
REMOTE_GAP = 1 << 20
#: rows of the gap below which a local read takes both ranges (a seek costs little)
LOCAL_GAP_ROWS = 64
#: the object that marks a prefix of an object store as a tiled build's work files
OWNER = ".lodbuilder-work"
#: lines of a task log object on an object store (then the process starts another)
LOG_LINES = 500

#: (store URL, claim, log name, pid) -> (object, its lines): the task log objects of this process
_LOGS: dict[tuple[str, str, str, int], tuple[str, list[str]]] = {}
_LOGS_LOCK = threading.Lock()


def _bytes(data: Any) -> Any:
    return np.ascontiguousarray(data) if isinstance(data, np.ndarray) else data


def _nbytes(data: Any) -> int:
    return int(data.nbytes) if isinstance(data, np.ndarray) else memoryview(data).nbytes


class Writer:
    """An object being written: :meth:`write` appends (keeping its size and CRC-32),
    :meth:`commit` makes it appear under its name, whole; closing without a commit discards it."""

    def __init__(self, f: Any) -> None:
        self._f = f
        self.size = 0
        self.crc = 0
        self.done = False

    def write(self, data: Any) -> None:
        data = _bytes(data)
        self.crc = zlib.crc32(cast(Any, data), self.crc)
        self.size += _nbytes(data)
        self._f.write(data)

    @property
    def sum(self) -> list[int]:
        return [self.size, self.crc]

    def commit(self) -> list[int]:
        if not self.done:
            self._f.close()
            self._publish()
            self.done = True
        return self.sum

    def close(self) -> None:
        """Discard the object unless it was committed."""
        if not self.done:
            self.done = True
            with contextlib.suppress(OSError):
                self._f.close()
            self._discard()

    def _publish(self) -> None:  # pragma: no cover - implemented by the stores' writers
        raise NotImplementedError

    def _discard(self) -> None:  # pragma: no cover
        raise NotImplementedError

    def __enter__(self) -> Writer:
        return self

    def __exit__(self, exc_type: Any, *exc: Any) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.close()


class Store:
    """The work files of one tiled build (see the module)."""

    url: str  # what messages show, and what tells two stores apart
    local = False

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.url!r})"

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and other.url == self.url

    def __hash__(self) -> int:
        return hash((type(self).__name__, self.url))

    def writer(self, name: str) -> Writer:
        raise NotImplementedError

    def put(self, name: str, data: Any) -> list[int]:
        """Write the object ``name`` whole (an array's raw bytes, or bytes); returns [size, crc]."""
        with self.writer(name) as w:
            w.write(data)
        return w.sum

    def get(self, name: str) -> bytes:
        """The whole object (FileNotFoundError when missing)."""
        raise NotImplementedError

    def marker(self, name: str) -> bytes | None:
        """The bytes of a marker object, None when there is none (one request on an object store)."""
        try:
            return self.get(name)
        except FileNotFoundError:
            return None

    def read_ranges(self, name: str, starts: list[int], ends: list[int]) -> list[bytes]:
        """The byte ranges ``[start, end)`` of the object, in the order given."""
        raise NotImplementedError

    def size(self, name: str) -> int | None:
        """The object's size in bytes, None when it is missing (or is not a plain object)."""
        raise NotImplementedError

    def tail(self, name: str, nbytes: int) -> bytes:
        """The object's last ``nbytes`` bytes (all of it when it is shorter; FileNotFoundError
        when it is missing)."""
        size = self.size(name)
        if size is None:
            raise FileNotFoundError(f"{self.url}: {name} is missing")
        (raw,) = self.read_ranges(name, [max(0, size - nbytes)], [size])
        return raw

    def names(self, prefix: str = "") -> list[str]:
        """The names of the objects whose names start with ``prefix``, sorted."""
        raise NotImplementedError

    def delete(self, name: str) -> None:
        """Delete the object (nothing to do when it is missing)."""
        raise NotImplementedError

    def delete_many(self, names: list[str]) -> None:
        """Delete the objects (those missing are no matter)."""
        for name in names:
            self.delete(name)

    def open(self, name: str) -> Any:
        """A binary file object reading the object sequentially."""
        raise NotImplementedError

    def log(self, name: str, line: str) -> None:
        """Add ``line`` to the task log ``name`` (a local file appended to; on an object store one
        small object per line, ``name.<n>``; :meth:`log_lines` reads them back)."""
        raise NotImplementedError

    def log_lines(self, prefix: str) -> list[str]:
        raise NotImplementedError

    gap_rows = LOCAL_GAP_ROWS

    @property
    def verified(self) -> set[str]:
        """The markers found done (with their files) since :meth:`claim` (see :mod:`.sums`)."""
        if "_verified" not in self.__dict__:
            self._verified: set[str] = set()
        return self._verified

    def gap(self, width: int) -> int:
        """Rows of a gap that one read takes rather than two (see :func:`.workdir.gather`)."""
        return self.gap_rows

    # ------------------------------------------------------------------ derived reads

    def read_array(self, name: str, dtype: Any, start: int = 0, count: int | None = None) -> np.ndarray:
        """Rows ``start .. start + count`` (default: to the end) of the object as records ``dtype``
        (a writable array); OSError when the object holds fewer rows."""
        dt = np.dtype(dtype)
        if count is None:
            size = self.size(name)
            if size is None:
                raise FileNotFoundError(f"{self.url}: {name} is missing")
            count = max(0, size // dt.itemsize - start)
        if count == 0:
            return np.zeros(0, dt)
        (raw,) = self.read_ranges(name, [start * dt.itemsize], [(start + count) * dt.itemsize])
        if len(raw) != count * dt.itemsize:
            raise OSError(f"{self.url}: {name} is truncated ({len(raw) // dt.itemsize} of {count} rows)")
        return np.frombuffer(bytearray(raw), dtype=dt)

    def load_npy(self, name: str) -> np.ndarray:
        return np.load(io.BytesIO(self.get(name)))

    def sum(self, name: str, chunk: int = 1 << 23) -> list[int]:
        """Size and CRC-32 of the object, read in chunks."""
        crc = size = 0
        with self.open(name) as f:
            while data := f.read(chunk):
                crc = zlib.crc32(data, crc)
                size += len(data)
        return [size, crc]

    def clear(self) -> None:
        """Delete every object of the store."""
        self.delete_many(self.names())

    def claim(self) -> None:
        """Make the store ready for a build (or check that what a stopped build left is lodbuilder's)."""
        self.verified.clear()

    def remove(self) -> None:
        """Delete the store and what it holds (a finished build)."""
        self.clear()


# ------------------------------------------------------------------------------ local directory


class _LocalWriter(Writer):
    def __init__(self, tmp: Path, path: Path) -> None:
        super().__init__(open(tmp, "wb"))  # noqa: SIM115 - closed by commit()/close()
        self.tmp, self.path = tmp, path

    def _publish(self) -> None:
        from ..._atomic import publish

        publish(self.tmp, self.path, durable=False)

    def _discard(self) -> None:
        with contextlib.suppress(OSError):
            self.tmp.unlink()


class LocalStore(Store):
    """A work directory on a local (or shared) file system: today's files and bytes."""

    local = True

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        self.url = str(self.root)

    def path(self, name: str) -> Path:
        return self.root / name

    def claim(self) -> None:
        """Create the work directory with lodbuilder's marker, or check the one that is there."""
        from ...archive.files import make_own_dir

        self.verified.clear()
        self.root.parent.mkdir(parents=True, exist_ok=True)  # (a --work-dir DIR: DIR/ARCHIVE/)
        make_own_dir(self.root, self.root.name)

    def remove(self) -> None:
        from ...archive.files import remove_own_dir

        remove_own_dir(self.root, self.root.name)

    def writer(self, name: str) -> Writer:
        from . import layout as WL

        return _LocalWriter(self.root / WL.writing(name), self.root / name)

    def put(self, name: str, data: Any) -> list[int]:
        from ..._atomic import replace_with

        data = _bytes(data)

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                f.write(data)

        replace_with(self.root / name, write, durable=False)
        return [_nbytes(data), zlib.crc32(cast(Any, data))]

    def get(self, name: str) -> bytes:
        return (self.root / name).read_bytes()

    def marker(self, name: str) -> bytes | None:
        path = self.root / name
        if not path.exists():
            return None
        try:
            return path.read_bytes()
        except OSError:
            return b""  # (there but unreadable: a damaged record)

    def read_ranges(self, name: str, starts: list[int], ends: list[int]) -> list[bytes]:
        out = []
        with open(self.root / name, "rb", buffering=0) as f:
            for a, z in zip(starts, ends, strict=True):
                f.seek(a)
                out.append(f.read(z - a))
        return out

    def read_array(self, name: str, dtype: Any, start: int = 0, count: int | None = None) -> np.ndarray:
        dt = np.dtype(dtype)
        path = self.root / name
        if count is None:
            count = max(0, path.stat().st_size // dt.itemsize - start)
        with open(path, "rb") as f:
            f.seek(start * dt.itemsize)
            a = np.fromfile(f, dtype=dt, count=count)
        if a.shape[0] != count:
            raise OSError(f"{path}: truncated ({start + a.shape[0]} of {start + count} rows)")
        return a

    def load_npy(self, name: str) -> np.ndarray:
        return np.load(self.root / name)

    def size(self, name: str) -> int | None:
        import stat

        try:
            st = os.lstat(self.root / name)
        except FileNotFoundError:
            return None
        return int(st.st_size) if stat.S_ISREG(st.st_mode) else None

    def names(self, prefix: str = "") -> list[str]:
        try:
            return sorted(e.name for e in os.scandir(self.root) if e.name.startswith(prefix) and e.is_file())
        except FileNotFoundError:
            return []

    def delete(self, name: str) -> None:
        (self.root / name).unlink(missing_ok=True)

    def open(self, name: str) -> Any:
        return open(self.root / name, "rb")  # noqa: SIM115 - the caller closes it

    def log(self, name: str, line: str) -> None:
        with contextlib.suppress(OSError), open(self.root / name, "a") as f:
            f.write(line + "\n")  # one short line: one write, whole or absent

    def log_lines(self, prefix: str) -> list[str]:
        out = []
        for n in self.names(prefix):
            with contextlib.suppress(OSError):
                out += (self.root / n).read_text().splitlines()
        return out


# ------------------------------------------------------------------------------ object store


class _RemoteWriter(Writer):
    def __init__(self, store: FsspecStore, name: str) -> None:
        fd, tmp = tempfile.mkstemp(prefix="lodbuilder-", suffix=".part")
        super().__init__(os.fdopen(fd, "wb"))
        self.tmp, self.store, self.name = tmp, store, name

    def _publish(self) -> None:
        try:
            self.store.fs.put_file(self.tmp, self.store.key(self.name))
        finally:
            self._discard()

    def _discard(self) -> None:
        with contextlib.suppress(OSError):
            os.unlink(self.tmp)


class FsspecStore(Store):
    """A prefix of an fsspec file system (an object store). Picklable: the file system's options
    travel with it to the workers."""

    gap_rows = 0  # (see gap())

    def __init__(self, url: str, fs: Any = None, **storage_options: Any) -> None:
        self.url = url.rstrip("/")
        if fs is None:
            fs, _ = url_to_fs(self.url, **storage_options)
        self.fs = fs
        self.root = fs._strip_protocol(self.url).rstrip("/")
        self._whole = _one_request(fs)

    def key(self, name: str) -> str:
        return f"{self.root}/{name}"

    def gap(self, width: int) -> int:
        return max(LOCAL_GAP_ROWS, REMOTE_GAP // max(width, 1))

    def claim(self) -> None:
        """Write the store's owner object (:data:`OWNER`), or fail in one line before any work
        when the store cannot be written (a missing bucket, wrong credentials, no endpoint)."""
        import uuid

        from ...errors import WorkStoreError

        self.verified.clear()
        self.claimed = uuid.uuid4().hex[:12]  # (travels to the workers: their task logs start afresh)
        try:
            self.put(OWNER, b"lodbuilder tiled build work files\n")
        except Exception as exc:  # noqa: BLE001 - any failure of the file system, said in one line
            text = " ".join(str(exc).split()) or type(exc).__name__
            raise WorkStoreError(f"work store {self.url}: cannot write there ({text}); check the URL, and the "
                                 "credentials and endpoint in fsspec's configuration (AWS_* or FSSPEC_S3_* "
                                 "variables, ~/.config/fsspec)") from None

    def writer(self, name: str) -> Writer:
        return _RemoteWriter(self, name)

    def put(self, name: str, data: Any) -> list[int]:
        data = _bytes(data)
        raw = data.tobytes() if isinstance(data, np.ndarray) else bytes(data)
        self.fs.pipe_file(self.key(name), raw)
        return [len(raw), zlib.crc32(raw)]

    def get(self, name: str) -> bytes:
        return cast(bytes, self.fs.cat_file(self.key(name), **self._whole))

    def read_array(self, name: str, dtype: Any, start: int = 0, count: int | None = None) -> np.ndarray:
        if count is not None or start != 0:
            return super().read_array(name, dtype, start, count)
        dt = np.dtype(dtype)  # (the whole object: one GET, without asking its size first)
        try:
            raw = self.get(name)
        except FileNotFoundError:
            raise FileNotFoundError(f"{self.url}: {name} is missing") from None
        return np.frombuffer(bytearray(raw[: len(raw) // dt.itemsize * dt.itemsize]), dtype=dt)

    def read_ranges(self, name: str, starts: list[int], ends: list[int]) -> list[bytes]:
        if not starts:
            return []
        key = self.key(name)
        if len(starts) == 1:
            return [self.fs.cat_file(key, start=starts[0], end=ends[0])]
        return cast(list[bytes], self.fs.cat_ranges([key] * len(starts), list(starts), list(ends)))

    def tail(self, name: str, nbytes: int) -> bytes:
        """One GET of a suffix range (``bytes=-nbytes``: the whole object when it is shorter),
        without asking the object's size first."""
        try:
            return cast(bytes, self.fs.cat_file(self.key(name), start=-max(1, int(nbytes))))
        except FileNotFoundError:
            raise FileNotFoundError(f"{self.url}: {name} is missing") from None

    def _fresh(self) -> None:
        """Forget fsspec's listings of the store (other processes write into it)."""
        self.fs.invalidate_cache(self.root)

    def size(self, name: str) -> int | None:
        self._fresh()
        try:
            info = self.fs.info(self.key(name))
        except (FileNotFoundError, OSError):
            return None
        return int(info["size"]) if info.get("type") == "file" else None

    def names(self, prefix: str = "") -> list[str]:
        self._fresh()
        try:
            found = self.fs.ls(self.root, detail=False)
        except FileNotFoundError:
            return []
        finally:
            self._fresh()
        names = (str(p).rstrip("/").rsplit("/", 1)[-1] for p in found)
        return sorted(n for n in names if n.startswith(prefix))

    def delete(self, name: str) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.fs.rm_file(self.key(name))

    def delete_many(self, names: list[str]) -> None:
        """One request per thousand objects on S3 (s3fs deletes a list of keys in bulk)."""
        keys = [self.key(n) for n in names]
        if keys:
            with contextlib.suppress(FileNotFoundError):
                self.fs.rm(keys)

    def open(self, name: str) -> Any:
        self._fresh()
        return self.fs.open(self.key(name), "rb", block_size=1 << 23, cache_type="readahead")

    def log(self, name: str, line: str) -> None:
        """The lines this process logged under ``name`` so far (up to :data:`LOG_LINES`) are one
        object, written whole again with each line: a task's line is there when the task ends,
        and reading the logs back takes a request per process rather than per task."""
        import uuid

        with _LOGS_LOCK:  # (threads of one worker: one object, its lines in order)
            key = (self.url, self.__dict__.get("claimed", ""), name, os.getpid())  # (a later build: new lines)
            obj, lines = _LOGS.get(key) or (f"{name}.{uuid.uuid4().hex[:12]}", [])
            lines.append(line)
            _LOGS[key] = (obj, lines) if len(lines) < LOG_LINES else (f"{name}.{uuid.uuid4().hex[:12]}", [])
            with contextlib.suppress(OSError):
                self.put(obj, ("\n".join(lines) + "\n").encode())

    def log_lines(self, prefix: str) -> list[str]:
        names = self.names(prefix)
        if not names:
            return []
        keys = [self.key(n) for n in names]
        got = self.fs.cat(keys, on_error="omit", **self._whole)
        return [ln for k in keys if isinstance(got.get(k), bytes) for ln in got[k].decode().splitlines()]


def _one_request(fs: Any) -> dict[str, Any]:
    """The keywords that make ``fs.cat_file`` of a whole object one GET: s3fs asks the object's
    size first (a HEAD, and for a missing object a listing too) to split a large object into
    concurrent ranged GETs unless ``max_concurrency`` is 1. Work objects are read by many tasks at
    once, each its own: the extra requests were a third of a tiled build's."""
    import inspect

    try:
        params = inspect.signature(fs._cat_file).parameters
    except (AttributeError, TypeError, ValueError):
        return {}
    return {"max_concurrency": 1} if "max_concurrency" in params else {}


def as_store(work: Store | str | os.PathLike[str]) -> Store:
    """``work`` as a store: a Store as it is, a URL as an :class:`FsspecStore`, a path as a
    :class:`LocalStore`."""
    if isinstance(work, Store):
        return work
    text = os.fspath(work)
    if is_remote(text):
        return FsspecStore(text)
    if text.startswith("file://"):
        text = text[len("file://"):]
    return LocalStore(Path(text))
