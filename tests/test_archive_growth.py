"""Archives that grow in O(new data): the streaming ScanWriter, register_parts, the index of part
files, what is never copied, and the confinement of parts to the archive's own directory."""

from __future__ import annotations

import os
import shutil

import h5py
import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive import layout as L
from lodbuilder.archive.scanwriter import ScanWriter, write_index
from lodbuilder.archive.validate import validate_archive
from lodbuilder.archive.writer import (
    ScanRecord,
    add_importance,
    add_ordering,
    register_parts,
    update_archive,
    write_archive,
    write_record,
)
from lodbuilder.datasets import demo_scan
from lodbuilder.errors import ArchiveError, CorruptArchiveError, InputError, UnsafeArchiveError
from lodbuilder.io import Scan


def record(n, name, seed=0, kind="wavy"):
    scan = demo_scan(n, kind=kind, seed=seed, name=name)
    return ScanRecord(scan, lodbuilder.euclidean_fps(scan.points))


def listing(path):
    """Relative names of the files of the archive's directory (recursively)."""
    return sorted(str(p.relative_to(path.parent)) for p in path.parent.rglob("*") if p.is_file())


def stats(path):
    """(inode, mtime_ns, bytes) of every part file of the archive."""
    pdir = path.with_name(path.name + ".scans")
    return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns, p.read_bytes()) for p in pdir.iterdir()}


# ---------------------------------------------------------------------------------- ScanWriter


def test_streamed_blocks_equal_the_in_memory_record(tmp_path):
    rec = record(9000, "s", seed=4)
    rec.scan.attributes["rgb"] = np.random.default_rng(0).integers(0, 255, (9000, 3), dtype=np.uint8)
    imp = np.linspace(0, 1, 9000)
    rec.importance["lin"] = (imp, {"k": 3})
    extra = lodbuilder.euclidean_fps(rec.scan.points, seeds=[17])
    rec.orderings["other"] = (extra, {"kind": "test"})
    whole = write_record(tmp_path / "whole.h5", rec)

    # the same scan written in uneven blocks through the public streaming writer
    with lodbuilder.open_archive(whole.path) as arc:
        v = arc.scan()
        pts, src, rad, par = v.points(), v.source_index, v.radius, v.parent
        attrs = v.attributes()
        inv = np.empty_like(src)
        inv[src] = np.arange(src.size)
    with ScanWriter(tmp_path / "streamed.h5", "s", 9000, metadata=rec.scan.metadata) as w:
        for lo, hi in [(0, 1), (1, 4000), (4000, 4001), (4001, 8999), (8999, 9000)]:
            w.write(pts[lo:hi], src[lo:hi], rad[lo:hi], par[lo:hi],
                    attributes={k: a[lo:hi] for k, a in attrs.items()},
                    importance={"lin": imp.astype(np.float32)[src][lo:hi]})
        info = w.finish(seeds=rec.ordering.seeds, importance_parameters={"lin": {"k": 3}},
                        orderings={"other": (inv[extra.order], extra.radius, extra.parent, {"kind": "test"})})
    assert (info.name, info.n_points, info.n_ordered) == ("s", 9000, 9000)
    assert info.nbytes == (tmp_path / "streamed.h5").stat().st_size
    np.testing.assert_allclose(info.bounds_min, rec.scan.points.min(0))
    assert validate_archive(info.path) == []
    with lodbuilder.open_archive(whole.path) as a, lodbuilder.open_archive(info.path) as b:
        va, vb = a.scan(), b.scan()
        assert vb.encoding == va.encoding == "float32"
        for k in (1, 100, 5000, 9000):
            la, lb = va.level(size=k), vb.level(size=k)
            np.testing.assert_array_equal(la.points, lb.points)
            for key in la.attributes:
                np.testing.assert_array_equal(la.attributes[key], lb.attributes[key])
        np.testing.assert_array_equal(va.importance("lin"), vb.importance("lin"))
        assert vb.importance_parameters("lin") == {"k": 3}
        np.testing.assert_array_equal(va.level(size=50, ordering="other").points,
                                      vb.level(size=50, ordering="other").points)
        np.testing.assert_array_equal(va.seeds, vb.seeds)


