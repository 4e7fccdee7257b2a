"""The tiled build's work files on disk (issue 19: work files <= 2 x the archive): the compressed
files read back exactly, and the phases never keep the largest files beside each other."""

from __future__ import annotations

import uuid

import numpy as np
import pytest

from lodbuilder.build.tiled import layout as WL
from lodbuilder.build.tiled import workdir as W
from lodbuilder.build.tiled.store import FsspecStore, LocalStore


@pytest.fixture(params=["local", "memory"])
def store(request, tmp_path):
    if request.param == "local":
        return LocalStore(tmp_path)
    return FsspecStore(f"memory://lodbuilder-test-{uuid.uuid4().hex}/work")


@pytest.mark.parametrize("band", [1, 7, 64, 10_000])
def test_a_banded_file_gives_every_band_of_ranks(store, band):
    """The records of a rank-sorted banded file (workdir.put_banded) in [k0, k1) and the one
    before, as a search of the whole array finds them, whatever the frames' band."""
    rng = np.random.default_rng(band)
    pt = np.zeros(900, WL.POINT)
    pt["rank"] = np.sort(rng.choice(5000, 900, replace=False))
    pt["parent"] = rng.integers(-1, 5000, 900)
    pt["space"] = rng.random(900)
    sums = W.put_banded(store, "cover.0.pt", pt, band)
    assert sums[0] == store.size("cover.0.pt")
    assert band < 64 or sums[0] < pt.nbytes  # (compressed: random records, large frames)
    cuts = [0, 1, 63, 64, 65, int(pt["rank"][7]), int(pt["rank"][9]), 2500, 4999, 5000, 6000, 7000]
    for k0 in cuts:
        for k1 in cuts:
            if k1 < k0:
                continue
            recs, before = W.banded_slice(store, "cover.0.pt", WL.POINT, k0, k1)
            a, z = np.searchsorted(pt["rank"], k0), np.searchsorted(pt["rank"], k1)
            np.testing.assert_array_equal(recs, pt[a:z])
            assert (before is None) if a == 0 else (before == pt[a - 1])


def test_an_empty_banded_file(store):
    W.put_banded(store, "cover.0.ev", np.zeros(0, WL.EVENT), 64)
    recs, before = W.banded_slice(store, "cover.0.ev", WL.EVENT, 0, 10)
    assert recs.shape == (0,) and recs.dtype == WL.EVENT and before is None


def test_a_damaged_banded_file_is_an_os_error(tmp_path):
    store = LocalStore(tmp_path)
    ev = np.zeros(100, WL.EVENT)
    ev["rank"] = np.arange(0, 1000, 10)
    W.put_banded(store, "cover.0.ev", ev, 64)
    raw = bytearray(store.get("cover.0.ev"))
    store.put("cover.0.ev", bytes(raw[:-3]))
    with pytest.raises(OSError, match="cover.0.ev: not a framed work file"):
        W.banded_slice(store, "cover.0.ev", WL.EVENT, 0, 100)
    raw[10] ^= 0xFF
    store.put("cover.0.ev", bytes(raw))
    with pytest.raises(OSError, match="cover.0.ev: a damaged frame"):
        W.banded_slice(store, "cover.0.ev", WL.EVENT, 0, 100)


@pytest.mark.parametrize("rows", [1, 7, 65536])
def test_a_framed_file_gives_every_run_of_rows(store, rows):
    """A tile's stream (workdir.put_framed: frames of ``rows`` records) read back by any run of
    rows, as the merge's bands read it."""
    rng = np.random.default_rng(rows)
    s = np.zeros(300, WL.STREAM)
    for name in WL.STREAM.names:
        s[name] = rng.random(300)
    W.put_framed(store, "stream.0.bin", s, rows)
    for a, z in [(0, 0), (0, 1), (0, 300), (6, 8), (7, 14), (13, 200), (299, 300), (250, 400), (300, 300)]:
        np.testing.assert_array_equal(W.read_framed(store, "stream.0.bin", WL.STREAM, a, z - a), s[a:z])
    W.put_framed(store, "stream.1.bin", s[:0], rows)
    assert W.read_framed(store, "stream.1.bin", WL.STREAM, 0, 5).shape == (0,)
    # written as it comes, in uneven pieces (a merge band's output): the same bytes
    f = W.Framed(store.writer("stream.2.bin"), rows)
    for a, z in [(0, 3), (3, 3), (3, 100), (100, 101), (101, 300)]:
        f.write(s[a:z])
    f.commit()
    f.close()
    assert store.get("stream.2.bin") == store.get("stream.0.bin")
    # runs read one after another by one reader (each frame decompressed once)
    r = W.FramedReader(store, "stream.2.bin", WL.STREAM)
    np.testing.assert_array_equal(np.concatenate([r.read(a, 50) for a in range(0, 300, 50)]), s)


def _counting_frames(monkeypatch):
    """The frames :func:`workdir._read_frames` decompresses, by their first row."""
    seen: list[int] = []
    real = W._read_frames

    def count(store, name, index, dtype):
        seen.extend(index["first"].tolist())
        return real(store, name, index, dtype)

    monkeypatch.setattr(W, "_read_frames", count)
    return seen


