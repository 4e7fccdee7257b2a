"""The JSON Schema of the archive, built from :mod:`lodbuilder.archive.layout`.

It validates the JSON description of an HDF5 archive (:func:`layout.describe`). The copy in
``schemas/archive.schema.json`` is generated from here (``python -m lodbuilder.archive.schema``)
and a test keeps the two identical.
"""

from __future__ import annotations

import json
import sys
from typing import Any

from . import layout as L

SCHEMA_ID = "https://lodbuilder.invalid/schemas/archive.schema.json"

INT_DTYPES = ["int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64"]
FLOAT_DTYPES = ["float16", "float32", "float64"]


def _ds(
    dtype: Any,
    ndim: int | None = None,
    cols: int | None = None,
    attrs: dict | None = None,
    required_attrs: list[str] | None = None,
    description: str = "",
    small: bool = False,
) -> dict[str, Any]:
    """A dataset: per-point ones are chunked with a fletcher32 checksum; ``small`` ones may
    instead be compact (kept in their object header, which carries its own checksum)."""
    dt = {"enum": dtype} if isinstance(dtype, list) else {"const": dtype}
    shape: dict[str, Any] = {"type": "array", "items": {"type": "integer", "minimum": 0}}
    if ndim is not None:
        shape.update(minItems=ndim, maxItems=ndim)
        if cols is not None:
            shape["prefixItems"] = [{"type": "integer", "minimum": 0}, {"const": cols}]
    else:
        shape.update(minItems=1, maxItems=2)
    attr_schema: dict[str, Any] = {"type": "object", "properties": attrs or {}}
    if required_attrs:
        attr_schema["required"] = required_attrs
    chunked = {"type": "array", "items": {"type": "integer", "minimum": 1}}
    out: dict[str, Any] = {
        "description": description,
        "type": "object",
        "required": ["kind", "dtype", "shape", "chunks", "fletcher32", "attrs"],
        "properties": {
            "kind": {"const": "dataset"},
            "dtype": dt,
            "shape": shape,
            "layout": {"const": "chunked"},
            "chunks": chunked,
            "compression": {"enum": [None, "gzip", "lzf"]},
            "fletcher32": {"const": True},
            "attrs": attr_schema,
        },
    }
    if small:
        props = out["properties"]
        props["layout"] = {"enum": ["chunked", "compact"]}
        props["chunks"] = {"type": ["array", "null"], "items": chunked["items"]}
        props["fletcher32"] = {"type": "boolean"}
        out["anyOf"] = [
            {"properties": {"layout": {"const": "compact"}}, "required": ["layout"]},
            {"properties": {"fletcher32": {"const": True}, "chunks": {"type": "array"}}},
        ]
    return out


def _group(
    members: dict[str, Any],
    required: list[str],
    attrs: dict[str, Any] | None = None,
    required_attrs: list[str] | None = None,
    additional: Any = False,
    description: str = "",
) -> dict[str, Any]:
    attr_schema: dict[str, Any] = {"type": "object", "properties": attrs or {}}
    if required_attrs:
        attr_schema["required"] = required_attrs
    return {
        "description": description,
        "type": "object",
        "required": ["kind", "attrs", "members"],
        "properties": {
            "kind": {"const": "group"},
            "attrs": attr_schema,
            "members": {
                "type": "object",
                "properties": members,
                "required": required,
                "additionalProperties": additional,
            },
        },
    }


JSON_TEXT = {"type": "string", "contentMediaType": "application/json"}
VEC3 = {"type": "array", "items": {"type": ["number", "string"]}, "minItems": 3, "maxItems": 3}
UTC = {"type": "string", "pattern": r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}"}


def _ordering_schema() -> dict[str, Any]:
    """An extra ordering's group."""
    return _group(
        {
            L.D_ORDER: _ds("int64", 1, description="positions into the stored points", small=True),
            L.D_RADIUS: _ds(
                "float64", 1, description="insertion radii of this ordering", small=True
            ),
            L.D_PARENT: _ds(
                "int64", 1, description="parent position in this ordering, -1 for roots",
                small=True,
            ),
        },
        [L.D_ORDER, L.D_RADIUS, L.D_PARENT],
        attrs={L.M_PARAMETERS: JSON_TEXT, L.S_N_ORDERED: {"type": "integer", "minimum": 0}},
        required_attrs=[L.M_PARAMETERS],
        description="an extra ordering (feature-sensitive, density floor, ...)",
    )


#: a scan's attributes, all required
_SCAN_ATTRS: dict[str, Any] = {
    L.S_N_POINTS: {"type": "integer", "minimum": 1},
    L.S_N_ORDERED: {"type": "integer", "minimum": 1},
    L.S_ENCODING: {"enum": list(L.ENCODINGS)},
    L.S_BOUNDS_MIN: VEC3,
    L.S_BOUNDS_MAX: VEC3,
    L.S_RADIUS_STEP: {"type": "integer", "minimum": 1},
    L.S_BUILD: JSON_TEXT,
    L.S_PROVENANCE: JSON_TEXT,
    L.S_FORMAT_METADATA: JSON_TEXT,
}
#: optional scan attributes (older archives lack them)
_SCAN_OPTIONAL_ATTRS: dict[str, Any] = {L.S_STOP_RADIUS: {"type": ["number", "string"]}}