def test_row_groups_are_contiguous_and_files_are_paged(tmp_path):
    rec = record(30000, "s", seed=1)
    rec.scan.attributes["i"] = np.arange(30000, dtype=np.float32)
    info = write_record(tmp_path / "a.h5", rec)
    with h5py.File(info.path, "r") as f:
        fcpl = f.id.get_create_plist()
        assert fcpl.get_file_space_strategy()[0] == h5py.h5f.FSPACE_STRATEGY_PAGE
        g = f["scans/s"]
        rows = g["points"].chunks[0]
        assert rows == L.row_group_rows(30000)
        per_point = ["points", "source_index", "radius", "parent", "attributes/i"]
        assert {g[d].chunks[0] for d in per_point} == {rows}
        # the first row group of every per-point dataset lies before any chunk of the second
        first = [g[d].id.get_chunk_info_by_coord((0,) * g[d].ndim) for d in per_point]
        second = [g[d].id.get_chunk_info_by_coord((rows,) + (0,) * (g[d].ndim - 1)) for d in per_point]
        assert max(c.byte_offset + c.size for c in first) <= min(c.byte_offset for c in second)


def _mutate(b, key, index, value):
    b[key][index] = value


@pytest.mark.parametrize(
    "bad,message",
    [
        (lambda b: _mutate(b, "radius", 1, 0.9),
         "radius of scan 's' increases at stored row 501; rows must be in farthest-point order"),
        (lambda b: _mutate(b, "radius", 3, np.nan), "radius of scan 's' holds NaN or negative values"),
        (lambda b: _mutate(b, "source_index", 5, 3),
         "source_index of scan 's' repeats an input index; each point goes once"),
        (lambda b: _mutate(b, "source_index", 5, 10**6),
         "source_index of scan 's' must be in [0, 1000); got values outside"),
        (lambda b: _mutate(b, "parent", 7, 600),
         "parent of scan 's' at stored row 507 is 600; parents must be earlier rows or -1"),
        (lambda b: _mutate(b, "points", (2, 1), np.nan),
         "points of scan 's' hold NaN or inf at stored row 502"),
        (lambda b: b.update(attributes={"j": np.zeros(500)}),
         "the attributes of scan 's' at stored row 500 are ['j'], the first block had ['i']"),
        (lambda b: b.update(attributes={"i": np.zeros(500, np.float32)}),
         "attribute 'i' of scan 's' is float32 at stored row 500, float64 in the first block"),
    ],
)
def test_scan_writer_refuses_bad_rows_and_leaves_nothing(tmp_path, bad, message):
    rng = np.random.default_rng(0)
    first = np.sort(rng.random(500))[::-1] + 1.0  # radii in (1, 2], non-increasing
    w = ScanWriter(tmp_path / "p.h5", "s", 1000)
    w.write(rng.random((500, 3)), np.arange(500), first, np.arange(-1, 499), attributes={"i": np.zeros(500)})
    second = {
        "points": rng.random((500, 3)),
        "source_index": np.arange(500, 1000),
        "radius": np.sort(rng.random(500))[::-1].copy() * 0.5,  # below the first block's radii
        "parent": np.arange(499, 999),
        "attributes": {"i": np.zeros(500)},
    }
    bad(second)
    with pytest.raises(InputError) as err:
        with w:
            w.write(second["points"], second["source_index"], second["radius"], second["parent"],
                    attributes=second["attributes"])
            w.finish()
    assert str(err.value).startswith(message), str(err.value)
    assert sorted(os.listdir(tmp_path)) == []


def test_scan_writer_counts_rows_and_keeps_the_encoding_exact(tmp_path):
    w = ScanWriter(tmp_path / "p.h5", "s", 10)
    w.write(np.zeros((4, 3)), np.arange(4), np.full(4, np.inf), np.full(4, -1))
    with pytest.raises(InputError, match=r"^scan 's': 4 rows written but the ScanWriter was opened for n_points=10$"):
        w.finish()
    assert os.listdir(tmp_path) == []
    # float32 chosen from the first row group; a later coordinate that float32 would round is refused
    n = 2 * L.row_group_rows(10_000)
    w = ScanWriter(tmp_path / "q.h5", "s", n)
    r = L.row_group_rows(n)
    w.write(np.full((r, 3), 0.5), np.arange(r), np.full(r, np.inf), np.full(r, -1))
    with pytest.raises(InputError, match=r"cannot be stored exactly as float32 \(chosen from the first row group\); pass encoding='float64'"):
        w.write(np.full((r, 3), 0.1), np.arange(r, 2 * r), np.full(r, np.inf), np.full(r, -1))
    assert os.listdir(tmp_path) == []
    with ScanWriter(tmp_path / "q.h5", "s", n, encoding="float64") as w:
        w.write(np.full((r, 3), 0.5), np.arange(r), np.full(r, np.inf), np.full(r, -1))
        w.write(np.full((r, 3), 0.1), np.arange(r, 2 * r), np.full(r, np.inf), np.full(r, -1))
        w.finish()
    with lodbuilder.open_archive(tmp_path / "q.h5") as arc:
        assert arc.scan().points()[-1].tolist() == [0.1, 0.1, 0.1]


