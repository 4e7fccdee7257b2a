"""Archive layout, writer and reader: round trips, encodings, errors, atomic updates."""

from __future__ import annotations

import hashlib
import inspect

import h5py
import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive import layout as L
from lodbuilder.archive.validate import validate_archive
from lodbuilder.archive.writer import ScanRecord, add_importance, add_ordering, update_archive
from lodbuilder.datasets import demo_scan
from lodbuilder.errors import (
    ArchiveError,
    CorruptArchiveError,
    InputError,
    NotAnArchiveError,
    ScanFileError,
    ScanNotFoundError,
    SchemaVersionError,
)
from lodbuilder.io import Scan


def sha(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A 2500-point demo scan, its ordering and an archive holding it."""
    scan = demo_scan(2500, seed=3, name="wavy")
    ordg = lodbuilder.fastfps(scan.points)
    path = tmp_path_factory.mktemp("arc") / "a.h5"
    update_archive(path, [ScanRecord(scan, ordg, provenance={"source_name": "gen"})])
    return scan, ordg, path


def test_round_trip_prefix_order_and_attributes(small):
    scan, ordg, path = small
    with lodbuilder.open_archive(path) as arc:
        assert arc.scans == ["wavy"]
        v = arc.scan()
        assert v.n_points == len(scan) == v.n_ordered
        np.testing.assert_array_equal(v.source_index, ordg.order)
        np.testing.assert_array_equal(v.radius, ordg.radius)
        np.testing.assert_array_equal(v.parent, ordg.parent)
        np.testing.assert_array_equal(v.points(), scan.points[ordg.order])  # lossless
        attrs = v.attributes()
        assert set(attrs) == set(scan.attributes)
        for key, arr in scan.attributes.items():
            assert attrs[key].dtype == arr.dtype
            np.testing.assert_array_equal(attrs[key], arr[ordg.order])
        assert v.encoding == "float32"  # demo coordinates are float32-exact
        assert v.provenance["source_name"] == "gen"
        assert v.provenance["lodbuilder_version"] == lodbuilder.__version__
        assert v.build["voxel_size"] == ordg.voxel_size
        assert v.format_metadata["generator"] == "wavy"
        np.testing.assert_array_equal(v.seeds, ordg.seeds)
        idx = arc.index()
        assert idx[0]["name"] == "wavy" and idx[0]["n_points"] == len(scan)
        np.testing.assert_allclose(idx[0]["bounds_min"], scan.points.min(0))
    assert validate_archive(path) == []


def test_every_dataset_is_checksummed(small):
    """Per-point datasets are chunked with a fletcher32 checksum; small ones (index columns,
    radius_index, seeds) are compact: their bytes sit in the object header, which HDF5 checksums."""
    with h5py.File(small[2], "r") as f:
        seen = {}

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                layout = obj.id.get_create_plist().get_layout()
                seen[name] = layout
                if layout == h5py.h5d.COMPACT:
                    assert obj.nbytes <= L.COMPACT_MAX, name
                else:
                    assert layout == h5py.h5d.CHUNKED and obj.fletcher32, name

        f.visititems(visit)
    for d in ("points", "source_index", "radius", "parent"):
        assert seen[f"scans/wavy/{d}"] == h5py.h5d.CHUNKED
    assert seen["index/name"] == seen["scans/wavy/radius_index"] == h5py.h5d.COMPACT


def test_damaged_compact_dataset_is_detected(small, tmp_path):
    p = tmp_path / "c.h5"
    p.write_bytes(small[2].read_bytes())
    with h5py.File(p, "r") as f:
        ri = f["scans/wavy/radius_index"][:]
    data = bytearray(p.read_bytes())
    i = bytes(data).find(ri[1:].tobytes())
    assert i > 0
    data[i + 3] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(Exception, match="checksum"):  # never a silently wrong rho level
        with lodbuilder.open_archive(p) as arc:
            arc.scan().level(rho=float(ri[1]) * 0.99)


@pytest.mark.parametrize(
    "points,meta,encoding",
    [
        (np.array([[0.1, 0.2, 0.3], [1e6 + 0.1, 2.0, 3.0]]), {}, "float64"),
        (np.array([[0.5, 0.25, 1.0], [2.0, 3.0, 4.0]]), {}, "float32"),
        (
            np.array([[500000.01, 4000000.02, 10.03], [500001.00, 4000001.99, 11.00]]),
            {"scale": [0.01, 0.01, 0.01], "offset": [500000.0, 4000000.0, 0.0]},
            "int32",
        ),
    ],
)
def test_coordinate_encoding_is_lossless(points, meta, encoding):
    stored, enc, off, sc = L.encode_points(points, meta)
    assert enc == encoding
    np.testing.assert_array_equal(L.decode_points(stored, enc, off, sc), points)


def test_offset_scale_not_used_when_lossy():
    pts = np.array([[500000.012345, 1.0, 2.0], [3.0, 4.0, 5.0]])
    _, enc, _, _ = L.encode_points(pts, {"scale": [0.01] * 3, "offset": [0.0] * 3})
    assert enc == "float64"


def test_int_encoded_archive_reads_back_exactly(tmp_path, rng):
    q = rng.integers(0, 100000, size=(400, 3))
    pts = q * 0.001 + np.array([512000.0, 4.1e6, 100.0])  # as laspy computes x = X * scale + offset
    meta = {"las_scales": [0.001] * 3, "las_offsets": [512000.0, 4.1e6, 100.0]}
    scan = Scan(points=pts, name="las_like", metadata=meta)
    ordg = lodbuilder.euclidean_fps(pts)
    update_archive(tmp_path / "b.h5", [ScanRecord(scan, ordg)])
    with lodbuilder.open_archive(tmp_path / "b.h5") as arc:
        v = arc.scan("las_like")
        assert v.encoding == "int32"
        np.testing.assert_array_equal(v.points(), pts[ordg.order])


def test_add_scan_keeps_existing_scans_and_duplicate_name_is_refused(small, tmp_path):
    scan, ordg, path = small
    p = tmp_path / "c.h5"
    update_archive(p, [ScanRecord(scan, ordg)])
    other = demo_scan(800, kind="sphere", seed=1, name="ball")
    update_archive(p, [ScanRecord(other, lodbuilder.fastfps(other.points))])
    with lodbuilder.open_archive(p) as arc:
        assert arc.scans == ["ball", "wavy"]
        np.testing.assert_array_equal(arc.scan("wavy").points(), scan.points[ordg.order])
        assert [r["name"] for r in arc.index()] == ["ball", "wavy"]
    before = sha(p)
    with pytest.raises(ArchiveError, match=r"already holds scan\(s\) \['ball'\]; pass --overwrite"):
        update_archive(p, [ScanRecord(other, lodbuilder.fastfps(other.points))])
    assert sha(p) == before
    smaller = demo_scan(300, kind="sphere", seed=2, name="ball")
    update_archive(p, [ScanRecord(smaller, lodbuilder.fastfps(smaller.points))], overwrite=True)
    with lodbuilder.open_archive(p) as arc:
        assert arc.scan("ball").n_points == 300
    assert validate_archive(p) == []


def test_importance_and_extra_ordering(small, tmp_path):
    scan, ordg, path = small
    p = tmp_path / "d.h5"
    update_archive(p, [ScanRecord(scan, ordg)])
    values = np.linspace(0, 1, len(scan))
    add_importance(p, "wavy", "curvature", values, {"k": 16})
    perm = np.random.default_rng(0).permutation(len(scan))
    extra = lodbuilder.fastfps(scan.points, seeds=[int(perm[0])])
    add_ordering(p, "wavy", "other", extra, {"kind": "test"})
    with lodbuilder.open_archive(p) as arc:
        v = arc.scan()
        np.testing.assert_allclose(
            v.importance("curvature"), values[v.source_index].astype(np.float32)
        )
        assert v.importance_parameters("curvature") == {"k": 16}
        assert v.ordering_names == ["other"]
        lev = v.level(size=50, ordering="other")
        np.testing.assert_array_equal(lev.source_index, extra.order[:50])
        np.testing.assert_array_equal(lev.points, scan.points[extra.order[:50]])
        assert v.ordering_parameters("other")["kind"] == "test"
        pos = v.ordering_positions("other")  # the public pair cli floor_level uses
        np.testing.assert_array_equal(v.source_index[pos], extra.order)
        same = v.positions_level(pos[:50], rho=lev.rho, ordering="other")
        np.testing.assert_array_equal(same.points, lev.points)
        np.testing.assert_array_equal(same.rank, lev.rank)
        assert (same.rho, same.ordering, same.size) == (lev.rho, "other", 50)
        with pytest.raises(InputError) as info:
            v.positions_level([0, len(scan)], rho=1.0)
        assert str(info.value) == (
            f"positions must be a list of stored positions 0..{len(scan) - 1} of scan 'wavy'"
        )
        with pytest.raises(InputError, match="has no ordering 'nope'"):
            v.ordering_positions("nope")
        with pytest.raises(InputError, match="has no ordering 'nope'"):
            v.level(size=5, ordering="nope")
        with pytest.raises(InputError, match=r"importance map 'x' must hold one number per point"):
            add_importance(p, "wavy", "x", np.ones(3))
    assert validate_archive(p) == []


def test_not_an_archive_and_newer_schema(tmp_path, small):
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"hello, not hdf5")
    with pytest.raises(NotAnArchiveError, match="is not an lodbuilder archive"):
        lodbuilder.open_archive(junk)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = 1
    with pytest.raises(NotAnArchiveError, match="HDF5 file but not an lodbuilder archive"):
        lodbuilder.open_archive(other)
    newer = tmp_path / "newer.h5"
    newer.write_bytes(small[2].read_bytes())
    with h5py.File(newer, "r+") as f:
        f.attrs["schema_version"] = np.int64(L.SCHEMA_VERSION + 1)
    with pytest.raises(SchemaVersionError, match=rf"schema version {L.SCHEMA_VERSION + 1}, newer than the {L.SCHEMA_VERSION} .*upgrade"):
        lodbuilder.open_archive(newer)
    with pytest.raises(ScanFileError, match="does not exist"):
        lodbuilder.open_archive(tmp_path / "missing.h5")


def test_unknown_scan_and_ambiguous_scan(small, tmp_path):
    with lodbuilder.open_archive(small[2]) as arc:
        with pytest.raises(ScanNotFoundError, match="has no scan 'nope'; it holds 'wavy'"):
            arc.scan("nope")


def test_missing_attribute_importance_and_ordering_name_the_ones_there_quoted(small):
    """Like scan names, the names a scan has are quoted (before: 'it has blue, green, ...')."""
    with lodbuilder.open_archive(small[2]) as arc:
        v = arc.scan()
        have = ", ".join(repr(k) for k in v.attribute_names)
        with pytest.raises(InputError) as exc:
            v.attributes(names=["nope"])
        assert str(exc.value) == f"scan 'wavy' has no attribute 'nope'; it has {have}"
        with pytest.raises(InputError) as exc:
            v.importance("nope")
        assert str(exc.value) == "scan 'wavy' has no importance map 'nope'; it has none"
        with pytest.raises(InputError) as exc:
            v.ordering("nope")
        assert str(exc.value) == "scan 'wavy' has no ordering 'nope'; it has 'uniform'"


def _public_members(cls):
    """Every public property and method of ``cls``, collected (so a new one is checked too)."""
    members = {n: getattr(cls, n) for n in dir(cls) if not n.startswith("_")}
    return sorted(n for n, m in members.items() if isinstance(m, property) or callable(m))


def _use(obj, name):
    """Read the property ``name`` of ``obj``, or call the method with placeholder arguments (the
    closed check comes before the arguments are looked at)."""
    member = getattr(type(obj), name)
    if isinstance(member, property):
        return getattr(obj, name)
    sig = inspect.signature(inspect.unwrap(member))
    required = [
        p
        for p in list(sig.parameters.values())[1:]
        if p.default is p.empty and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
    ]
    return getattr(obj, name)(*[None] * len(required))


def test_every_public_member_of_a_closed_archive_is_an_archive_error(small):
    """Before: on a closed archive ScanView.build/.provenance/.attribute_names... returned {} or
    [], .points()/.radius raised 'is damaged', Archive.scan() said 'the index is damaged'."""
    from lodbuilder.archive.reader import Archive, ScanView

    path = small[2]
    with lodbuilder.open_archive(path) as arc:
        v = arc.scan()
    views = _public_members(ScanView)
    archives = [n for n in _public_members(Archive) if n != "close"]
    assert {"build", "points", "level", "refine_box", "crs", "attribute_names"} <= set(views)
    assert {"scan", "scans", "index", "file"} <= set(archives)
    for obj, names in ((v, views), (arc, archives)):
        for name in names:
            with pytest.raises(ArchiveError) as info:
                _use(obj, name)
            assert str(info.value) == (
                f"archive {path} is closed; read it inside `with open_archive(...)`"
            ), name
    arc.close()  # closing twice is fine
    assert repr(arc) == f"<Archive {path} scans=['wavy']>"


def _flip_byte_in_dataset(path, dataset):
    with h5py.File(path, "r") as f:
        ds = f[dataset]
        offset = ds.id.get_chunk_info(0).byte_offset
        size = ds.id.get_chunk_info(0).size
    with open(path, "r+b") as fh:
        fh.seek(offset + size // 2)
        b = fh.read(1)
        fh.seek(offset + size // 2)
        fh.write(bytes([b[0] ^ 0xFF]))


def test_checksum_failure_names_scan_and_dataset(small, tmp_path):
    p = tmp_path / "bad.h5"
    p.write_bytes(small[2].read_bytes())
    _flip_byte_in_dataset(p, "scans/wavy/radius")
    with lodbuilder.open_archive(p) as arc:
        v = arc.scan()
        with pytest.raises(
            CorruptArchiveError, match=r"scan 'wavy' dataset /scans/wavy/radius fails its checksum"
        ):
            v.level(size=10)
    faults = validate_archive(p)
    assert any("/scans/wavy/radius" in f for f in faults)


def test_bad_scan_names_are_refused(small):
    scan, ordg, _ = small
    for bad in ["a/b", "", ".hidden"]:
        s = Scan(points=scan.points, name=bad)
        with pytest.raises(InputError, match="scan name"):
            update_archive("/tmp/never-written.h5", [ScanRecord(s, ordg)])


def test_record_size_mismatch(small, tmp_path):
    scan, ordg, _ = small
    s = Scan(points=scan.points[:10], name="x")
    with pytest.raises(
        InputError, match="ordering of scan 'x' is for 2500 points but the scan has 10"
    ):
        update_archive(tmp_path / "e.h5", [ScanRecord(s, ordg)])
    assert not (tmp_path / "e.h5").exists()


def test_partial_ordering_tail_is_stored_last(tmp_path, rng):
    pts = rng.random((300, 3))
    ordg = lodbuilder.euclidean_fps(pts, size=200)
    update_archive(tmp_path / "f.h5", [ScanRecord(Scan(points=pts, name="p"), ordg)])
    with lodbuilder.open_archive(tmp_path / "f.h5") as arc:
        v = arc.scan()
        assert (v.n_points, v.n_ordered) == (300, 200)
        assert sorted(v.source_index) == list(range(300))
        assert (v.radius[200:] == 0).all()
        assert v.level(fraction=1.0).size == 200
        with pytest.raises(InputError) as exc:
            v.level(size=201)
        assert str(exc.value).startswith(
            "scan 'p' is ordered only down to covering radius ") and str(exc.value).endswith(
            " (200 of 300 points: a partial build), so no level holds 201 points; rebuild it with "
            "--size 201 or without --size: lodbuilder build SOURCE -o ARCHIVE --force")
    assert validate_archive(tmp_path / "f.h5") == []


def test_compression_pays_decision():
    assert L.compression_pays(np.zeros(10000, dtype=np.int64))
    assert L.compression_pays(np.random.default_rng(0).permutation(10000).astype(np.int64))
    assert not L.compression_pays(np.random.default_rng(0).random(10000))


@pytest.mark.parametrize("n", [1, 1000, 65536, 65537, 1_000_000])
def test_chunks_are_balanced(n):
    rows = L.chunk_shape((n, 3), 8)[0]
    n_chunks = -(-n // rows)
    assert rows * n_chunks - n < n_chunks  # the last chunk is nearly full
    assert rows * 3 * 8 <= (1 << 20) + 24


def test_validate_names_invariant_faults(small, tmp_path):
    p = tmp_path / "v.h5"
    p.write_bytes(small[2].read_bytes())
    with h5py.File(p, "r+") as f:
        g = f["scans/wavy"]
        src = g["source_index"][:]
        src[5] = src[6]
        del g["source_index"]
        L.create_dataset(g, "source_index", src)
        par = g["parent"][:]
        par[20] = 25
        del g["parent"]
        L.create_dataset(g, "parent", par)
        g.attrs["build"] = "{not json"
    faults = validate_archive(p)
    assert any("source_index is not a permutation of 0..2499" in f for f in faults)
    assert any("parent of position 20 is 25; parents must come earlier" in f for f in faults)
    assert any("attribute 'build' is not valid JSON" in f for f in faults)


def test_reading_a_level_imports_nothing_heavy(small):
    import subprocess
    import sys

    code = (
        "import sys, lodbuilder\n"
        f"with lodbuilder.open_archive({str(small[2])!r}) as a:\n"
        "    lev = a.scan().level(fraction=0.5)\n"
        "print(lev.size, [m for m in ('numba', 'pyvista', 'dask', 'scipy', 'fsspec', 's3fs', 'aiohttp') if m in sys.modules])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1250", "[]"]


def test_output_directory_checks_are_one_check(tmp_path, monkeypatch):
    """archive.files.check_writable_dir and io._files.check_output_path share
    io._files.output_dir_problem; each keeps its subject and exception class."""
    from lodbuilder.archive.files import check_writable_dir
    from lodbuilder.io._files import check_output_path

    missing = tmp_path / "no" / "a.h5"
    with pytest.raises(ArchiveError) as info:
        check_writable_dir(missing, "archive")
    assert str(info.value) == f"archive directory {tmp_path / 'no'} does not exist; create it first"
    with pytest.raises(ScanFileError) as info2:
        check_output_path(missing)
    assert str(info2.value) == (
        f"{missing}: output directory {tmp_path / 'no'} does not exist; create it first"
    )
    monkeypatch.setattr("lodbuilder.io._files.os.access", lambda *a, **k: False)
    with pytest.raises(ArchiveError) as info:
        check_writable_dir(tmp_path / "a.h5", "part")
    assert str(info.value) == (
        f"part directory {tmp_path} is not writable; choose another output path"
    )
    with pytest.raises(ScanFileError) as info2:
        check_output_path(tmp_path / "a.ply")
    assert str(info2.value) == (
        f"{tmp_path / 'a.ply'}: output directory {tmp_path} is not writable; choose another "
        "output path"
    )


def test_messages_quote_the_scan_names(small, tmp_path):
    """Before: 'it holds wavy' and '(one of a, b)', and add_importance said "it holds ['wavy']"."""
    scan, ordg, path = small
    with pytest.raises(ScanNotFoundError) as info:
        add_importance(path, "nope", "m", np.zeros(len(scan)))
    assert str(info.value) == f"archive {path} has no scan 'nope'; it holds 'wavy'"
    many = tmp_path / "many.h5"
    names = [f"s,{i:02d}" for i in range(12)]  # a comma in a name stays readable
    scans = [demo_scan(200, seed=i, name=n) for i, n in enumerate(names)]
    update_archive(many, [ScanRecord(s, lodbuilder.fastfps(s.points)) for s in scans])
    listed = ", ".join(repr(n) for n in names[:10]) + ", ..."
    with lodbuilder.open_archive(many) as arc:
        with pytest.raises(ScanNotFoundError) as info:
            arc.scan()
        assert str(info.value) == (
            f"archive {many} holds 12 scans; choose one with --scan (one of {listed})"
        )
        with pytest.raises(ScanNotFoundError) as info:
            arc.scan("x")
        assert str(info.value) == f"archive {many} has no scan 'x'; it holds {listed}"
