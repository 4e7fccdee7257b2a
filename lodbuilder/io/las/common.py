"""What every part of the LAS/LAZ module shares: laspy (an optional dependency), its LAZ backend
and its logging, and the marker of exact-value extra bytes."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ...errors import MissingDependencyError

log = logging.getLogger(__name__)


#: description prefix of an extra-bytes dimension that holds the exact values of a standard field
EXACT_PREFIX = "lodbuilder exact "


def laspy_module(path: Path | str) -> Any:
    from ..._optional import require

    return require("laspy", f"{path}: LAS/LAZ")


def check_laz_backend(laspy: Any, path: Path) -> None:
    if path.suffix.lower() == ".laz" and not laspy.LazBackend.detect_available():
        from ..._optional import missing_message

        raise MissingDependencyError(missing_message("lazrs", f"{path}: LAZ"))


@contextlib.contextmanager
def quiet_laspy() -> Iterator[None]:
    """laspy logs an ERROR line before raising on a damaged file; the raised error is reported
    as one line by the caller, so the log line would only repeat it."""
    lg = logging.getLogger("laspy")
    old = lg.level
    lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        lg.setLevel(old)