def test_unordered_tail_must_be_empty(tmp_path):
    w = ScanWriter(tmp_path / "p.h5", "s", 5)
    w.write(np.zeros((5, 3)), np.arange(5), [np.inf, 1, 0.5, 0.0, 0.0], [-1, 0, 0, 1, -1])
    with pytest.raises(InputError, match=r"stored row 3 is beyond n_ordered=3 but has a radius or a parent"):
        w.finish(n_ordered=3)


# ----------------------------------------------------------------------------- register_parts


def test_register_parts_single_then_index(tmp_path):
    staged = tmp_path / "staged"
    staged.mkdir()
    a = write_record(staged / "a.h5", record(2000, "a", 1))
    b = write_record(staged / "b.h5", record(1500, "b", 2))
    c = write_record(staged / "c.h5", record(1000, "c", 3))
    arc = tmp_path / "out" / "x.h5"
    arc.parent.mkdir()
    # one part on a new archive: the archive is that one self-contained file (a hard link)
    assert register_parts(arc, [a]) == ["a"]
    assert listing(arc) == ["x.h5"]
    assert arc.stat().st_ino == a.path.stat().st_ino
    # more: an index and the parts directory; the caller's files stay where they were
    assert register_parts(arc, [b.path, c]) == ["b", "c"]
    assert (staged / "b.h5").is_file() and (staged / "c.h5").is_file()
    with lodbuilder.open_archive(arc) as x:
        assert x.scans == ["a", "b", "c"]
        parts = {r.name: r.part for r in x.rows}
        assert all(L.PART_NAME.fullmatch(p) for p in parts.values())
        np.testing.assert_array_equal(x.scan("b").points(), lodbuilder.open_archive(b.path).scan().points())
    assert listing(arc) == sorted(["x.h5"] + [f"x.h5.scans/{p}" for p in parts.values()])
    assert validate_archive(arc) == []
    with pytest.raises(ArchiveError, match=r"already holds scan\(s\) \['b'\]; pass --overwrite"):
        register_parts(arc, [b])
    two = tmp_path / "two.h5"
    update_archive(two, [record(300, "p", 4)])
    update_archive(two, [record(300, "q", 5)])
    with pytest.raises(ArchiveError, match=r"two.h5 is not a part file: it must hold exactly one scan stored in it \(it holds 2 in parts\)"):
        register_parts(arc, [two])


def test_adding_a_scan_copies_no_existing_data(tmp_path):
    path = tmp_path / "many.h5"
    update_archive(path, [record(4000, "s00", 0)])
    for i in range(1, 12):
        update_archive(path, [record(1000, f"s{i:02d}", i)])
    before = stats(path)
    index_before = path.stat().st_size
    update_archive(path, [record(1000, "zz", 99)])
    after = stats(path)
    new = set(after) - set(before)
    assert len(new) == 1
    for name, st in before.items():  # same inode, same mtime, same bytes: untouched
        assert after[name] == st
    # what was written: the new part and a new index of a few kB, nothing else
    assert path.stat().st_size < 64_000 and path.stat().st_size - index_before < 2_000
    with lodbuilder.open_archive(path) as arc:
        assert len(arc.scans) == 13
    assert validate_archive(path) == []


