"""Reading archives over HTTP(S) and S3 in a few requests.

h5py has no remote driver, so an archive at a URL is opened through a Python file object
(:class:`RemoteFile`) whose bytes come from fsspec ranged reads (``fs.cat_file(path, start,
end)``; s3fs for ``s3://``). There is no read-ahead: the file object keeps a cache of byte spans
that only grows by what is asked for:

* the first request reads the first ``FIRST_BLOCK`` bytes (HDF5's superblock and, in an archive
  written with paged aggregation, every metadata block of a scan: object headers, attributes,
  chunk indexes), or the whole file when it is small;
* a read outside the cache fetches the blocks around it (one request per contiguous run of
  missing blocks; blocks are the file's page once it is known);
* before a level is read, the reader asks for the byte ranges of every chunk the level needs
  (:func:`chunk_ranges`) and :meth:`RemoteFile.prefetch` fetches them with one request per
  contiguous span. Archives are written in row groups, so a level is one span.

Opening an archive and reading a 10k-point level of one scan is then one HEAD (the file size)
and two or three GETs. Nothing here is imported unless a URL is opened.

Every read is bounded: a server that does not answer (connect, or send the next bytes) within
``timeout`` seconds (default :data:`DEFAULT_TIMEOUT`) ends the read with one line; an HTTP
redirect to another host is refused unless ``follow_redirects``. Both are storage options of
lodbuilder's own (``open_archive(url, storage_options={"timeout": 5})``), and the command line's
``--timeout`` / ``--follow-redirects`` set them for the whole command (:func:`settings`). A URL's
query (a signed URL) is kept on every part of a grown archive (:func:`sibling_url`).
"""

from __future__ import annotations

import bisect
import contextlib
import io
import logging
from collections.abc import Iterator
from typing import Any

from ..errors import ArchiveError, InputError, MissingDependencyError, ScanFileError

log = logging.getLogger(__name__)

SCHEMES = ("http", "https", "s3")
#: bytes of the first request (superblock and metadata of a paged archive)
FIRST_BLOCK = 1 << 16
#: a file at most this large is read whole by the first request
SMALL_FILE = 1 << 18
#: cache block before the file's page size is known
BLOCK = 1 << 16
#: seconds a server may take to connect or to send the next bytes of an answer
DEFAULT_TIMEOUT = 30.0

_SETTINGS: dict[str, Any] = {"timeout": DEFAULT_TIMEOUT, "follow_redirects": False}


@contextlib.contextmanager
def settings(*, timeout: float | None = None, follow_redirects: bool | None = None) -> Iterator[None]:
    """The defaults of ``timeout`` and ``follow_redirects`` for every URL opened inside the block
    (the command line's --timeout and --follow-redirects); storage options still win."""
    before = dict(_SETTINGS)
    if timeout is not None:
        _SETTINGS["timeout"] = check_timeout(timeout)
    if follow_redirects is not None:
        _SETTINGS["follow_redirects"] = bool(follow_redirects)
    try:
        yield
    finally:
        _SETTINGS.clear()
        _SETTINGS.update(before)


def check_timeout(value: Any) -> float:
    """``value`` as a number of seconds above 0, else InputError."""
    try:
        t = float(value)
    except (TypeError, ValueError):
        t = float("nan")
    if not t > 0 or t == float("inf"):
        raise InputError(f"timeout must be a number of seconds above 0, got {value!r}")
    return t


def sibling_url(url: str, tail: str) -> str:
    """``url`` with ``tail`` appended to its path, its query kept: the part
    ``g.h5.scans/p.h5?sig=...`` of the archive ``g.h5?sig=...`` (a fragment is dropped)."""
    from urllib.parse import urlsplit, urlunsplit

    parts = urlsplit(url)
    return urlunsplit((parts.scheme, parts.netloc, parts.path + tail, parts.query, ""))


class RedirectRefused(Exception):
    """An HTTP redirect to another host, refused (``follow_redirects`` is off)."""

    def __init__(self, target: str) -> None:
        super().__init__(target)
        self.target = target


