"""The JSON Schema in schemas/ is current and real archives validate against it."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import h5py
import jsonschema
import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive import layout as L
from lodbuilder.archive.schema import build_schema, schema_text, validate_description
from lodbuilder.archive.writer import ScanRecord, update_archive
from lodbuilder.io import read_scan

SCHEMA_FILE = Path(__file__).resolve().parents[1] / "schemas" / "archive.schema.json"


def test_schema_file_is_generated_from_layout():
    assert SCHEMA_FILE.read_text() == schema_text(), (
        "schemas/archive.schema.json is stale: python -m lodbuilder.archive.schema > schemas/archive.schema.json"
    )
    jsonschema.Draft202012Validator.check_schema(json.loads(SCHEMA_FILE.read_text()))


@pytest.fixture(scope="module")
def real_archive(tmp_path_factory, shared_data):
    """An archive of a real PLY scan (bun_zipper_res3, 1889 points, with confidence/intensity)."""
    scan = read_scan(shared_data / "bun_zipper_res3.ply")
    path = tmp_path_factory.mktemp("schema") / "bunny.h5"
    ordg = lodbuilder.fastfps(scan.points)
    update_archive(path, [ScanRecord(scan, ordg)])
    lodbuilder.archive.writer.add_importance(path, scan.name, "z", scan.points[:, 2], {"axis": 2})
    return path


def describe(path):
    with h5py.File(path, "r") as f:
        return L.describe(f)


def test_real_archive_validates(real_archive):
    doc = describe(real_archive)
    jsonschema.validate(doc, json.loads(SCHEMA_FILE.read_text()))
    assert validate_description(doc) == []
    scan = doc["members"]["scans"]["members"]["bun_zipper_res3"]
    assert set(scan["members"]["attributes"]["members"]) == {"confidence", "intensity"}
    assert scan["members"]["points"]["dtype"] == "float32"


@pytest.mark.parametrize(
    "mutate,message",
    [
        (lambda d: d["attrs"].update(format="other"), "'lodbuilder' was expected"),
        (lambda d: d["attrs"].update(schema_version=99), "99 is greater than the maximum"),
        (lambda d: d["attrs"].pop("schema_version"), "'schema_version' is a required property"),
        (lambda d: _scan(d)["members"]["radius"].update(fletcher32=False), "True was expected"),
        (
            lambda d: _scan(d)["members"]["source_index"].update(dtype="int32"),
            "'int64' was expected",
        ),
        (lambda d: _scan(d)["members"].pop("parent"), "'parent' is a required property"),
        (lambda d: _scan(d)["members"]["points"].update(shape=[10, 2]), "shape/1: 3 was expected"),
        (
            lambda d: _scan(d)["members"].update(
                junk={"kind": "group", "attrs": {}, "members": {}}
            ),
            "Additional properties are not allowed",
        ),
    ],
)
def test_schema_rejects_broken_descriptions(real_archive, mutate, message):
    doc = copy.deepcopy(describe(real_archive))
    mutate(doc)
    faults = validate_description(doc)
    assert faults and any(message in f for f in faults), faults


def _scan(doc):
    return doc["members"]["scans"]["members"]["bun_zipper_res3"]


def test_build_schema_is_deterministic():
    assert build_schema() == build_schema()
    assert np.int64(L.SCHEMA_VERSION) == 2