def test_overwrite_importance_and_ordering_rewrite_one_part(tmp_path):
    path = tmp_path / "a.h5"
    update_archive(path, [record(3000, "a", 1)])
    update_archive(path, [record(2000, "b", 2)])
    update_archive(path, [record(2500, "c", 3)])
    st = stats(path)
    with lodbuilder.open_archive(path) as arc:
        part_a = {r.name: r.part for r in arc.rows}["a"]
    values = np.linspace(0, 1, 3000)
    add_importance(path, "a", "lin", values, {"k": 1})
    rec_b = record(2000, "b", 2)
    add_ordering(path, "b", "again", lodbuilder.euclidean_fps(rec_b.scan.points, seeds=[5]), {"x": 1})
    update_archive(path, [record(800, "c", 9)], overwrite=True)
    after = stats(path)
    assert part_a not in after  # replaced parts are removed
    assert len(after) == 3 and not set(after) & set(st) - {part_a}  # a, b, c each rewritten once
    with lodbuilder.open_archive(path) as arc:
        v = arc.scan("a")
        np.testing.assert_allclose(v.importance("lin"), values[v.source_index].astype(np.float32))
        assert arc.scan("b").ordering_names == ["again"]
        assert arc.scan("c").n_points == 800
    assert validate_archive(path) == []
    # a single-scan archive stays one file when its scan is rewritten
    one = tmp_path / "one" / "o.h5"
    one.parent.mkdir()
    update_archive(one, [record(900, "o", 1)])
    add_importance(one, "o", "z", np.arange(900.0))
    assert listing(one) == ["o.h5"]


def test_write_archive_and_drop(tmp_path):
    path = tmp_path / "w.h5"
    write_archive(path, [record(500, "a", 1), record(600, "b", 2)])
    assert len(listing(path)) == 3
    update_archive(path, [], drop=["a"])
    with lodbuilder.open_archive(path) as arc:
        assert arc.scans == ["b"]
    assert len(listing(path)) == 2
    write_archive(path, [record(700, "c", 3)])
    assert listing(path) == ["w.h5"]
    with lodbuilder.open_archive(path) as arc:
        assert arc.scans == ["c"]


def test_no_lock_file_is_left_beside_the_archive(tmp_path):
    """reliability-2 item 13: a .NAME.h5.lock file was left beside every archive."""
    path = tmp_path / "a.h5"
    update_archive(path, [record(300, "a", 1)])
    assert listing(path) == ["a.h5"]
    update_archive(path, [record(300, "b", 2)])
    assert not (tmp_path / ".a.h5.lock").exists()
    assert [n for n in listing(path) if "lock" in n] == []


# -------------------------------------------------------------------------------- confinement


def _parted(tmp_path):
    path = tmp_path / "arc" / "a.h5"
    path.parent.mkdir()
    update_archive(path, [record(600, "one", 1)])
    update_archive(path, [record(500, "two", 2)])
    with lodbuilder.open_archive(path) as arc:
        rows = arc.rows
    return path, rows


def _set_row(path, name, **changes):
    """Rewrite the index of ``path`` with one row changed (what a crafted archive could hold)."""
    from dataclasses import replace

    with lodbuilder.open_archive(path) as arc:
        rows = [replace(r, **changes) if r.name == name else r for r in arc.rows]
    with h5py.File(path, "r+") as f:
        write_index(f, rows)


def _err(path, name="two"):
    with pytest.raises((CorruptArchiveError, ArchiveError)) as err:
        with lodbuilder.open_archive(path) as arc:
            arc.scan(name).level(size=10)
    return str(err.value)


@pytest.mark.parametrize("part", ["../x.h5", "/etc/passwd", "x.h5.scans/../../etc/passwd", "two.h5", ""])
def test_part_names_other_than_ours_are_refused(tmp_path, part):
    path, rows = _parted(tmp_path)
    if part == "":  # an inline row whose group is missing
        _set_row(path, "two", part="", part_bytes=0)
        assert _err(path) == (f"archive {path}: it does not hold scan 'two' (no group /scans/two); "
                              "the index is damaged or crafted")
        return
    _set_row(path, "two", part=part)
    assert _err(path) == (
        f"archive {path}: scan 'two' names part file {part!r}, which is not a plain part name in "
        f"{path}.scans; refusing to follow it (the index is damaged or crafted)"
    )
    # the writer refuses to carry such a row into a new index
    with pytest.raises(CorruptArchiveError, match="refusing to follow it"):
        update_archive(path, [record(100, "three", 3)])


