"""Opening untrusted HDF5 files safely: nothing outside the file, no hang, no raw h5py errors.

An archive is data from anywhere (a download, a bucket, a colleague's disk), so the reader treats
it as hostile until checked:

* :func:`open_h5` opens a path or a binary file object (local or fsspec) through
  :class:`GuardedFile`, which checks every global heap collection HDF5 loads before HDF5 parses
  it: a heap whose objects do not advance (a zero free-space size, an object larger than its
  collection) makes HDF5 2.0 spin forever inside ``H5HG__cache_heap_deserialize``, holding the
  GIL, so no Python timer could stop it. The check raises instead.
* :func:`check_file` walks the whole file's metadata before any dataset is read, with bounded
  counts and depth, and refuses every way HDF5 can point outside the file (external links,
  external raw storage, virtual datasets, user-defined links), soft links, hard-link cycles,
  unknown filters, variable-length or reference datasets, declared sizes larger than the file
  can hold and datasets whose chunks were never written.
* :func:`h5_errors` (and the :func:`guarded` class decorator built on it) turns every exception
  raised from inside h5py into a one-line :class:`~lodbuilder.errors.CorruptArchiveError` naming
  the file.

Layout-level checks (what a scan must hold, values a slice reads) are in :mod:`.checks`.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import inspect
import os
import weakref
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..errors import ArchiveError, CorruptArchiveError, LodbuilderError, UnsafeArchiveError

MAX_DEPTH = 16  # groups below the root (the layout uses 4)
MAX_OBJECTS = 1_000_000  # groups and datasets in one file
MAX_ATTRS = 1024  # attributes of one object
MAX_ATTR_BYTES = 1 << 28  # declared size of one attribute
MAX_EXPANSION = 1100  # declared dataset bytes per stored byte (deflate's ceiling is 1032)
# HDF5's own filters and h5py's LZF: anything else would make HDF5 look for a plugin library
FILTERS = {
    1: "gzip",
    2: "shuffle",
    3: "fletcher32",
    4: "szip",
    5: "nbit",
    6: "scaleoffset",
    32000: "lzf",
}

_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_GCOL = b"GCOL"
_REBUILD = "rebuild it from the source scan"
_REFUSE = "lodbuilder reads nothing outside an archive; rebuild it with 'lodbuilder build'"


def damaged(path: Any, detail: str) -> CorruptArchiveError:
    """The error for a file HDF5 cannot read or whose structure is wrong."""
    return CorruptArchiveError(f"archive {path} is damaged: {_one_line(detail)}; {_REBUILD}")


def _unsafe(path: Any, detail: str) -> UnsafeArchiveError:
    return UnsafeArchiveError(f"archive {path} is refused: {_one_line(detail)}; {_REFUSE}")


def _one_line(text: str, limit: int = 300) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


# ---------------------------------------------------------------------------------------------
# the file object HDF5 reads through


class GuardedFile:
    """A binary file object for h5py's ``fileobj`` driver that checks global heaps on read.

    HDF5 parses a global heap collection (where variable-length strings such as the archive's
    JSON attributes live; it has no checksum) by walking its objects; an object whose size does
    not move the walk forward loops forever. Every read that returns a whole collection is
    walked here first, the same way, and refused when the walk would not end inside it."""

    def __init__(self, raw: Any, path: Any) -> None:
        self._raw = raw
        self._path = path
        self._len_size = 8  # "size of lengths" from the superblock; h5py always writes 8

    def seek(self, pos: int, whence: int = 0) -> int:
        return self._raw.seek(pos, whence)

    def tell(self) -> int:
        return self._raw.tell()

    def readinto(self, buf: Any) -> int:
        pos = self._raw.tell()
        n = self._raw.readinto(buf)
        if n:
            self._inspect(memoryview(buf)[:n], pos)
        return n

    def read(self, size: int = -1) -> bytes:
        pos = self._raw.tell()
        data = self._raw.read(size)
        if data:
            self._inspect(memoryview(data), pos)
        return data

    def close(self) -> None:
        self._raw.close()

    def _inspect(self, buf: memoryview, pos: int) -> None:
        head = bytes(buf[:8])
        if head == _SIGNATURE and len(buf) >= 16:  # the superblock: learn the size of lengths
            version = buf[8]
            at = 14 if version < 2 else 10
            if len(buf) > at and buf[at] in (2, 4, 8, 16):
                self._len_size = buf[at]
        elif head[:4] == _GCOL:
            check_heap_collection(buf, self._len_size, pos, self._path)


def check_heap_collection(buf: memoryview, len_size: int, pos: int, path: Any) -> None:
    """Walk the objects of the global heap collection in ``buf`` as HDF5 does; raise
    CorruptArchiveError if the walk would not end (or would leave the collection)."""
    hdr = 8 + len_size
    if len(buf) < hdr:
        return
    size = int.from_bytes(buf[8:hdr], "little")
    if size > len(buf):
        return  # a first, partial read: HDF5 reads the whole collection before parsing it
    obj_hdr = 8 + len_size
    p = hdr
    while p < size:
        if p + obj_hdr > size:
            return  # the tail is too short for an object header: free space
        idx = int.from_bytes(buf[p : p + 2], "little")
        osize = int.from_bytes(buf[p + 8 : p + obj_hdr], "little")
        need = obj_hdr + ((osize + 7) & ~7) if idx else osize
        if need == 0 or need > size - p:
            raise damaged(
                path,
                f"its global heap at byte {pos} is malformed (object {idx} at offset {p} has size "
                f"{osize}, the collection {size})",
            )
        p += need


# h5py Files opened here, by id (a File whose root header is damaged cannot even be hashed)
_OPEN: dict[int, weakref.ref[Any]] = {}


@atexit.register
def _close_open_files() -> None:
    # HDF5 closes files left open from its own exit handler, after Python has gone: a file read
    # through a Python file object must be closed while Python still runs.
    for ref in list(_OPEN.values()):
        f = ref()
        if f is not None:
            with contextlib.suppress(Exception):
                f.close()


def _register(f: Any) -> None:
    key = id(f)
    _OPEN[key] = weakref.ref(f, lambda _ref: _OPEN.pop(key, None))


def open_h5(source: str | os.PathLike[str] | Any, path: Any = None) -> Any:
    """Open ``source`` (a path or a binary file object with seek/tell/readinto) read-only through
    :class:`GuardedFile`. ``path`` names it in messages (default: ``source``)."""
    import h5py

    name = source if path is None else path
    if isinstance(source, (str, os.PathLike)):
        raw: Any = open(Path(source), "rb", buffering=0)  # noqa: SIM115 - closed with the File
        owned = True
    else:
        raw, owned = source, False
    guarded = GuardedFile(raw, name)
    try:
        f = h5py.File(guarded, "r")  # h5py's own error if this is no HDF5 file: the caller words it
    except BaseException:
        if owned:
            raw.close()
        raise
    if owned:  # h5py does not close a file object it did not open: close ours with the File
        _wrap_close(f, raw)
    _register(f)
    return f


def _wrap_close(f: Any, raw: Any) -> None:
    close = f.close

    def close_both() -> None:
        try:
            close()
        finally:
            raw.close()

    f.close = close_both


# ---------------------------------------------------------------------------------------------
# h5py exceptions -> CorruptArchiveError


def _h5py_dir() -> str:
    import h5py

    return os.path.dirname(h5py.__file__)


def from_h5py(exc: BaseException) -> bool:
    """True when ``exc`` was raised from inside h5py (its Python or Cython code)."""
    root = _h5py_dir()
    tb = exc.__traceback__
    while tb is not None:
        fn = tb.tb_frame.f_code.co_filename
        if fn.startswith(root) or fn.startswith("h5py/") or fn.startswith("h5py\\"):
            return True
        tb = tb.tb_next
    return False


def _message(exc: BaseException) -> str:
    arg = exc.args[0] if exc.args and isinstance(exc.args[0], str) else str(exc)
    return f"{type(exc).__name__}: {arg}" if not arg or type(exc) is MemoryError else arg


@contextlib.contextmanager
def h5_errors(path: Any, what: str = "it") -> Iterator[None]:
    """Turn an exception from inside h5py into CorruptArchiveError naming ``path``."""
    try:
        yield
    except LodbuilderError:
        raise
    except Exception as exc:
        if not from_h5py(exc):
            raise
        raise damaged(path, f"HDF5 cannot read {what} ({_message(exc)})") from None


def guarded(path_of: Callable[[Any], Any]) -> Callable[[type], type]:
    """Class decorator: every method and property of the class runs under :func:`h5_errors`
    with the path ``path_of(self)``."""

    def wrap(fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def inner(self: Any, *args: Any, **kwargs: Any) -> Any:
            try:
                return fn(self, *args, **kwargs)
            except LodbuilderError:
                raise
            except Exception as exc:
                if not from_h5py(exc):
                    raise
                raise damaged(
                    _path_or(path_of, self), f"HDF5 cannot read it ({_message(exc)})"
                ) from None

        return inner

    return _wrapping(
        wrap, lambda name: not name.startswith("__") or name in ("__init__", "__len__", "__getitem__")
    )


def closed_error(path: Any) -> ArchiveError:
    """What every member of a closed archive or scan view raises (see :func:`open_only`)."""
    return ArchiveError(f"archive {path} is closed; read it inside `with open_archive(...)`")


def open_only(*, allowed: tuple[str, ...] = ()) -> Callable[[type], type]:
    """Class decorator: every public method and property (but those ``allowed``) first calls
    ``self._check_open()``, which raises ArchiveError once the archive is closed (h5py reads a
    closed file's attributes as empty and its datasets as missing, not as an error). Put it below
    :func:`~lodbuilder._validate.strict_methods`, so that an unknown keyword is reported first."""

    def wrap(fn: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(fn)
        def inner(self: Any, *args: Any, **kwargs: Any) -> Any:
            self._check_open()
            return fn(self, *args, **kwargs)

        return inner

    return _wrapping(wrap, lambda name: not name.startswith("_") and name not in allowed)


def _wrapping(
    wrap: Callable[[Callable[..., Any]], Callable[..., Any]], chosen: Callable[[str], bool]
) -> Callable[[type], type]:
    """Class decorator: ``wrap`` every method and property getter whose name is ``chosen``."""

    def deco(cls: type) -> type:
        for name, member in list(vars(cls).items()):
            if not chosen(name):
                continue
            if isinstance(member, property) and member.fget is not None:
                setattr(
                    cls, name, property(wrap(member.fget), member.fset, member.fdel, member.__doc__)
                )
            elif inspect.isfunction(member):
                setattr(cls, name, wrap(member))
        return cls

    return deco


def _path_or(path_of: Callable[[Any], Any], obj: Any) -> Any:
    try:
        return path_of(obj)
    except Exception:  # pragma: no cover - an object broken before its path was set
        return "?"


# ---------------------------------------------------------------------------------------------
# the structural walk


def check_file(f: Any, path: Any) -> int:
    """Check the metadata of the open h5py File ``f`` before any dataset is read; raise
    UnsafeArchiveError for anything pointing outside the file, CorruptArchiveError for anything
    else wrong. Returns the number of groups and datasets."""
    with h5_errors(path, "its metadata"):
        return _Walk(f, path).run()


class _Walk:
    def __init__(self, f: Any, path: Any) -> None:
        self.f, self.path = f, path
        self.filesize = max(1, int(f.id.get_filesize()))
        self.seen: dict[Any, str] = {}

    def run(self) -> int:
        from h5py import h5o

        root = self.f.id
        self.seen[h5o.get_info(root).addr] = "/"
        self._attrs(root, "/")
        stack = [(root, "/", 0)]
        while stack:
            gid, gname, depth = stack.pop()
            for raw in self._names(gid, gname):
                name = _decode(raw)
                full = f"{gname.rstrip('/')}/{name}"
                oid, kind = self._open(gid, raw, full)
                if kind == h5o.TYPE_GROUP:
                    if depth + 1 > MAX_DEPTH:
                        raise damaged(self.path, f"groups nest deeper than {MAX_DEPTH} at {full!r}")
                    stack.append((oid, full, depth + 1))
                else:
                    self._dataset(oid, full)
        return len(self.seen) - 1

    def _names(self, gid: Any, gname: str) -> list[bytes]:
        names: list[bytes] = []

        def collect(name: bytes) -> int | None:
            names.append(name)
            return 1 if len(self.seen) + len(names) > MAX_OBJECTS else None

        gid.links.iterate(collect)
        if len(self.seen) + len(names) > MAX_OBJECTS:
            raise damaged(self.path, f"it holds more than {MAX_OBJECTS} objects (at {gname!r})")
        return names

    def _open(self, gid: Any, raw: bytes, full: str) -> tuple[Any, int]:
        from h5py import h5l, h5o

        if b"/" in raw or raw in (b"", b".", b".."):
            raise damaged(self.path, f"it has a link named {_decode(raw)!r}")
        info = gid.links.get_info(raw)
        if info.type == h5l.TYPE_EXTERNAL:
            target, obj = (_decode(v) for v in gid.links.get_val(raw))
            raise _unsafe(self.path, f"{full!r} is an external link to {obj!r} in file {target!r}")
        if info.type == h5l.TYPE_SOFT:
            target = _decode(gid.links.get_val(raw))
            raise damaged(
                self.path, f"{full!r} is a soft link to {target!r} (archives hold only hard links)"
            )
        if info.type != h5l.TYPE_HARD:
            raise _unsafe(self.path, f"{full!r} is a user-defined link (type {info.type})")
        oid = h5o.open(gid, raw)
        oinfo = h5o.get_info(oid)
        if oinfo.addr in self.seen:
            raise damaged(
                self.path,
                f"{full!r} links again to {self.seen[oinfo.addr]!r} (a hard-link cycle "
                "or a shared object)",
            )
        self.seen[oinfo.addr] = full
        if oinfo.type not in (h5o.TYPE_GROUP, h5o.TYPE_DATASET):
            raise damaged(self.path, f"{full!r} is neither a group nor a dataset")
        self._attrs(oid, full, oinfo.num_attrs)
        return oid, oinfo.type

    def _attrs(self, oid: Any, full: str, n: int | None = None) -> None:
        from h5py import h5a, h5o

        n = h5o.get_info(oid).num_attrs if n is None else n
        if n > MAX_ATTRS:
            raise damaged(self.path, f"{full!r} has {n} attributes (at most {MAX_ATTRS} are read)")
        for i in range(n):
            aid = h5a.open(oid, index=i)
            nbytes = aid.get_space().get_simple_extent_npoints() * aid.get_type().get_size()
            if nbytes > MAX_ATTR_BYTES:
                raise damaged(
                    self.path,
                    f"attribute {_decode(aid.name)!r} of {full!r} declares {nbytes} bytes",
                )

    def _dataset(self, did: Any, full: str) -> None:
        from h5py import h5d, h5t

        dcpl = did.get_create_plist()
        layout = dcpl.get_layout()
        if layout == h5d.VIRTUAL:
            raise _unsafe(
                self.path, f"dataset {full!r} is a virtual dataset (its data lives in other files)"
            )
        if dcpl.get_external_count() > 0:
            target = _decode(dcpl.get_external(0)[0])
            raise _unsafe(
                self.path, f"dataset {full!r} stores its data in external file {target!r}"
            )
        for j in range(dcpl.get_nfilters()):
            code = dcpl.get_filter(j)[0]
            if code not in FILTERS:
                raise damaged(
                    self.path,
                    f"dataset {full!r} uses HDF5 filter {code}, which lodbuilder does not read",
                )
        tid = did.get_type()
        cls = tid.get_class()
        if cls in (h5t.VLEN, h5t.REFERENCE) or (cls == h5t.STRING and tid.is_variable_str()):
            raise damaged(self.path, f"dataset {full!r} holds variable-length or reference values")
        space = did.get_space()
        shape = space.shape or ()
        n = 1
        for d in shape:
            n *= int(d)
        nbytes = n * tid.get_size()
        if nbytes == 0 or layout == h5d.COMPACT:
            return
        if nbytes > MAX_EXPANSION * self.filesize:
            raise damaged(
                self.path,
                f"dataset {full!r} declares shape {tuple(shape)} ({nbytes} bytes), more "
                f"than a {self.filesize}-byte file can hold",
            )
        if layout == h5d.CHUNKED:
            chunk = dcpl.get_chunk()
            expected = 1
            for d, c in zip(shape, chunk, strict=False):
                expected *= -(-int(d) // max(1, int(c)))
            stored = did.get_num_chunks()
            if stored < expected:
                raise damaged(
                    self.path,
                    f"dataset {full!r} declares shape {tuple(shape)} but only {stored} "
                    f"of its {expected} chunks are stored",
                )
        elif did.get_storage_size() < nbytes:
            raise damaged(self.path, f"dataset {full!r} declares {nbytes} bytes but stores fewer")


def _decode(raw: Any) -> str:
    return raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw)