def _scan_schema() -> dict[str, Any]:
    """One scan's group."""
    attribute_ds = _ds(
        INT_DTYPES + FLOAT_DTYPES + ["bool"], description="an input attribute, stored order"
    )
    importance_ds = _ds(
        "float32",
        1,
        attrs={L.M_PARAMETERS: JSON_TEXT},
        required_attrs=[L.M_PARAMETERS],
        description="an importance map, stored order",
    )
    ordering = _ordering_schema()
    return _group(
        {
            L.D_POINTS: _ds(
                list(L.ENCODINGS),
                2,
                3,
                attrs={L.P_OFFSET: VEC3, L.P_SCALE: VEC3},
                description="coordinates in farthest-point order",
            ),
            L.D_SOURCE_INDEX: _ds("int64", 1, description="input index of each stored point"),
            L.D_RADIUS: _ds(
                "float64", 1, description="insertion radius, non-increasing, inf for seeds"
            ),
            L.D_PARENT: _ds("int64", 1, description="stored position of the parent, -1 for roots"),
            L.D_RADIUS_INDEX: _ds(
                "float64", 1, description="radius[::radius_index_step]", small=True
            ),
            L.D_SEEDS: _ds("int64", 1, description="input indices of the seeds", small=True),
            L.G_ATTRIBUTES: _group({}, [], additional=attribute_ds, description="input attributes"),
            L.G_IMPORTANCE: _group({}, [], additional=importance_ds, description="importance maps"),
            L.G_ORDERINGS: _group({}, [], additional=ordering, description="extra orderings"),
        },
        [
            L.D_POINTS,
            L.D_SOURCE_INDEX,
            L.D_RADIUS,
            L.D_PARENT,
            L.D_RADIUS_INDEX,
            L.D_SEEDS,
            L.G_ATTRIBUTES,
        ],
        attrs={**_SCAN_ATTRS, **_SCAN_OPTIONAL_ATTRS},
        required_attrs=list(_SCAN_ATTRS),
        description="one scan",
    )


def _index_schema() -> dict[str, Any]:
    """The index group: one row per scan."""
    index = _group(
        {
            L.I_NAME: _ds(
                {"pattern": r"^S\d+$"}, 1, description="scan names, UTF-8, fixed length",
                small=True,
            ),
            L.I_N_POINTS: _ds("int64", 1, small=True),
            L.I_BOUNDS_MIN: _ds("float64", 2, 3, small=True),
            L.I_BOUNDS_MAX: _ds("float64", 2, 3, small=True),
            L.I_PART: _ds(
                {"pattern": r"^S\d+$"},
                1,
                description="part file in NAME.h5.scans/ holding the scan, empty when it is in "
                "this file; matches " + L.PART_NAME.pattern,
                small=True,
            ),
            L.I_PART_BYTES: _ds(
                "int64", 1, description="size of the part file, 0 when none", small=True
            ),
        },
        [L.I_NAME, L.I_N_POINTS, L.I_BOUNDS_MIN, L.I_BOUNDS_MAX],
        attrs={L.A_N_SCANS: {"type": "integer", "minimum": 0}},
        required_attrs=[L.A_N_SCANS],
        additional=True,  # the collections issue may add columns
        description="one row per scan, in name order (schema 1 archives have no part columns)",
    )
    # the dtype of the name column is a pattern, not a const
    for col in (L.I_NAME, L.I_PART):
        index["properties"]["members"]["properties"][col]["properties"]["dtype"] = {
            "type": "string",
            "pattern": r"^S\d+$",
        }
    return index


def build_schema() -> dict[str, Any]:
    """The archive's JSON Schema, derived from :mod:`lodbuilder.archive.layout`."""
    scan, index = _scan_schema(), _index_schema()
    root = _group(
        {
            L.G_SCANS: _group({}, [], additional=scan, description="scans by name"),
            L.G_INDEX: index,
        },
        [L.G_SCANS, L.G_INDEX],
        attrs={
            L.A_FORMAT: {"const": L.FORMAT},
            L.A_SCHEMA_VERSION: {"type": "integer", "minimum": 1, "maximum": L.SCHEMA_VERSION},
            L.A_VERSION: {"type": "string"},
            L.A_CREATED: UTC,
            L.A_MODIFIED: UTC,
        },
        required_attrs=[L.A_FORMAT, L.A_SCHEMA_VERSION, L.A_VERSION],
        description="an lodbuilder archive",
    )
    root["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    root["$id"] = SCHEMA_ID
    root["title"] = f"lodbuilder archive, schema version {L.SCHEMA_VERSION}"
    return root


def schema_text() -> str:
    return json.dumps(build_schema(), indent=2, sort_keys=True) + "\n"


def validate_description(description: dict[str, Any]) -> list[str]:
    """Schema faults of an archive description, as one-line messages (empty when valid).

    Needs ``jsonschema``; raises MissingDependencyError without it."""
    try:
        import jsonschema
    except ImportError:  # pragma: no cover - jsonschema is a dev dependency
        from ..errors import MissingDependencyError

        raise MissingDependencyError(
            "schema validation needs the jsonschema package: pip install jsonschema"
        ) from None
    validator = jsonschema.Draft202012Validator(build_schema())
    faults = []
    for err in sorted(validator.iter_errors(description), key=lambda e: list(e.path)):
        where = "/".join(str(p) for p in err.path if p not in ("members", "properties"))
        faults.append(f"schema: at /{where}: {err.message}")
    return faults


if __name__ == "__main__":  # pragma: no cover
    sys.stdout.write(schema_text())
