"""The write of a tiled build in bands of stored positions (lodbuilder.build.tiled.bands): band
tasks filter their rows into finished HDF5 chunks, the parent places them; the archive is the one
the one-process write (a ScanWriter fed every row in order) gives, and a kill at any moment of the
band phase resumes to the same archive."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import h5py
import numpy as np
import pytest
from test_tiled import wavy

import lodbuilder
from lodbuilder.archive import layout as L
from lodbuilder.io import Scan, write_points


def _datasets(path, name):
    """Every dataset of scan ``name``: its values, creation properties and raw chunks."""
    out = {}
    with h5py.File(path) as f:
        g = f[f"{L.G_SCANS}/{name}"]

        def visit(key, obj):
            if isinstance(obj, h5py.Dataset):
                chunks = None
                if obj.chunks is not None:
                    step = obj.chunks[0]
                    chunks = [obj.id.read_direct_chunk((i,) + (0,) * (obj.ndim - 1)) for i in range(0, obj.shape[0], step)]
                out[key] = (obj[()], obj.dtype, obj.chunks, obj.compression, obj.compression_opts, obj.shuffle,
                            obj.fletcher32, dict(obj.attrs), chunks)

        g.visititems(visit)
        attrs = {k: v for k, v in g.attrs.items() if k not in (L.S_BUILD, L.S_PROVENANCE)}
    return out, attrs


def _same(a, b):
    (da, aa), (db, ab) = a, b
    assert sorted(da) == sorted(db)
    for key in da:
        for x, y in zip(da[key], db[key], strict=True):
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y, err_msg=key)
            elif isinstance(x, dict):
                assert sorted(x) == sorted(y), key
                for k in x:
                    np.testing.assert_array_equal(x[k], y[k], err_msg=f"{key} {k}")
            else:
                assert x == y, key
    assert sorted(aa) == sorted(ab)
    for k in aa:
        np.testing.assert_array_equal(aa[k], ab[k], err_msg=k)


@pytest.mark.parametrize("encoding", ["float64", "int32"])
def test_chunks_made_apart_give_the_scan_writers_file(tmp_path, encoding):
    """Rows filtered into chunks in bands (any number of whole row groups, the last one short) and
    placed by a ChunkWriter: the same datasets, creation properties and chunk bytes as a
    ScanWriter fed the rows."""
    from lodbuilder.archive.chunks import filter_rows, spec_of
    from lodbuilder.archive.chunkwriter import ChunkWriter, radius_index
    from lodbuilder.archive.scanwriter import ScanWriter

    rng = np.random.default_rng(3)
    n = 45_001
    rows = L.row_group_rows(n)
    meta = {"scale": [0.01] * 3, "offset": [100.0, 200.0, 0.0]}
    pts = rng.integers(0, 5000, (n, 3)) * 0.01 + np.array([100.0, 200.0, 0.0])
    src = rng.permutation(n)
    rad = np.sort(rng.exponential(1.0, n))[::-1].copy()
    rad[0] = np.inf
    par = np.maximum(-1, np.arange(n) - 1 - rng.integers(0, 50, n))
    attrs = {"intensity": rng.integers(0, 300, n).astype(np.uint16), "rgb": rng.integers(0, 255, (n, 3)).astype(np.uint8)}
    ref = tmp_path / "ref.h5"
    with ScanWriter(ref, "s", n, metadata=meta, encoding=encoding) as w:
        for a in range(0, n, 7000):
            z = min(n, a + 7000)
            w.write(pts[a:z], src[a:z], rad[a:z], par[a:z], attributes={k: v[a:z] for k, v in attrs.items()})
        w.finish(seeds=[int(src[0])])
    offset, scale = L.metadata_scale(meta)
    stored = L.encode_as(pts, encoding, offset, scale)
    arrays = {L.D_SOURCE_INDEX: src, L.D_RADIUS: rad, L.D_PARENT: par, L.D_POINTS: stored,
              **{f"{L.G_ATTRIBUTES}/{k}": v for k, v in attrs.items()}}
    spec = spec_of({k: a[:rows] for k, a in arrays.items()})
    out = tmp_path / "bands.h5"
    with ChunkWriter(out, "s", n, spec, metadata=meta, encoding=encoding) as w:
        for k0 in range(0, n, 2 * rows):
            k1 = min(n, k0 + 2 * rows)
            table, blob = filter_rows(spec, rows, {k: a[k0:k1] for k, a in arrays.items()})
            w.write_chunks(k0, k1, table, blob, bounds=(pts[k0:k1].min(0), pts[k0:k1].max(0)),
                           radius_index=radius_index(rad[k0:k1], k0), last_tail=k1 - 1, last_radius=rad[k1 - 1])
        w.finish(seeds=[int(src[0])])
    _same(_datasets(ref, "s"), _datasets(out, "s"))
    assert out.stat().st_size == ref.stat().st_size


def _script(tmp_path, fault_after=None):
    """A build of a small sheet in tiny tiles, with row groups of 200 rows and one per band (the
    knobs are the parent's: it passes them to the tasks)."""
    script = tmp_path / "run.py"
    script.write_text(textwrap.dedent("""
        import sys
        import lodbuilder
        from lodbuilder.archive import layout as L
        import lodbuilder.build.tiled.write as write
        L.ROW_GROUP_MIN = 200
        write.BLOCK = 200
        if __name__ == "__main__":
            lodbuilder.build_archive(sys.argv[1], sys.argv[2], workers=2, _tile_points=400)
    """))
    return script


def _small_bands(monkeypatch):
    import lodbuilder.build.tiled.write as write

    monkeypatch.setattr(L, "ROW_GROUP_MIN", 200)
    monkeypatch.setattr(write, "BLOCK", 200)


def test_the_banded_write_gives_the_one_process_write(tmp_path, monkeypatch):
    """A tiny scan in many tiles and many bands: the archive's datasets (values, creation
    properties, chunk bytes) are those of the one-process write from the same work files."""
    from lodbuilder.build.tiled import driver
    from lodbuilder.build.tiled.write import write_scan

    _small_bands(monkeypatch)
    pts = wavy(2400, np.random.default_rng(5))
    real = driver._write
    ref = tmp_path / "ref.part.h5"
    seen = {}

    def both(executor, work, part, name, sp, seeds, record, provenance, buckets, radii, progress):
        write_scan(work, ref, name, sp.n, sp.fields, sp.metadata, sp.encoding, seeds, {}, {}, None, buckets, radii)
        seen["bands"] = int(buckets["buckets"])
        return real(executor, work, part, name, sp, seeds, record, provenance, buckets, radii, progress)

    monkeypatch.setattr(driver, "_write", both)
    scan = Scan(points=pts, attributes={"i": np.arange(len(pts), dtype=np.int32)}, name="t")
    out = tmp_path / "t.h5"
    res = lodbuilder.build_archive(scan, out, _tile_points=300)
    assert res.scans[0].method == "tiled"
    assert seen["bands"] == 12  # 2304 points (a 48 x 48 grid) in row groups of 192, one a band
    _same(_datasets(ref, "t"), _datasets(out, "t"))
    with lodbuilder.open_archive(out) as arc:
        v = arc.scan("t")
        assert v.build["tiled"]["tiles"] >= 8
        kinds = [r[0] for r in v.build["tasks"]["rows"]]
        assert kinds.count("write_band") == 12 and v.build["phase_order"][-1] == "write"
    from lodbuilder.archive.validate import validate_archive

    assert validate_archive(out) == []


def test_a_kill_in_the_band_phase_resumes_to_the_same_archive(tmp_path, monkeypatch):
    """kill -9 of the build right after the first band's marker (many bands), and an interrupt in
    the middle of placing the bands, a damaged band file: each resumes to the uninterrupted
    build's archive; finished bands are not filtered again."""
    from lodbuilder.build.tiled import bands
    from lodbuilder.build.tiled import layout as WL

    pts = wavy(2400, np.random.default_rng(6))
    src = write_points(tmp_path / "sheet.npy", pts)
    _small_bands(monkeypatch)
    ref = tmp_path / "ref.h5"
    lodbuilder.build_archive(src, ref, workers=2, _tile_points=400)
    want = _datasets(ref, "sheet")
    # kill -9 after the first band's marker
    archive = tmp_path / "killed.h5"
    env = dict(os.environ, **{WL.FAULT_ENV: "chunks"})
    proc = subprocess.run([sys.executable, str(_script(tmp_path)), str(src), str(archive)], env=env,
                          stderr=subprocess.DEVNULL, timeout=600)
    assert proc.returncode == -signal.SIGKILL
    (work,) = archive.with_name(f".{archive.name}.parts").glob("*.work")
    assert sorted(p.name for p in work.glob("chunks.*.json")) == ["chunks.0.json"]
    time.sleep(0.3)
    lodbuilder.build_archive(src, archive, workers=2, _tile_points=400)
    _same(want, _datasets(archive, "sheet"))
    # an interrupt while the bands are placed (after the fourth band's marker), then a finished
    # band's file damaged
    again = tmp_path / "again.h5"
    real = bands.mark
    marked = []

    def stop(work, piece, doc):
        out = real(work, piece, doc)
        marked.append(piece)
        if len(marked) == 4:
            raise KeyboardInterrupt
        return out

    with monkeypatch.context() as mp:
        mp.setattr(bands, "mark", stop)
        with pytest.raises(KeyboardInterrupt):
            lodbuilder.build_archive(src, again, workers=2, _tile_points=400)
    (work,) = again.with_name(f".{again.name}.parts").glob("*.work")
    done = {int(p.name.split(".")[1]) for p in work.glob("chunks.*.json")}
    assert len(done) == 4 and 0 in done
    blob = work / WL.chunks(max(done))
    data = bytearray(blob.read_bytes())
    data[10] ^= 0xFF
    blob.write_bytes(bytes(data))
    lodbuilder.build_archive(src, again, workers=2, _tile_points=400)
    _same(want, _datasets(again, "sheet"))
    with lodbuilder.open_archive(again) as arc:  # this run's band tasks: the unfinished and the damaged
        rows = arc.scan("sheet").build["tasks"]["rows"]
    assert sum(1 for r in rows if r[0] == "write_band" and r[4] >= 0) == 12 - len(done) + 1


def test_a_failed_band_names_itself_and_leaves_the_archive(tmp_path, monkeypatch):
    """A band task that fails fails the build naming the band and its positions; the archive is
    as it was."""
    from lodbuilder.build.tiled import bands
    from lodbuilder.errors import BuildError

    _small_bands(monkeypatch)
    out = tmp_path / "t.h5"
    lodbuilder.build_archive(Scan(points=np.random.default_rng(1).random((300, 3)), name="other"), out)
    before = out.read_bytes()
    real = bands.write_band

    def broken(work, band, *args):
        if band == 2:
            raise MemoryError("no room for this band")
        return real(work, band, *args)

    monkeypatch.setattr(bands, "write_band", broken)
    scan = Scan(points=wavy(2400, np.random.default_rng(5)), name="t")
    with pytest.raises(BuildError) as exc:
        lodbuilder.build_archive(scan, out, _tile_points=300)
    assert str(exc.value) == ("scan 't': the write of band 3 of 12 (positions 384 to 576) failed: MemoryError: "
                              "no room for this band")
    assert out.read_bytes() == before


def test_a_raw_block_writes_a_bounded_number_of_bucket_files(tmp_path, monkeypatch):
    """The 10^8-point survey (900 files, 342 bands) wrote one bucket file per raw block and band:
    307,800 files, and its permutation took 16 x the time per point of a 21.56M survey. A block now
    writes at most BUCKET_FILES files (runs of consecutive buckets, one frame per piece); each file is
    deleted once every band it holds is written; the archive is the same."""
    import lodbuilder.build.tiled.write as write
    from lodbuilder.build.tiled import bands, driver
    from lodbuilder.build.tiled import layout as WL

    _small_bands(monkeypatch)
    pts = wavy(2400, np.random.default_rng(5))
    d = tmp_path / "survey"
    d.mkdir()
    for i in range(3):  # (three raw blocks)
        write_points(d / f"part{i}.npy", pts[i::3])
    one = tmp_path / "one.h5"
    lodbuilder.build_archive(d, one, joint="t", _tile_points=300)  # (12 bands: a file per bucket)
    monkeypatch.setattr(write, "BUCKET_FILES", 4)
    real_write, real_prune = driver._write, bands.prune
    seen: dict = {"pruned": []}

    def spy(executor, work, part, name, sp, seeds, record, provenance, buckets, radii, progress):
        seen["files"] = work.names("bucket.")
        return real_write(executor, work, part, name, sp, seeds, record, provenance, buckets, radii, progress)

    def prune(work, names):
        for f in names:  # (each only once every band it holds is written)
            assert all(work.size(WL.marker(WL.chunks_piece(k))) is not None for k in WL.bucket_range(f)), f
        seen["pruned"] += names
        real_prune(work, names)

    monkeypatch.setattr(driver, "_write", spy)
    monkeypatch.setattr(bands, "prune", prune)
    runs = tmp_path / "runs.h5"
    lodbuilder.build_archive(d, runs, joint="t", _tile_points=300)
    per_block: dict[str, int] = {}
    for f in seen["files"]:
        per_block[f.split(".")[2]] = per_block.get(f.split(".")[2], 0) + 1
    assert max(per_block.values()) == 4 and len(per_block) == 3
    assert {f.split(".")[1] for f in seen["files"]} == {"0_3", "3_6", "6_9", "9_12"}
    assert sorted(seen["pruned"]) == sorted(seen["files"])
    _same(_datasets(one, "t"), _datasets(runs, "t"))


def test_the_bands_are_handed_out_before_the_part_file_is_made(tmp_path, monkeypatch):
    """Once the first band has decided the datasets' creation properties, the other bands go to
    the workers before the parent makes the part file and places the first band's chunks (the
    workers waited for both: 0.84 s of a loaded 2-worker build of the 21.56M survey). In this
    process (an in-memory scan) a band runs when it is handed out, so each has run by then; the
    archive is the same."""
    from lodbuilder.archive import chunkwriter
    from lodbuilder.build.tiled import bands

    _small_bands(monkeypatch)
    scan = Scan(points=wavy(2400, np.random.default_rng(5)), name="t")
    ref = tmp_path / "ref.h5"
    lodbuilder.build_archive(scan, ref, _tile_points=300)
    calls: list[int] = []
    seen: list[int] = []
    real_band, real_writer = bands.write_band, chunkwriter.ChunkWriter

    def band(work, b, *args):
        calls.append(b)
        return real_band(work, b, *args)

    class Writer(real_writer):
        def __init__(self, *a, **k):
            seen.append(len(calls))
            super().__init__(*a, **k)

    monkeypatch.setattr(bands, "write_band", band)
    monkeypatch.setattr(chunkwriter, "ChunkWriter", Writer)
    out = tmp_path / "t.h5"
    lodbuilder.build_archive(scan, out, _tile_points=300)
    assert seen == [12] and sorted(calls) == list(range(12))
    _same(_datasets(ref, "t"), _datasets(out, "t"))