def _same_host_only() -> Any:
    """An aiohttp trace config that refuses a redirect to another scheme, host or port."""
    import aiohttp
    from yarl import URL

    async def on_redirect(session: Any, ctx: Any, params: Any) -> None:
        location = params.response.headers.get("Location", "")
        target = params.url.join(URL(location))
        if (target.scheme, target.host, target.port) != (
            params.url.scheme, params.url.host, params.url.port
        ):
            raise RedirectRefused(str(target))

    trace = aiohttp.TraceConfig()
    trace.on_request_redirect.append(on_redirect)
    return trace


def _bounded(scheme: str, options: dict[str, Any]) -> tuple[dict[str, Any], float]:
    """fsspec options with lodbuilder's ``timeout`` and ``follow_redirects`` applied, and the
    timeout."""
    opts = dict(options)
    timeout = check_timeout(opts.pop("timeout", _SETTINGS["timeout"]))
    follow = bool(opts.pop("follow_redirects", _SETTINGS["follow_redirects"]))
    if scheme in ("http", "https"):
        import aiohttp

        opts.setdefault("encoded", True)  # a URL as given: a signature's %2F stays %2F
        client = dict(opts.get("client_kwargs") or {})
        client.setdefault(
            "timeout", aiohttp.ClientTimeout(total=None, sock_connect=timeout, sock_read=timeout)
        )
        if not follow:
            client["trace_configs"] = [*client.get("trace_configs", []), _same_host_only()]
        opts["client_kwargs"] = client
    elif scheme == "s3":
        config = dict(opts.get("config_kwargs") or {})
        config.setdefault("connect_timeout", timeout)
        config.setdefault("read_timeout", timeout)
        opts["config_kwargs"] = config
    return opts, timeout


def normalise_url(url: str) -> str:
    """``url`` with its scheme checked; ``https:/host/x`` (a URL passed through ``pathlib``)
    gets its second slash back."""
    scheme, sep, rest = url.partition(":")
    if scheme.lower() not in SCHEMES:
        raise InputError(
            f"{url}: unsupported URL scheme {scheme!r}; archives can be read from http://, "
            "https:// and s3:// URLs or local files"
        )
    rest = rest.lstrip("/")
    if not rest:
        raise InputError(f"{url}: the URL names no file")
    return f"{scheme.lower()}://{rest}"


def filesystem(url: str, storage_options: dict[str, Any] | None = None) -> tuple[Any, str]:
    """``(fsspec filesystem, path)`` for ``url``; a one-line error when the extra is missing.
    ``storage_options`` go to fsspec, but for lodbuilder's ``timeout`` and ``follow_redirects``
    (module docstring)."""
    scheme = url.split(":", 1)[0]
    try:
        import fsspec.core
    except ImportError:
        raise MissingDependencyError(
            "reading archives over HTTP/S3 needs fsspec: pip install 'lodbuilder[remote]'"
        ) from None
    try:
        opts, _ = _bounded(scheme, storage_options or {})
        return fsspec.core.url_to_fs(url, **opts)
    except ImportError:
        need, extra = ("s3fs", "s3") if scheme == "s3" else ("aiohttp", "remote")
        raise MissingDependencyError(
            f"reading {scheme}:// archives needs {need}: pip install 'lodbuilder[{extra}]'"
        ) from None
    except (TypeError, ValueError) as exc:
        raise InputError(f"{url}: bad storage options ({exc})") from None


