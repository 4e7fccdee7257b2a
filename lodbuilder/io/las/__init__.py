"""LAS / LAZ / COPC reader and writer, built on laspy (``pip install lodbuilder[las]``).

Reading keeps every point dimension (standard ones and extra bytes) as an attribute, with laspy's
dtypes (bit fields as uint8, extra bytes scaled when the file says so); coordinates are the scaled
doubles. ``metadata`` keeps what is needed to write the same format back: LAS version, point format
id, scales, offsets, the CRS (WKT string and the raw LASF_Projection VLRs), the extra-byte
definitions, system identifier and generating software; ``crs_wkt`` holds the CRS as WKT (the WKT
VLR as written, else the GeoTIFF keys through pyproj).

Writing goes through :func:`las_layout`, the one mapping from points + attributes + metadata to
what laspy writes (the COPC exporter uses it too); see its docstring for every rule. In short:
nothing is dropped; a value that does not fit its standard LAS field exactly is written to an
extra-bytes dimension in its own dtype (and the standard field gets a scaled copy for viewers);
8-bit colours are scaled x257; the coordinate scale comes from the source LAS or from the point
spacing; every change is logged as a warning and listed in :attr:`LasLayout.notes`.

The module is split by concern: :mod:`.read` (checks and metadata), :mod:`.layout` (what is written
and how), :mod:`.write`; :mod:`.common` holds what they share.
"""

from __future__ import annotations

from .common import EXACT_PREFIX
from .layout import ExtraDim, LasLayout, choose_quantization, exact_decimal_quantization, las_layout
from .read import las_metadata, read
from .write import check_output, write

__all__ = ["EXACT_PREFIX", "ExtraDim", "LasLayout", "check_output", "choose_quantization",
           "exact_decimal_quantization", "las_layout", "las_metadata", "read", "write"]
