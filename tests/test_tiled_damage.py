"""A resumed tiled build never trusts a damaged work file (finding 5 of reliability-3).

A build is stopped at a chosen moment (a deterministic fault hook: the next phase raises
KeyboardInterrupt, as Ctrl-C does; the work directory stays for a resume), then one work file is
flipped, truncated or zeroed, and the build is run again: the archive must equal, bit for bit, the
one an uninterrupted build writes (the damaged piece is done again), and say nothing wrong."""

from __future__ import annotations

import re
import shutil
import zlib
from pathlib import Path

import numpy as np
import pytest

import lodbuilder
from lodbuilder.archive.validate import validate_archive
from lodbuilder.build.tiled import driver as D
from lodbuilder.io import Scan

TILE_POINTS = 5_000


def _scan():
    rng = np.random.default_rng(4)
    side = 140
    g = np.stack(np.meshgrid(np.arange(side), np.arange(side)), -1).reshape(-1, 2).astype(float)
    g = (g + rng.uniform(-0.3, 0.3, g.shape)) / side
    pts = np.c_[g, 0.08 * np.sin(4 * np.pi * g[:, 0]) * np.cos(4 * np.pi * g[:, 1])]
    return Scan(points=pts, attributes={"intensity": rng.random(len(pts)).astype(np.float32)}, name="sheet")


def _build(archive, **kw):
    return lodbuilder.build_archive(_scan(), archive, _tile_points=TILE_POINTS, **kw)


def _same(a, b):
    with lodbuilder.open_archive(a) as x, lodbuilder.open_archive(b) as y:
        va, vb = x.scan("sheet"), y.scan("sheet")
        for field in ("source_index", "radius", "parent"):
            np.testing.assert_array_equal(getattr(va, field)[:], getattr(vb, field)[:])
        np.testing.assert_array_equal(va.points(), vb.points())
        np.testing.assert_array_equal(va.attributes()["intensity"], vb.attributes()["intensity"])


# the moment of the stop: the module and function that raises (what is done by then: everything before)
MOMENTS = {"split": ("driver", "distribute_phase"), "tiles": ("driver", "put_json"), "merge": ("driver", "_merge"),
           "radii": ("radii", "radii_phase"), "write": ("bands", "write_phase"),
           "bands": ("driver", "_timings")}  # (bands: every band of the write done, the part not yet finished)


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    path = tmp_path_factory.mktemp("clean") / "clean.h5"
    res = _build(path)
    assert res.scans[0].method == "tiled"
    return path


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """moment -> (archive, pristine copy of its work directory), each built once."""
    out = {}
    mp = pytest.MonkeyPatch()
    try:
        for moment, (module, fn) in MOMENTS.items():
            d = tmp_path_factory.mktemp(moment)
            archive = d / "a.h5"

            def stop(*a, **k):
                raise KeyboardInterrupt

            if fn == "put_json":  # stopped once two tiles are ordered (their markers written)
                stop = _after_two_orderings(D.put_json)
            mp.setattr(f"lodbuilder.build.tiled.{module}.{fn}", stop)
            with pytest.raises(KeyboardInterrupt):
                _build(archive)
            mp.undo()
            parts = d / ".a.h5.parts"
            shutil.copytree(parts, d / "pristine", symlinks=True)
            out[moment] = (archive, parts, d / "pristine")
    finally:
        mp.undo()
    return out


def _after_two_orderings(put_json):
    written = []

    def write(store, name, doc):
        sums = put_json(store, name, doc)
        if name.startswith("order."):
            written.append(name)
            if len(written) == 2:
                raise KeyboardInterrupt
        return sums

    return write


def _work(parts):
    (w,) = parts.glob("*.work")
    return w