def _remote_error(exc: BaseException, url: str, timeout: float | None = None) -> BaseException:
    """A one-line error for a failed request."""
    cause: BaseException | None = exc
    while cause is not None:  # (fsspec reports any failure of its size lookup as "not found")
        if isinstance(cause, RedirectRefused):
            return ArchiveError(
                f"archive {url}: the server redirects to another host ({cause.target}); pass "
                "--follow-redirects to follow it, or use that URL"
            )
        if isinstance(cause, TimeoutError):
            return ArchiveError(
                f"archive {url}: the server did not answer within "
                f"{timeout or _SETTINGS['timeout']:g} s; "
                "try again later or give more time with --timeout SECONDS"
            )
        cause = cause.__cause__ or cause.__context__
    if isinstance(exc, FileNotFoundError):
        return ScanFileError(f"archive {url} does not exist (the server has no such file); check the URL")
    if isinstance(exc, PermissionError):
        return ArchiveError(f"archive {url}: access denied; check the URL or your credentials")
    text = " ".join(str(exc).split()) or type(exc).__name__
    return ArchiveError(f"archive {url} cannot be read ({text[:200]})")


class RemoteFile(io.RawIOBase):
    """A read-only, seekable file over ranged requests, with a cache of fetched spans.

    ``requests`` and ``bytes_fetched`` count what went over the network (GETs; the size lookup,
    when the size is not given, is one HEAD, counted in ``heads``)."""

    def __init__(
        self, fs: Any, path: str, url: str, size: int | None = None, timeout: float | None = None
    ) -> None:
        super().__init__()
        self.fs, self.path, self.url = fs, path, url
        self.timeout = timeout
        self.requests = 0
        self.heads = 0
        self.bytes_fetched = 0
        self.block = BLOCK
        self._pos = 0
        self._starts: list[int] = []  # sorted starts of the cached spans
        self._spans: dict[int, bytes] = {}
        head = b""
        if size is None:
            # the size (one HEAD) and the first block (one GET) at the same time: one round trip
            info, head = self._size_and_head()
            self.heads += 1
            size = info.get("size")
            if size is None:
                raise ArchiveError(
                    f"archive {url}: the server does not report the file size; it cannot be read "
                    "in ranges"
                )
        self.size = int(size)
        if head:
            self.requests += 1
            self.bytes_fetched += len(head)
            if len(head) == self.size or len(head) == min(self.size, FIRST_BLOCK):
                self._insert(0, bytes(head[: self.size]))
                if len(head) > FIRST_BLOCK:
                    self._warn_whole()
            else:
                raise ArchiveError(
                    f"archive {url}: asked for its first {FIRST_BLOCK} bytes, got {len(head)} of "
                    f"{self.size}; the file changed while it was read"
                )
            if self.size <= SMALL_FILE:
                self._fetch(self._missing(0, self.size))
        else:
            self._fetch([(0, min(self.size, FIRST_BLOCK if self.size > SMALL_FILE else self.size))])

    def _size_and_head(self) -> tuple[dict[str, Any], bytes]:
        """``(fs.info(path), the first FIRST_BLOCK bytes)``, concurrently on an async filesystem."""
        fs, path = self.fs, self.path
        try:
            if getattr(fs, "async_impl", False):
                import asyncio

                from fsspec.asyn import sync

                async def both() -> tuple[Any, Any]:
                    info, data = await asyncio.gather(
                        fs._info(path), fs._cat_file(path, start=0, end=FIRST_BLOCK)
                    )
                    return info, data

                return sync(fs.loop, both)
            return fs.info(path), fs.cat_file(path, start=0, end=FIRST_BLOCK)
        except Exception as exc:  # noqa: BLE001 - any backend error becomes one line
            raise _remote_error(exc, self.url, self.timeout) from None

    # -- io.RawIOBase ----------------------------------------------------------------------------
    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        if whence == io.SEEK_SET:
            self._pos = offset
        elif whence == io.SEEK_CUR:
            self._pos += offset
        else:
            self._pos = self.size + offset
        return self._pos

    def readinto(self, buffer: Any) -> int:
        view = memoryview(buffer).cast("B")
        lo = self._pos
        hi = min(self.size, lo + len(view))
        if hi <= lo:
            return 0
        self._ensure(lo, hi)
        n = self._copy(lo, hi, view)
        self._pos = lo + n
        return n

    def looks_like_hdf5(self) -> bool:
        head = self._spans.get(0, b"")[:8]
        return head == b"\x89HDF\r\n\x1a\n"

    # -- the cache -------------------------------------------------------------------------------
    def set_block(self, nbytes: int) -> None:
        """Fetch misses in blocks of ``nbytes`` (the file's page size, once known)."""
        if nbytes > 0:
            self.block = int(nbytes)

    def prefetch(self, ranges: list[tuple[int, int]]) -> None:
        """Fetch the byte ranges ``(offset, length)`` not cached yet: ranges closer than a block
        are merged, and every contiguous span is one request."""
        spans: list[list[int]] = []
        for off, length in sorted(r for r in ranges if r[1] > 0):
            end = min(self.size, off + length)
            if spans and off - spans[-1][1] <= self.block:
                spans[-1][1] = max(spans[-1][1], end)
            else:
                spans.append([off, end])
        missing = []
        for lo, hi in spans:
            missing += self._missing(lo, hi)
        self._fetch(missing)

    def _missing(self, lo: int, hi: int) -> list[tuple[int, int]]:
        """Sub-ranges of [lo, hi) not in the cache."""
        out = []
        i = bisect.bisect_right(self._starts, lo) - 1
        pos = lo
        if i >= 0:
            s = self._starts[i]
            pos = max(pos, s + len(self._spans[s]))
        j = i + 1
        while pos < hi:
            nxt = self._starts[j] if j < len(self._starts) else self.size
            if nxt > pos:
                out.append((pos, min(hi, nxt)))
            if j >= len(self._starts):
                break
            pos = max(pos, nxt + len(self._spans[nxt]))
            j += 1
        return [(a, b) for a, b in out if b > a]

    def _ensure(self, lo: int, hi: int) -> None:
        gaps = self._missing(lo, hi)
        if not gaps:
            return
        b = self.block
        want = []
        for a, z in gaps:  # whole blocks around each miss, not overlapping what is cached
            want += self._missing(max(0, a - a % b), min(self.size, -(-z // b) * b))
        merged: list[tuple[int, int]] = []
        for a, z in sorted(want):
            if merged and a <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(z, merged[-1][1]))
            else:
                merged.append((a, z))
        self._fetch(merged)

    def _fetch(self, ranges: list[tuple[int, int]]) -> None:
        ranges = [(a, z) for a, z in ranges if z > a]
        if not ranges:
            return
        try:
            if len(ranges) == 1:
                datas = [self.fs.cat_file(self.path, start=ranges[0][0], end=ranges[0][1])]
            else:
                datas = self.fs.cat_ranges(
                    [self.path] * len(ranges), [a for a, _ in ranges], [z for _, z in ranges],
                    on_error="raise",
                )
        except Exception as exc:  # noqa: BLE001 - any backend error becomes one line
            raise _remote_error(exc, self.url, self.timeout) from None
        self.requests += len(ranges)
        for (a, z), data in zip(ranges, datas, strict=True):
            self.bytes_fetched += len(data)
            if len(data) == self.size and z - a != self.size:
                # the server ignored the Range header and sent the whole file: keep all of it
                self._warn_whole()
                self._starts, self._spans = [0], {0: bytes(data)}
                return
            if len(data) != z - a:
                raise ArchiveError(
                    f"archive {self.url}: asked for bytes {a}-{z - 1}, got {len(data)}; the file "
                    "changed or is shorter than expected"
                )
            self._insert(a, bytes(data))

    def _warn_whole(self) -> None:
        log.warning(
            "%s: the server ignores range requests, so the whole file was read (%.1f MB); serve "
            "it with range support (e.g. RangeHTTPServer, nginx, S3) to read levels in a few "
            "small requests", self.url, self.size / 1e6,
        )

    def _insert(self, lo: int, data: bytes) -> None:
        bisect.insort(self._starts, lo)
        self._spans[lo] = data

    def _copy(self, lo: int, hi: int, view: memoryview) -> int:
        i = bisect.bisect_right(self._starts, lo) - 1
        pos = lo
        while pos < hi and 0 <= i < len(self._starts):
            s = self._starts[i]
            data = self._spans[s]
            if s > pos:
                break
            end = min(hi, s + len(data))
            if end > pos:
                view[pos - lo : end - lo] = data[pos - s : end - s]
                pos = end
            i += 1
        return pos - lo

    def cached_bytes(self) -> int:
        return sum(len(d) for d in self._spans.values())


def open_remote(
    url: str, *, size: int | None = None, storage_options: dict[str, Any] | None = None
) -> RemoteFile:
    """A :class:`RemoteFile` for ``url`` (``size`` known saves the HEAD request)."""
    fs, path = filesystem(url, storage_options)
    timeout = check_timeout((storage_options or {}).get("timeout", _SETTINGS["timeout"]))
    return RemoteFile(fs, path, url, size, timeout)


def chunk_ranges(ds: Any, lo: int, hi: int) -> list[tuple[int, int]]:
    """``(offset, length)`` in the file of the chunks of ``ds`` that hold rows [lo, hi)."""
    if hi <= lo or ds.shape[0] == 0:
        return []
    chunks = ds.chunks
    if chunks is None:
        off = ds.id.get_offset()
        return [] if off is None else [(int(off), int(ds.id.get_storage_size()))]
    rows = chunks[0]
    out = []
    tail = (0,) * (len(ds.shape) - 1)
    for start in range(lo - lo % rows, min(hi, ds.shape[0]), rows):
        info = ds.id.get_chunk_info_by_coord((start, *tail))
        if info.byte_offset is not None and info.size:
            out.append((int(info.byte_offset), int(info.size)))
    return out


class Prefetcher:
    """What a read of a scan's per-point dataset fetches first, for one scan of a remote archive.

    A level (a prefix of at most 1/8 of the scan, or two row groups) gets rows [0, stop) of every
    per-point dataset of the scan: they are stored in row groups, so that is one request per
    contiguous span (one for a level), and the level's other reads are then cached. A longer
    read (``info``'s radii, a whole scan for ``view``) gets the chunks of that one dataset,
    fetched concurrently. Small datasets (orderings, radius_index, ...) go through the cache."""

    def __init__(self, io: RemoteFile, group: Any, n_points: int) -> None:
        self.io, self.group, self.n = io, group, n_points
        self.rows = 0  # rows [0, rows) of every per-point dataset are cached
        self.done: dict[str, tuple[int, int]] = {}
        self._datasets: list[Any] | None = None

    def _per_point(self) -> list[Any]:
        if self._datasets is None:
            from . import layout as L

            g, n = self.group, self.n
            keys = [L.D_POINTS, L.D_SOURCE_INDEX, L.D_RADIUS, L.D_PARENT]
            keys += [f"{grp}/{k}" for grp in (L.G_ATTRIBUTES, L.G_IMPORTANCE) if grp in g for k in g[grp]]
            self._datasets = [g[k] for k in keys if k in g and g[k].shape[:1] == (n,)]
        return self._datasets

    def before(self, ds: Any, sel: Any) -> None:
        """Fetch what reading ``ds[sel]`` needs (and, for a level, its sibling datasets)."""
        from . import layout as L

        n, prefix = self.n, f"{self.group.name}/"
        name = ds.name or ""
        if ds.shape[:1] != (n,) or not name.startswith(prefix) or not isinstance(sel, slice):
            return
        if name.startswith(prefix + L.G_ORDERINGS + "/"):
            return
        stop = n if sel.stop is None else min(n, int(sel.stop))
        rows = ds.chunks[0] if ds.chunks else n
        if stop <= max(n // 8, 2 * rows):
            if stop <= self.rows:
                return
            ranges = [r for d in self._per_point() for r in chunk_ranges(d, self.rows, stop)]
            self.rows = stop
        else:
            start = 0 if sel.start is None else max(0, int(sel.start))
            lo, hi = self.done.get(name, (0, 0))
            if lo <= start and stop <= hi:
                return
            ranges = chunk_ranges(ds, start, stop)
            self.done[name] = (start, stop)
        self.io.prefetch(ranges)
