"""Damaged or edited archives give one-line errors: no hang, no h5py traceback, no wrong level.

Findings 2, 4, 5 and 6 of ``../shared/findings/reliability-2.md``: a one-byte change that made
every command spin forever, raw h5py exceptions from damaged metadata, structurally wrong
archives that crashed commands, and stored values that slices trusted.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
from clirun import in_child, one_line_error, run
from hostile import SCAN, N, copy, edit, make_archive, rewrite, small_ply, vlen_strings

import lodbuilder
from lodbuilder.archive import layout as L
from lodbuilder.archive.safety import check_heap_collection
from lodbuilder.archive.validate import validate_archive
from lodbuilder.errors import CorruptArchiveError

REPO = Path(__file__).resolve().parents[1]
REBUILD = "; rebuild it from the source scan"


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return make_archive(tmp_path_factory.mktemp("base") / "base.h5")


@pytest.fixture
def arc(base, tmp_path):
    return copy(base, tmp_path / "a.h5")


@pytest.fixture
def old(base, tmp_path):
    """The archive with its text attributes as variable-length strings (as lodbuilder 0.1 wrote
    them, and as anyone can craft them): their bytes are in a global heap."""
    return vlen_strings(copy(base, tmp_path / "a.h5"))




one_error = one_line_error


# --- finding 2: the one-byte hang ----------------------------------------------------------


def heap_objects(data: bytes) -> tuple[int, list[tuple[int, int, int]]]:
    """Offset of the first global heap collection and its objects as (offset, index, size)."""
    at = data.index(b"GCOL")
    size = int.from_bytes(data[at + 8 : at + 16], "little")
    objs, p = [], 16
    while p + 16 <= size:
        idx = int.from_bytes(data[at + p : at + p + 2], "little")
        osize = int.from_bytes(data[at + p + 8 : at + p + 16], "little")
        objs.append((p, idx, osize))
        if idx == 0:
            break
        p += 16 + ((osize + 7) & ~7)
    return at, objs


def cli(*argv, timeout=120):
    return in_child(*argv, cwd=REPO, timeout=timeout)


HANG_COMMANDS = {
    "info": [],
    "validate": [],
    "slice": ["--size", "10", "-o", "{d}/o.ply"],
    "view": ["--screenshot", "{d}/o.png"],
    "evaluate": ["--json", "{d}/o.json"],
    "export": ["--size", "10", "-o", "{d}/o.copc.laz"],
}


@pytest.mark.parametrize("cmd", [*HANG_COMMANDS, "build"])
def test_a_heap_that_never_ends_is_refused_not_looped_on(old, tmp_path, cmd):
    """The free-space object of the global heap claims size 0: HDF5 2.0 loops forever on it
    (inside H5HG__cache_heap_deserialize, holding the GIL). Every command refuses it instead."""
    arc = old
    data = bytearray(arc.read_bytes())
    at, objs = heap_objects(bytes(data))
    p = next(p for p, idx, _ in objs if idx == 0)
    data[at + p + 8 : at + p + 16] = bytes(8)
    arc.write_bytes(bytes(data))
    if cmd == "build":
        argv = ["build", small_ply(tmp_path / "in.ply"), "-o", arc, "--no-progress"]
    else:
        argv = [cmd, arc, *(a.format(d=tmp_path) for a in HANG_COMMANDS[cmd])]
    res = cli(*argv)  # a regression times out here instead of hanging the suite
    assert res.returncode == 2, (res.stdout, res.stderr)
    assert res.stderr.splitlines() == [
        f"lodbuilder {cmd}: error: archive {arc} is damaged: its global heap at byte {at} is "
        f"malformed (object 0 at offset {p} has size 0, the collection 4096){REBUILD}"
    ]
    assert sorted(os.listdir(tmp_path)) == sorted(["a.h5"] + (["in.ply"] if cmd == "build" else []))


def test_the_fuzzers_one_bit_change_is_refused(old, tmp_path):
    """What the fuzzer found: bit 8 of one heap object's size (the scan's provenance JSON)."""
    arc = old
    data = bytearray(arc.read_bytes())
    at, objs = heap_objects(bytes(data))
    p = next(p for p, idx, _ in objs if bytes(data[at + p + 16 : at + p + 32]).startswith(b'{"cr'))
    data[at + p + 9] ^= 0x01
    arc.write_bytes(bytes(data))
    for cmd in ("info", "slice"):
        extra = ["--size", "10", "-o", tmp_path / "o.ply"] if cmd == "slice" else []
        res = cli(cmd, arc, *extra)
        assert res.returncode == 2, res.stderr
        assert re.fullmatch(
            rf"lodbuilder {cmd}: error: archive {re.escape(str(arc))} is damaged: its global heap "
            rf"at byte {at} is malformed \(object \d+ at offset \d+ has size \d+, the collection "
            rf"4096\){REBUILD}\n",
            res.stderr,
        ), res.stderr


def _heap(objects, size=4096):
    buf = bytearray(size)
    buf[:4] = b"GCOL"
    buf[4] = 1
    buf[8:16] = size.to_bytes(8, "little")
    p = 16
    for idx, osize in objects:
        buf[p : p + 2] = idx.to_bytes(2, "little")
        buf[p + 8 : p + 16] = osize.to_bytes(8, "little")
        p += 16 + ((osize + 7) & ~7) if idx else osize
    return memoryview(bytes(buf))


def test_heap_walk_accepts_good_heaps_and_refuses_loops():
    check_heap_collection(_heap([(1, 10), (2, 20), (0, 4096 - 16 - 32 - 40)]), 8, 0, "f.h5")
    check_heap_collection(_heap([(1, 10)])[:2048], 8, 0, "f.h5")  # a partial first read
    for objs, detail in [
        ([(1, 10), (0, 0)], "object 0 at offset 48 has size 0"),
        ([(1, 5000)], "object 1 at offset 16 has size 5000"),
        ([(1, 2**64 - 8)], f"object 1 at offset 16 has size {2**64 - 8}"),
    ]:
        with pytest.raises(CorruptArchiveError, match=re.escape(detail)):
            check_heap_collection(_heap(objs), 8, 0, "f.h5")


# --- finding 4: h5py exceptions become CorruptArchiveError ---------------------------------

SIGNATURES = (b"OHDR", b"OCHK", b"FRHP", b"FHDB", b"BTHD", b"BTLF", b"GCOL")


def metadata_blocks(path):
    data = path.read_bytes()
    return sorted(
        (m.start(), sig.decode()) for sig in SIGNATURES for m in re.finditer(re.escape(sig), data)
    )


@pytest.mark.parametrize("strings", ["fixed", "variable"])
def test_every_damaged_metadata_block_gives_one_line(base, tmp_path, capsys, strings):
    """One bit changed inside each metadata block of the archive (object headers and their
    continuations, fractal heaps of dense links and attributes, B-trees, the global heap of an
    archive with variable-length strings): one line naming the file, never a traceback."""
    src = copy(base, tmp_path / "src.h5")
    if strings == "variable":
        vlen_strings(src)
    blocks = metadata_blocks(src)
    assert len(blocks) >= 15
    seen = set()
    for pos, sig in blocks:
        arc = copy(src, tmp_path / f"m{pos}.h5")
        data = bytearray(arc.read_bytes())
        data[pos + 9] ^= 0x40
        arc.write_bytes(bytes(data))
        for cmd, extra in (
            ("info", []),
            ("validate", []),
            ("slice", ["--size", "50", "-o", tmp_path / "o.ply"]),
            ("evaluate", ["--json", tmp_path / "o.json"]),
        ):
            rc, out, err = run(capsys, cmd, arc, *extra)
            if rc == 0:  # a block this command does not read: the command did its job
                for o in (tmp_path / "o.ply", tmp_path / "o.json"):
                    o.unlink(missing_ok=True)
                continue
            lines = err.splitlines()
            assert rc in (1, 2) and lines, (sig, rc, err)
            if rc == 2:
                assert len(lines) == 1 and str(arc) in lines[0], (sig, err)
                assert re.search(r"damaged|cannot be opened as an HDF5 archive", lines[0]), (
                    sig,
                    err,
                )
                seen.add(re.sub(r"\d+", "#", lines[0].split("(", 1)[-1]))
            else:  # validate lists what it found
                assert cmd == "validate" and all(
                    x.startswith("lodbuilder validate: ") for x in lines
                )
        assert not (tmp_path / "o.ply").exists() and not (tmp_path / "o.json").exists()
    # the h5py failures of the finding, now one line each
    joined = " ".join(seen)
    for text in ("incorrect metadata checksum",):
        assert text in joined, seen


def test_damaged_scan_header_names_the_hdf5_failure(arc, capsys):
    with h5py.File(arc, "r") as f:
        addr = h5py.h5o.get_info(f[f"scans/{SCAN}"].id).addr
    data = bytearray(arc.read_bytes())
    data[addr + 9] ^= 0x40
    arc.write_bytes(bytes(data))
    msg = one_error(capsys, "info", arc)
    assert msg == (
        f"archive {arc} is damaged: HDF5 cannot read its metadata (Unable to synchronously open "
        f"object (incorrect metadata checksum after all read attempts)){REBUILD}"
    )
    with pytest.raises(CorruptArchiveError, match="incorrect metadata checksum"):
        lodbuilder.open_archive(arc)


def test_truncated_archive(arc, capsys):
    data = arc.read_bytes()
    arc.write_bytes(data[: len(data) * 2 // 3])
    msg = one_error(capsys, "info", arc)
    assert msg.startswith(f"{arc} cannot be opened as an HDF5 archive: ")
    assert "truncated file" in msg


def test_h5_errors_converts_only_what_h5py_raises(arc):
    from lodbuilder.archive.safety import h5_errors

    with h5py.File(arc, "r") as f:
        with pytest.raises(CorruptArchiveError) as err, h5_errors(arc, "its scans"):
            f["scans/nothing-here"]
        assert str(err.value) == (
            f"archive {arc} is damaged: HDF5 cannot read its scans (Unable to synchronously open "
            f"object (object 'nothing-here' doesn't exist)){REBUILD}"
        )
        with pytest.raises(ZeroDivisionError), h5_errors(arc):
            raise ZeroDivisionError("ours")  # our own bugs are not disguised as damage


# --- findings 5 and 6: structure and values ------------------------------------------------


def _add_ordering(g, order=None):
    og = g["orderings"].create_group("w")
    L.create_dataset(og, "order", np.arange(N, dtype=np.int64) if order is None else order)
    L.create_dataset(og, "radius", g["radius"][:])
    L.create_dataset(og, "parent", g["parent"][:])
    og.attrs["parameters"] = "{}"
    og.attrs["n_ordered"] = np.int64(N)


def _int_points(g, f):
    pts = g["points"][:]
    rewrite(g, "points", np.rint(pts * 1000).astype(np.int32))
    g.attrs["coordinate_encoding"] = "int32"


def _compound_points(g, f):
    pts = g["points"][:]
    rec = np.zeros(N, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    rec["x"], rec["y"], rec["z"] = pts.T
    rewrite(g, "points", rec)


def _declare(g, rel, shape, chunks):
    del g[rel]
    g.create_dataset(rel, shape=shape, chunks=chunks, dtype=np.float64)


def _column(rel, fn):
    def edit_fn(g, f):
        arr = g[rel][:]
        fn(arr)
        rewrite(g, rel, arr)

    return edit_fn


def _set(i, value):
    def fn(arr):
        arr[i] = value

    return fn


def _all_inf(g, f):
    r = np.full(N, np.inf)
    rewrite(g, "radius", r)
    rewrite(g, "radius_index", r[:: L.RADIUS_INDEX_STEP].copy())


def _attr(key, value):
    def edit_fn(g, f):
        g.attrs[key] = value

    return edit_fn


S = f"scan '{SCAN}'"
SIZE = ["--size", "10"]
# name: (edit(g, f), message after "archive A is damaged: " (A replaced), slice options, commands)
CASES = {
    "hard-link cycle": (
        lambda g, f: g.__setitem__("loop", g),
        f"'/scans/{SCAN}/loop' links again to '/scans/{SCAN}' (a hard-link cycle or a shared object)",
        SIZE,
        "isv",
    ),
    "soft-link loop": (
        lambda g, f: (
            g.__setitem__("a", h5py.SoftLink(f"/scans/{SCAN}/b")),
            g.__setitem__("b", h5py.SoftLink(f"/scans/{SCAN}/a")),
        ),
        f"'/scans/{SCAN}/a' is a soft link to '/scans/{SCAN}/b' (archives hold only hard links)",
        SIZE,
        "isv",
    ),
    "dangling link": (
        lambda g, f: (g.__delitem__("points"), g.__setitem__("points", h5py.SoftLink("/nowhere"))),
        f"'/scans/{SCAN}/points' is a soft link to '/nowhere' (archives hold only hard links)",
        SIZE,
        "isv",
    ),
    "compound points": (
        _compound_points,
        f"{S} dataset 'points' has shape (300,) and dtype dtype([('x', '<f4'), ('y', '<f4'), "
        "('z', '<f4')]), expected (300, 3) float32",
        SIZE,
        "isve",
    ),
    "n_points is a word": (
        _attr("n_points", "many"),
        f"{S} attribute n_points is 'many', not an integer",
        SIZE,
        "isve",
    ),
    "10^12 declared rows": (
        lambda g, f: _declare(g, "radius", (10**12,), (65536,)),
        "dataset '/scans/wavy/radius' declares shape (1000000000000,) (8000000000000 bytes), more "
        "than a {size}-byte file can hold",
        SIZE,
        "isve",
    ),
    "rows never written": (
        lambda g, f: _declare(g, "radius", (N,), (32,)),
        "dataset '/scans/wavy/radius' declares shape (300,) but only 0 of its 10 chunks are stored",
        SIZE,
        "isve",
    ),
    "no points": (
        lambda g, f: g.__delitem__("points"),
        f"{S} has no dataset 'points'",
        SIZE,
        "isve",
    ),
    "no radius": (
        lambda g, f: g.__delitem__("radius"),
        f"{S} has no dataset 'radius'",
        SIZE,
        "isve",
    ),
    "radius shorter than points": (
        lambda g, f: rewrite(g, "radius", g["radius"][:-1]),
        f"{S} dataset 'radius' has shape (299,), expected (300,)",
        SIZE,
        "isve",
    ),
    "attribute shorter than points": (
        lambda g, f: rewrite(g, "attributes/intensity", g["attributes/intensity"][:-5]),
        f"{S} dataset 'attributes/intensity' has shape (295,), expected (300,)",
        SIZE,
        "isve",
    ),
    "integer coordinates without a scale": (
        _int_points,
        f"{S} has int32 coordinates without offset and scale attributes",
        SIZE,
        "isve",
    ),
    "n_ordered=0": (
        _attr("n_ordered", np.int64(0)),
        f"{S} has n_ordered=0; it must be in [1, n_points=300]",
        SIZE,
        "isve",
    ),
    "radius_index_step=0": (
        _attr("radius_index_step", np.int64(0)),
        f"{S} has radius_index_step=0; it must be a positive integer",
        ["--rho", "0.05"],
        "isve",
    ),
    "invalid JSON in build": (
        _attr("build", "{not json"),
        f"{S} attribute 'build' is not valid JSON (Expecting property name enclosed in double "
        "quotes: line 1 column 2 (char 1))",
        SIZE,
        "i",
    ),
    "invalid JSON in provenance": (
        _attr("provenance", '{"a": 1'),
        f"{S} attribute 'provenance' is not valid JSON (Expecting ',' delimiter: line 1 column 8 "
        "(char 7))",
        SIZE,
        "i",
    ),
    "20 MB of non-JSON provenance": (
        _attr("provenance", "x" * 20_000_000),
        f"{S} attribute 'provenance' is not valid JSON (Expecting value: line 1 column 1 (char 0))",
        SIZE,
        "i",
    ),
    "NaN point": (
        _column("points", _set(5, np.nan)),
        f"{S} has a NaN or inf coordinate at stored position 5",
        SIZE,
        "sve",
    ),
    "moved point": (
        _column("points", _set(3, [5.0, 5.0, 5.0])),
        f"{S} has point 3 at [5.0, 5.0, 5.0], outside its bounds {{lo}} .. {{hi}}",
        SIZE,
        "sve",
    ),
    "increasing radius": (
        _column("radius", _set(11, 0.9)),
        f"{S} dataset 'radius' increases at row 11 ({{r10}} -> 0.9); radii must be non-increasing",
        ["--size", "50"],
        "isve",
    ),
    "NaN radius": (
        _column("radius", _set(10, np.nan)),
        f"{S} dataset 'radius' holds NaN at row 10",
        ["--size", "50"],
        "isve",
    ),
    "all-inf radius": (
        _all_inf,
        f"{S} dataset 'radius' is inf at row 1 but its parent is 0; only roots (parent -1) have "
        "radius inf",
        ["--rho", "0.05"],
        "isve",
    ),
    "radius index that disagrees": (
        _column("radius_index", _set(0, 1e-9)),
        f"{S} dataset 'radius_index' does not match 'radius': the level for rho=0.05 came out "
        "with 1 points",
        ["--rho", "0.05"],
        "s",
    ),
    "source index twice": (
        _column("source_index", lambda arr: arr.__setitem__(5, arr[4])),
        f"{S} dataset 'source_index' holds the same position twice",
        SIZE,
        "s",
    ),
    "parent later than its child": (
        _column("parent", _set(5, 7)),
        f"{S} dataset 'parent' gives row 5 the parent 7; parents come earlier",
        SIZE,
        "v",
    ),
    "ordering index out of range": (
        lambda g, f: _add_ordering(g, np.r_[np.arange(N - 1), 10**6].astype(np.int64)),
        f"{S} dataset 'orderings/w/order' holds 1000000, outside [0, 300)",
        ["--size", str(N), "--ordering", "w"],
        "sv",
    ),
    "ordering position twice": (
        lambda g, f: _add_ordering(g, np.r_[0, 1, 2, 3, 4, 4, np.arange(6, N)].astype(np.int64)),
        f"{S} dataset 'orderings/w/order' holds the same position twice",
        ["--size", "20", "--ordering", "w"],
        "sv",
    ),
    "negative ordering position": (
        lambda g, f: _add_ordering(g, np.r_[0, 1, 2, 3, 4, -5, np.arange(6, N)].astype(np.int64)),
        f"{S} dataset 'orderings/w/order' holds -5, outside [0, 300)",
        ["--size", "20", "--ordering", "w"],
        "sv",
    ),
}
COMMANDS = {"i": "info", "s": "slice", "v": "view", "e": "evaluate"}


def _argv(cmd, arc, d, slice_opts):
    ordering = slice_opts[slice_opts.index("--ordering") :] if "--ordering" in slice_opts else []
    return {
        "info": ["info", arc],
        "slice": ["slice", arc, *slice_opts, "--extra", "-o", d / "o.csv"],
        "view": ["view", arc, *ordering, "--screenshot", d / "o.png"],
        "evaluate": ["evaluate", arc, "--json", d / "o.json"],
    }[cmd]


def _expected(arc, base, detail):
    with h5py.File(base, "r") as f:
        g = f[f"scans/{SCAN}"]
        lo, hi = g.attrs["bounds_min"].tolist(), g.attrs["bounds_max"].tolist()
        r10 = repr(float(g["radius"][10]))
    detail = detail.format(size=os.path.getsize(arc), lo=lo, hi=hi, r10=r10)
    return f"archive {arc} is damaged: {detail}{REBUILD}"


@pytest.mark.parametrize("case", list(CASES))
def test_wrong_archives_give_one_line_errors(base, tmp_path, capsys, case):
    fn, detail, slice_opts, cmds = CASES[case]
    arc = copy(base, tmp_path / "a.h5")
    edit(arc, fn)
    expected = _expected(arc, base, detail)
    before = sorted(os.listdir(tmp_path))
    for c in cmds:
        cmd = COMMANDS[c]
        assert one_error(capsys, cmd, *_argv(cmd, arc, tmp_path, slice_opts)[1:]) == expected, cmd
        assert sorted(os.listdir(tmp_path)) == before, cmd
    rc, out, err = run(capsys, "validate", arc)  # never a traceback: a fault list or one error
    assert (
        rc in (1, 2)
        and err
        and all(line.startswith("lodbuilder validate: ") for line in err.splitlines())
    )


def test_the_clean_copy_passes_every_command(base, tmp_path, capsys):
    """The cases above are edits of this archive, which every command accepts."""
    arc = copy(base, tmp_path / "a.h5")
    edit(arc, lambda g, f: _add_ordering(g))
    for cmd in ("info", "slice", "evaluate"):
        rc, out, err = run(capsys, *_argv(cmd, arc, tmp_path, ["--rho", "0.05"]))
        assert rc == 0, (cmd, err)
    rc, out, err = run(
        capsys, "slice", arc, "--size", "20", "--ordering", "w", "-o", tmp_path / "w.ply"
    )
    assert rc == 0, err
    rc, out, err = run(capsys, "validate", arc)
    assert rc == 0, err


def test_validate_flags_an_all_inf_radius(arc):
    edit(arc, _all_inf)
    faults = validate_archive(arc)
    assert (
        f"{S}: position 1 has radius inf and parent 0; radius is inf exactly for the roots (parent -1) (299 bad)"
        in faults
    )


@pytest.mark.parametrize(
    "case",
    [
        "hard-link cycle",
        "soft-link loop",
        "compound points",
        "n_points is a word",
        "10^12 declared rows",
    ],
)
def test_validate_does_not_crash(base, tmp_path, capsys, case):
    """Finding 5: validate itself crashed on these (RecursionError, TypeError, 7 TiB allocation)."""
    import resource

    arc = copy(base, tmp_path / "a.h5")
    edit(arc, CASES[case][0])
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rc, out, err = run(capsys, "validate", arc)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 200_000  # KiB
    expected = _expected(arc, base, CASES[case][1])
    if rc == 2:
        assert err.splitlines() == [f"lodbuilder validate: error: {expected}"]
    else:
        assert (
            rc == 1
            and f"lodbuilder validate: {arc}: {S}: cannot be checked: {expected}"
            in err.splitlines()
        )


def test_a_scan_member_that_is_a_dataset(arc, capsys):
    def swap(g, f):
        del f["scans"][SCAN]
        f["scans"].create_dataset(SCAN, data=np.zeros(3))

    edit(arc, swap)
    assert one_error(capsys, "info", arc) == (
        f"archive {arc}: it does not hold scan {SCAN!r} (no group /scans/{SCAN}); the index is "
        "damaged or crafted"
    )


def test_representatives_cannot_loop_on_cyclic_parents(arc):
    """Pointer doubling over parents that form a cycle never ends; parents are checked first."""
    edit(arc, _column("parent", _set(5, 7)))
    with (
        lodbuilder.open_archive(arc) as a,
        pytest.raises(CorruptArchiveError, match="parents come earlier"),
    ):
        a.scan().representatives(3)