def _damage(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    assert data, path
    if how == "flip":
        for i in np.linspace(0, len(data) - 1, 5).astype(int):
            data[i] ^= 0x5A
        path.write_bytes(bytes(data))
    elif how == "truncate":
        path.write_bytes(bytes(data[: len(data) // 2]))
    else:
        path.write_bytes(bytes(len(data)))


def _cases():
    """(moment, file, damage): every kind of work file the moment has, each damage in turn."""
    kinds = {
        # (a read or split task's marker is not read again once its phase's marker is written)
        # (the read blocks' samples are deleted once summed into sample.npy)
        # (the sample is deleted once the plan is done; the read blocks' coordinates once every split is)
        "split": ["raw.0.xyz", "decimated.bin", "spill.json", "plan.json"],
        # {t}: a tile whose ordering was done when the build stopped
        "tiles": ["stream.{t}.keys", "face.{t}.1.bin", "order.{t}.1.json", "halo.{t}.0.bin", "head.bin", "coarse.json"],
        # (the faces are deleted once every tile is ordered: the order marker damaged, every ordering again;
        # the read blocks' coordinates once the tiles' pieces are written: a damaged plan reads the blocks again)
        "merge": ["core.0.0.bin", "halo.1.0.bin", "head.bin", "stream.2.keys", "order.json", "order.1.1.json",
                  "distribute.json", "decimated.bin"],
        "radii": ["merged.1.i8", "rank.0.i8", "spill.json", "cover.0.ev", "cover.1.pt", "cover.2.json",
                  "pieces.1.links.bin"],
        # (by the write the streams, faces, raw blocks, tiles' points and covering files are deleted: a damaged
        # merge.json or radii.json makes the pieces that wrote them, and those before, again)
        # (a read block's ranks are deleted once it is permuted: a damaged covering or permutation marker makes
        # the ranks again)
        "write": ["ranks.json", "radius.0.f8", "parent.0.i8", "merge.json", "radii.json", "coarse.json", "head.bin",
                  "permute.0.json", "pieces.json", "order.1.1.json", "cover.1.json"],
        # (each band's bucket is deleted once the band is written: its chunks.json damaged, the buckets again)
        "bands": ["chunks.0.bin", "chunks.0.json", "merged.0.i8", "buckets.json"],
    }
    how = ["flip", "truncate", "zero"]
    out = []
    for moment, files in kinds.items():
        for i, f in enumerate(files):
            out.append((moment, f, how[i % 3]))
    return out


@pytest.mark.parametrize(("moment", "name", "how"), _cases())
def test_a_damaged_work_file_is_made_again(stopped, clean, moment, name, how, caplog):
    archive, parts, pristine = stopped[moment]
    if parts.exists():
        shutil.rmtree(parts)
    shutil.copytree(pristine, parts, symlinks=True)
    w = _work(parts)
    if "{t}" in name:
        name = name.format(t=sorted(w.glob("order.*.1.json"))[0].name.split(".")[1])
    _damage(w / name, how)
    with caplog.at_level("WARNING", logger="lodbuilder"):
        res = _build(archive)
    assert res.scans[0].status == "built"
    assert validate_archive(archive) == []
    _same(archive, clean)
    assert not parts.exists()
    assert "doing it again" in caplog.text
    archive.unlink()


def test_the_markers_hold_a_checksum_of_every_file(stopped):
    """Every file in the work directory is listed, with its size and CRC-32, by a marker."""
    from lodbuilder.build.tiled import layout as WL
    from lodbuilder.build.tiled.sums import read_json, sum_file

    _, _, pristine = stopped["bands"]
    (w,) = pristine.glob("*.work")
    listed: dict[str, list[int]] = {}
    for m in w.glob("*.json"):
        doc = read_json(m)
        assert doc is not None, m
        listed.update(doc.get("files") or {})
    # (the workers' task logs, tasks.<pid>.jsonl, are diagnostics that no phase reads back)
    files = {p.name for p in w.iterdir() if p.suffix not in (".json", ".jsonl") and p.name != ".lodbuilder-work"}
    assert files <= set(listed)
    for name in files:
        assert sum_file(w / name) == listed[name]
    order = (w / "merged.1.i8").read_bytes()
    assert listed["merged.1.i8"] == [len(order), zlib.crc32(order)]
    # the orderings' markers, listed by the order phase's marker from what the parent wrote
    orderings = [n for n in listed if n.startswith("order.") and n.endswith(".json")]
    assert orderings and all(sum_file(w / n) == listed[n] for n in orderings)
    # what is listed but gone was deleted once every piece that reads it was done (layout.PRUNE_AFTER;
    # every band is written, so are their buckets)
    gone = {n for n in set(listed) - files if not (w / n).exists()}  # (the order marker lists the orderings' markers)
    assert {n.split(".")[0] for n in gone} == {"raw", "stream", "seam", "links", "deferred", "dropped", "core", "halo", "cover", "radloc",
                                               "space", "bucket", "face", "sample", "rank"}
    assert all(WL.consumers(n) is not None for n in gone)


def test_the_parent_does_not_read_back_the_markers_it_wrote(tmp_path, monkeypatch, clean):
    """The order phase's marker lists the orderings' markers with the size and CRC-32 of what the
    parent wrote, and the merge takes their contents from the same: none is read back (on an
    object store that was three requests a tile, one after another in the parent)."""
    from lodbuilder.build.tiled import store as S

    read = []
    get, total = S.LocalStore.get, S.Store.sum
    monkeypatch.setattr(S.LocalStore, "get", lambda self, name: read.append(name) or get(self, name))
    monkeypatch.setattr(S.Store, "sum", lambda self, name, *a, **k: read.append(name) or total(self, name, *a, **k))
    res = _build(tmp_path / "a.h5")
    assert res.scans[0].method == "tiled"
    assert read and not [n for n in read if re.fullmatch(r"order\.\d+\.\d+\.json", n)]
    _same(tmp_path / "a.h5", clean)


def test_force_recovers_from_a_forged_work_directory(stopped, clean):
    """A damaged file whose marker was rewritten to match (a forger, or a bug) cannot be found by
    its checksum: --force starts the scan's work afresh and the archive is right again."""
    from lodbuilder.build.tiled.sums import read_json, sum_file, write_json

    archive, parts, pristine = stopped["merge"]
    if parts.exists():
        shutil.rmtree(parts)
    shutil.copytree(pristine, parts, symlinks=True)
    w = _work(parts)
    _damage(w / "halo.0.0.bin", "flip")
    for marker in ("distribute.json", "split.0.json"):
        doc = read_json(w / marker)
        doc["files"]["halo.0.0.bin"] = sum_file(w / "halo.0.0.bin")
        write_json(w / marker, doc)
    res = _build(archive, force=True)
    assert res.scans[0].status == "built"
    _same(archive, clean)
    archive.unlink()


def test_a_forged_las_work_file_names_no_internal_option(tmp_path, monkeypatch):
    """Finding 5: damaged LAS coordinates in a resumed build said "pass encoding='float64' to
    ScanWriter", an option the command line does not have. A damage that gets past the checksums
    (here a forged marker) is reported as damaged work files, with --force, which recovers. (The
    buckets now hold the coordinates as the archive stores them, int32 here: a flipped bit of one
    is another coordinate on the grid, which nothing but the checksums can tell; the forged bit is
    the first record's stored position, which then repeats another's.)"""
    import zstandard

    from lodbuilder.build.tiled.sums import read_json, sum_file, write_json
    from lodbuilder.errors import BuildError

    src = Path("/work/shared/data/simple.las")
    clean = tmp_path / "clean.h5"
    lodbuilder.build_archive(src, clean, _tile_points=400)
    archive = tmp_path / "a.h5"

    def stop(*a, **k):
        raise KeyboardInterrupt

    with monkeypatch.context() as mp:
        mp.setattr("lodbuilder.build.tiled.bands.write_phase", stop)  # (just before the write)
        with pytest.raises(KeyboardInterrupt):
            lodbuilder.build_archive(src, archive, _tile_points=400)
    (w,) = (tmp_path / ".a.h5.parts").glob("*.work")
    doc = read_json(w / "buckets.json")
    fname, a, z = doc["pieces"][0][0]  # (bucket 0's first piece: one compressed frame of its file)
    bucket = w / fname
    raw = bucket.read_bytes()
    data = bytearray(zstandard.ZstdDecompressor().decompress(raw[a:z]))
    data[0] ^= 0x01  # the lowest bit of the first record's stored position
    frame = zstandard.ZstdCompressor(level=1).compress(bytes(data))
    bucket.write_bytes(raw[:a] + frame + raw[z:])
    shift = len(frame) - (z - a)
    for pieces in doc["pieces"]:  # (the frames after it in that file moved)
        for p in pieces:
            if p[0] == fname and p[1] >= z:
                p[1], p[2] = p[1] + shift, p[2] + shift
    doc["pieces"][0][0][2] = a + len(frame)
    doc["files"][fname] = sum_file(bucket)
    write_json(w / "buckets.json", doc)
    with pytest.raises(BuildError) as e:
        lodbuilder.build_archive(src, archive, _tile_points=400)
    assert "ScanWriter" not in str(e.value) and "encoding=" not in str(e.value)
    assert str(e.value).startswith("scan 'simple': the tiled build's work files disagree (bucket 0 holds ")
    assert str(e.value).endswith("); they are damaged: run the build again with --force")
    lodbuilder.build_archive(src, archive, _tile_points=400, force=True)
    with lodbuilder.open_archive(archive) as x, lodbuilder.open_archive(clean) as y:
        np.testing.assert_array_equal(x.scan("simple").points(), y.scan("simple").points())
        np.testing.assert_array_equal(x.scan("simple").radius[:], y.scan("simple").radius[:])


KILLED = """
import os, signal, sys
from pathlib import Path
import lodbuilder
from lodbuilder.build.tiled import driver as D

if __name__ == "__main__":
    put_json = D.put_json
    written = []

    def write(store, name, doc):  # kill -9 once two tiles are ordered (their markers written)
        put_json(store, name, doc)
        if name.startswith("order."):
            written.append(name)
            if len(written) == 2:
                os.kill(os.getpid(), signal.SIGKILL)

    D.put_json = write
    lodbuilder.build_archive(sys.argv[1], sys.argv[2], workers=2, _tile_points=5000)
"""


def test_kill_9_then_damage_then_resume(tmp_path):
    """A real kill -9 (the pool's workers die with the build) in the tile phase, then a flipped
    decimated copy (the plan again, from read blocks read again) and a truncated halo piece of an
    ordered tile: the resumed build redoes both pieces and stores exactly what an uninterrupted
    build stores."""
    import subprocess
    import sys

    from lodbuilder.io import write_points

    src = write_points(tmp_path / "sheet.npy", _scan().points)
    clean = tmp_path / "clean.h5"
    lodbuilder.build_archive(src, clean, workers=2, _tile_points=5000)
    archive = tmp_path / "a.h5"
    script = tmp_path / "killed.py"
    script.write_text(KILLED)
    r = subprocess.run([sys.executable, str(script), str(src), str(archive)], capture_output=True, timeout=300)
    assert r.returncode == -9, r.stderr
    w = _work(tmp_path / ".a.h5.parts")
    t = sorted(w.glob("order.*.1.json"))[0].name.split(".")[1]
    _damage(w / "decimated.bin", "flip")  # (the plan again: the read blocks' coordinates, deleted, read again)
    _damage(w / f"halo.{t}.0.bin", "truncate")
    res = lodbuilder.build_archive(src, archive, workers=2, _tile_points=5000)
    assert res.scans[0].status == "built"
    with lodbuilder.open_archive(archive) as x, lodbuilder.open_archive(clean) as y:
        va, vb = x.scan("sheet"), y.scan("sheet")
        np.testing.assert_array_equal(va.source_index[:], vb.source_index[:])
        np.testing.assert_array_equal(va.radius[:], vb.radius[:])
        np.testing.assert_array_equal(va.points(), vb.points())
        assert va.build["tiled"]["resumed"]["tiles_ordered_before"] >= 1