def test_runs_read_on_decompress_each_frame_once(store, monkeypatch):
    """Runs of rows read one after another, across frames (frames of 7 rows, runs of 50): every
    frame is decompressed once (a run that began in a frame read before decompressed it again)."""
    s = np.arange(300, dtype="<i8")
    W.put_framed(store, "merged.1.i8", s, 7)
    seen = _counting_frames(monkeypatch)
    r = W.FramedReader(store, "merged.1.i8", np.dtype("<i8"))
    np.testing.assert_array_equal(np.concatenate([r.read(a, 50) for a in range(0, 300, 50)]), s)
    assert sorted(seen) == list(range(0, 300, 7))


@pytest.mark.parametrize("rows", [1, 3, 65536])
def test_a_tile_stream_is_framed_within_key_bins(store, monkeypatch, rows):
    """A tile's stream (workdir.put_stream) keeps input index and key, in frames of at most ``rows``
    rows that never hold two key bins: the rows of any run of whole bins (a band of the merge) are
    read by decompressing that run's frames alone, each once."""
    rng = np.random.default_rng(rows)
    s = np.zeros(400, WL.STREAM)
    s["key"] = np.sort(np.r_[np.inf, rng.random(390) * 50, np.zeros(9)])[::-1]
    s["g"], s["x"], s["m"] = rng.permutation(400), rng.random(400), rng.random(400)
    W.put_stream(store, "stream.0.keys", s, rows)
    index = W._frames_index(store, "stream.0.keys")
    bins = WL.key_bins(s["key"])
    assert (index["count"] <= rows).all() and index["count"].sum() == 400
    assert all(bins[f] == bins[z] for f, z in zip(index["first"], index["last"], strict=True))
    every = W.FramedReader(store, "stream.0.keys", WL.KEYS).read(0, 400)
    np.testing.assert_array_equal(every["g"], s["g"])
    np.testing.assert_array_equal(every["key"], s["key"])
    cuts = np.flatnonzero(np.diff(bins)) + 1
    a, z = int(cuts[3]), int(cuts[9])  # bins 4 to 9, read in runs of 5 rows
    seen = _counting_frames(monkeypatch)
    r = W.FramedReader(store, "stream.0.keys", WL.KEYS)
    got = np.concatenate([r.read(k, min(5, z - k)) for k in range(a, z, 5)])
    np.testing.assert_array_equal(got["g"], s["g"][a:z])
    assert sorted(seen) == [int(f) for f in index["first"] if a <= f < z]


def test_the_largest_work_files_are_never_on_disk_together(tmp_path, monkeypatch):
    """Whenever a piece's marker is written, the work directory holds no write bucket beside a
    covering file or a tile's points (the buckets come after the radii and the join), no tile
    stream beside a rank file, no block sample after the spill, no sample after the plan, no read
    block's coordinates once the tiles' pieces are written and never a copy of the attributes (the
    marker being written aside: its own files are pruned after it), and no read block's ranks
    once its permutation is done (0.27 x the archive on a one-file survey)."""
    import lodbuilder
    from lodbuilder.build.tiled import driver, sums
    from lodbuilder.io import Scan

    seen: list[tuple[str, set[str]]] = []
    put_json = sums.put_json

    def snapshot(work, name, doc):
        put_json(work, name, doc)
        (w,) = [p for p in (tmp_path / ".t.h5.parts").glob("*.work")]
        seen.append((name, {p.name for p in w.iterdir()}))

    # the driver holds put_json by name: patch it there too (and import it before patching, else a first
    # import during the patch would keep the snapshot for every later build of the session)
    monkeypatch.setattr(sums, "put_json", snapshot)
    monkeypatch.setattr(driver, "put_json", snapshot)
    rng = np.random.default_rng(1)
    g = (np.stack(np.meshgrid(np.arange(140), np.arange(140)), -1).reshape(-1, 2) + rng.uniform(-0.3, 0.3, (19600, 2)))
    pts = np.c_[g / 140, 0.08 * np.sin(4 * np.pi * g[:, 0] / 140)]
    res = lodbuilder.build_archive(Scan(points=pts, attributes={"i": np.arange(19600, dtype=np.int32)}, name="t"),
                                   tmp_path / "t.h5", _tile_points=6_000)
    assert res.scans[0].method == "tiled"
    assert any(n.startswith("permute.") for n, _ in seen) and any(n.startswith("band.") for n, _ in seen)
    for name, files in seen:
        files = files - {name}  # (what its own marker prunes goes once the marker is written)
        kinds = {f.split(".")[0] for f in files if not f.endswith((".json", ".jsonl"))}
        assert not ("bucket" in kinds and kinds & {"cover", "core", "halo", "radloc", "space"}), (name, kinds)
        assert not ("stream" in kinds and "rank" in kinds), (name, kinds)
        if "spill.json" in files:
            assert not [f for f in files if f.startswith("sample.") and f.endswith(".f64")], name
        if "plan.json" in files:  # (the sample: read by the plan alone)
            assert "sample.npy" not in files, name
        if "distribute.json" in files:  # (the read blocks' coordinates: read by the plan and the split alone)
            assert not [f for f in files if f.startswith("raw.")], name
        assert not [f for f in files if f.startswith("raw.") and not f.endswith(".xyz")], name  # (no attributes)
        # a read block's ranks: read by the covering passes and its own permutation, then deleted
        permuted = {f.split(".")[1] for f in files if f.startswith("permute.") and f.endswith(".json")}
        assert not [f for f in files if f.startswith("rank.") and f.endswith(".i8") and f.split(".")[1] in permuted], name