def test_symlinks_non_archives_and_foreign_scans_are_refused(tmp_path):
    path, rows = _parted(tmp_path)
    pdir = path.with_name("a.h5.scans")
    two = {r.name: r for r in rows}["two"]
    one = {r.name: r for r in rows}["one"]
    victim = tmp_path / "outside.h5"
    shutil.copyfile(pdir / two.part, victim)
    # a symbolic link (out of the directory) where a part should be
    (pdir / two.part).unlink()
    (pdir / two.part).symlink_to(victim)
    assert _err(path) == (f"archive {path}: part {two.part} of scan 'two' is not a regular file "
                          "(a symbolic link?); refusing to follow it")
    # a file that is not an archive
    (pdir / two.part).unlink()
    (pdir / two.part).write_bytes(b"root:x:0:0:root:/root:/bin/bash\n" * 10)
    _set_row(path, "two", part_bytes=320)
    assert _err(path) == (f"archive {path}: part {two.part} of scan 'two' is not an lodbuilder "
                          "archive; refusing to read it")
    # a part that holds another scan
    _set_row(path, "two", part=one.part, part_bytes=one.part_bytes)
    assert _err(path) == (f"archive {path}: part {one.part} does not hold scan 'two' (no group "
                          "/scans/two); the index is damaged or crafted")
    # a part of another size than the index records
    _set_row(path, "two", part=one.part, part_bytes=one.part_bytes + 1)
    assert _err(path) == (f"archive {path}: part {one.part} of scan 'two' has {one.part_bytes} "
                          f"bytes, the index says {one.part_bytes + 1}; the part was changed or truncated")
    # the parts directory itself replaced by a link to somewhere else
    shutil.move(pdir, tmp_path / "elsewhere")
    pdir.symlink_to(tmp_path / "elsewhere")
    assert _err(path, "one") == (f"archive {path}: {pdir} is not a directory (a symbolic link or a "
                                 "file); refusing to follow it")
    with pytest.raises(CorruptArchiveError, match="is not a directory"):  # nor writes through it
        update_archive(path, [record(100, "three", 3)])


def test_moving_archives(tmp_path):
    single = tmp_path / "s.h5"
    update_archive(single, [record(400, "only", 1)])
    moved = tmp_path / "sub" / "t.h5"
    moved.parent.mkdir()
    shutil.move(single, moved)  # a single-scan archive is one file: move it anywhere
    with lodbuilder.open_archive(moved) as arc:
        assert arc.scan().n_points == 400
    path, rows = _parted(tmp_path)
    alone = tmp_path / "alone.h5"
    shutil.copyfile(path, alone)  # the index without its directory
    with pytest.raises(ArchiveError) as err:
        with lodbuilder.open_archive(alone) as arc:
            arc.scan("one")
    part = {r.name: r for r in rows}["one"].part
    assert str(err.value) == (
        f"archive {alone}: scan 'one' is stored in {tmp_path}/alone.h5.scans/{part}, and the "
        f"directory {tmp_path}/alone.h5.scans is missing: an archive of several scans is the file "
        "and that directory, move or copy them together"
    )
    # both together (renamed consistently) work
    dest = tmp_path / "dest"
    dest.mkdir()
    shutil.move(path, dest / "b.h5")
    shutil.move(path.with_name("a.h5.scans"), dest / "b.h5.scans")
    with lodbuilder.open_archive(dest / "b.h5") as arc:
        assert arc.scans == ["one", "two"] and arc.scan("two").n_points == 500
    assert validate_archive(dest / "b.h5") == []


# ------------------------------------------------------------------------- damaged archives


def _flip(path, dataset):
    with h5py.File(path, "r") as f:
        info = f[dataset].id.get_chunk_info(0)
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        b = fh.read(1)
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(bytes([b[0] ^ 0xFF]))


