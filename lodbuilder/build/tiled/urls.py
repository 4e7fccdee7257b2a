"""Where a tiled build's work files may live: a directory or an fsspec URL (see :mod:`.store`),
checked before any work, and the file system a URL names (its package a one-line error when it
is not installed)."""

from __future__ import annotations

import os
from typing import Any, cast

from ...errors import InputError

#: URL schemes that name a local directory (a LocalStore), not an object store
LOCAL_SCHEMES = ("", "file", "local")


def url_to_fs(url: str, **storage_options: Any) -> tuple[Any, str]:
    """``(fsspec file system, path)`` for a work directory's URL; a one-line error naming the
    extra to install when fsspec or the scheme's package is missing."""
    scheme = url.split("://", 1)[0].lower()
    try:
        import fsspec.core
    except ImportError:
        raise _missing("fsspec", "remote") from None
    try:
        return cast(tuple[Any, str], fsspec.core.url_to_fs(url, **storage_options))
    except ImportError:
        need, extra = ("s3fs", "s3") if scheme in ("s3", "s3a") else (scheme, "remote")
        raise _missing(need, extra) from None


def _missing(package: str, extra: str) -> Exception:
    from ...errors import MissingDependencyError

    return MissingDependencyError(f"work files on an object store need {package}, which is not installed; install "
                                  f"it with: pip install 'lodbuilder[{extra}]'")


def is_remote(url: str | os.PathLike[str]) -> bool:
    """True when ``url`` names an object store (a URL whose scheme is not file://)."""
    text = os.fspath(url)
    return "://" in text and text.split("://", 1)[0].lower() not in LOCAL_SCHEMES


def check_work_url(url: Any) -> str | None:
    """``url`` (where tiled builds keep their work files; None: beside the archive) checked: a
    non-empty path (returned absolute: workers may run elsewhere) or URL whose scheme fsspec knows."""
    if url is None:
        return None
    if not isinstance(url, (str, os.PathLike)) or not os.fspath(url).strip():
        raise InputError(f"work_dir must be a directory or an fsspec URL like s3://BUCKET/PREFIX, got {url!r}")
    text = os.fspath(url)
    if is_remote(text):
        scheme = text.split("://", 1)[0].lower()
        try:
            from fsspec.registry import known_implementations
        except ImportError:
            raise _missing("fsspec", "remote") from None
        from fsspec.registry import registry

        if scheme not in known_implementations and scheme not in registry:
            raise InputError(f"work_dir {text!r}: fsspec knows no file system {scheme!r}; give a directory or a URL "
                             "like s3://BUCKET/PREFIX")
        return text
    return os.path.abspath(text[len("file://"):] if text.startswith("file://") else text)