def test_adding_to_a_damaged_archive_copies_nothing(tmp_path):
    """reliability-2 item 7: adding a scan to a damaged archive copied the damaged scan."""
    path = tmp_path / "d.h5"
    update_archive(path, [record(3000, "bad", 1)])
    _flip(path, "scans/bad/radius")
    damaged = path.read_bytes()
    ino = path.stat().st_ino
    update_archive(path, [record(500, "good", 2)])
    with lodbuilder.open_archive(path) as arc:
        part = {r.name: r.part for r in arc.rows}["bad"]
        assert arc.scan("good").level(size=10).size == 10
    stored = path.with_name("d.h5.scans") / part
    assert stored.stat().st_ino == ino and stored.read_bytes() == damaged  # linked, not copied
    assert any("/scans/bad/radius fails its checksum" in f for f in validate_archive(path))
    # rewriting the damaged scan (which copies it) is refused, and nothing changes
    index = path.read_bytes()
    with pytest.raises(CorruptArchiveError, match=r"scan 'bad' dataset /scans/bad/radius fails its checksum"):
        add_importance(path, "bad", "z", np.zeros(3000))
    assert path.read_bytes() == index
    assert sorted(p.name for p in path.with_name("d.h5.scans").iterdir()) == sorted(
        r.part for r in lodbuilder.open_archive(path).rows
    )


def test_rewriting_a_scan_with_broken_invariants_is_refused(tmp_path):
    path = tmp_path / "i.h5"
    update_archive(path, [record(2000, "s", 1)])
    with h5py.File(path, "r+") as f:
        r = f["scans/s/radius"][:]
        r[10] = r[5] * 2  # radii increase: not a farthest point ordering any more
        del f["scans/s/radius"]
        L.create_dataset(f["scans/s"], "radius", r)
    before = path.read_bytes()
    # the reader's checks refuse it as the scan is read for the rewrite
    with pytest.raises(CorruptArchiveError, match=r"scan 's' dataset 'radius' increases at row 10 "):
        add_importance(path, "s", "z", np.zeros(2000))
    assert path.read_bytes() == before


def test_rewriting_a_scan_with_external_data_is_refused(tmp_path):
    """An attribute stored in another file (HDF5 external storage) is never copied in."""
    path = tmp_path / "e.h5"
    update_archive(path, [record(500, "s", 1)])
    secret = tmp_path / "secret.bin"
    secret.write_bytes(b"root:x:0:0:root:/root:/bin/bash\n" * 200)
    with h5py.File(path, "r+") as f:
        f["scans/s/attributes"].create_dataset("stolen", shape=(500,), dtype="u1",
                                               external=[(str(secret), 0, 500)])
    before = path.read_bytes()
    with pytest.raises(UnsafeArchiveError) as err:
        add_importance(path, "s", "z", np.zeros(500))
    assert str(err.value) == (
        f"archive {path} is refused: dataset '/scans/s/attributes/stolen' stores its data in "
        f"external file '{secret}'; lodbuilder reads nothing outside an archive; rebuild it with "
        "'lodbuilder build'"
    )
    assert path.read_bytes() == before and listing(path) == ["e.h5", "secret.bin"]


# ------------------------------------------------------------------------- schema 1 archives


def test_schema_1_archive_is_read_and_grown(tmp_path):
    """An archive written before parts existed (schema 1: scans in the file, no part columns)."""
    path = tmp_path / "v1.h5"
    write_record(path, record(700, "a", 1))
    with h5py.File(path, "r+") as f:  # what lodbuilder 0.1 wrote: two scans inline, no part column
        other = tmp_path / "b.h5"
        write_record(other, record(600, "b", 2))
        with h5py.File(other, "r") as g:
            g.copy(g["scans/b"], f["scans"], name="b")
        del f["index"]
        f.attrs["schema_version"] = np.int64(1)
    with lodbuilder.open_archive(path) as arc:
        assert arc.schema_version == 1 and arc.scans == ["a", "b"]
        pts = arc.scan("b").points()
    update_archive(path, [record(500, "c", 3)])
    with lodbuilder.open_archive(path) as arc:
        assert arc.scans == ["a", "b", "c"]
        parts = {r.part for r in arc.rows}
        np.testing.assert_array_equal(arc.scan("b").points(), pts)
    assert len(parts) == 2  # a and b share the old file, linked once as a part


def test_scan_view_int_encoding_streams(tmp_path, rng):
    q = rng.integers(0, 100000, size=(6000, 3))
    pts = q * 0.001 + np.array([512000.0, 4.1e6, 100.0])
    meta = {"las_scales": [0.001] * 3, "las_offsets": [512000.0, 4.1e6, 100.0]}
    scan = Scan(points=pts, name="las_like", metadata=meta)
    info = write_record(tmp_path / "l.h5", ScanRecord(scan, lodbuilder.euclidean_fps(pts)))
    with lodbuilder.open_archive(info.path) as arc:
        assert arc.scan().encoding == "int32"
