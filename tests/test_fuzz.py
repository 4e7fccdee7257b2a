"""A bounded, seeded run of tools/fuzz.py over the PLY, LAS/LAZ and archive readers.

Every mutant runs in a forked child with a time limit: no exception other than lodbuilder's
documented errors (one line each), no hang, no signal, and no archive level that differs from the
seed's without an error. The long campaign (>= 5,000 mutants per reader) is ``tools/fuzz.py``.
"""

from __future__ import annotations

import importlib.util
import os
import struct
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _load_fuzz():
    spec = importlib.util.spec_from_file_location("lodbuilder_fuzz", REPO / "tools" / "fuzz.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


fuzz = _load_fuzz()


@pytest.fixture(scope="module")
def seeds(shared_data, tmp_path_factory):
    return fuzz.make_seeds(tmp_path_factory.mktemp("seeds"))


@pytest.mark.data
@pytest.mark.parametrize("reader", fuzz.READERS)
def test_seeded_mutants_give_only_documented_errors(seeds, tmp_path, reader):
    res = fuzz.fuzz([reader], 40, seed=20261123, timeout=60, work=tmp_path, seeds=seeds)[reader]
    assert res["mutants"] == 40
    assert (res["traceback"], res["wrong"], res["hang"], res["signal"]) == (0, 0, 0, 0), res[
        "failures"
    ]
    assert res["ok"] + res["clean"] == 40
    assert res["clean"] > 0  # the mutants do reach the error paths


def test_the_runner_counts_hangs_signals_and_tracebacks():
    """The campaign's verdicts are real: a loop is a hang, an abort a signal, a KeyError a
    traceback, a lodbuilder error clean."""
    from lodbuilder.errors import FormatError

    def loop():
        while True:
            pass

    def boom():
        raise FormatError("bad file")

    assert fuzz.run_child(loop, 1.0) == "hang"
    assert fuzz.run_child(lambda: os.abort(), 10) == "signal: SIGABRT"
    assert fuzz.run_child(lambda: {}["x"], 10).startswith("traceback: KeyError at test_fuzz.py:")
    assert fuzz.run_child(boom, 10) == "clean: FormatError"
    assert fuzz.run_child(lambda: "ok", 10) == "ok"


def test_mutants_are_reproducible_from_the_seed():
    import random

    seed = b"ply\nformat ascii 1.0\nelement vertex 3\n" + bytes(range(256)) * 4
    a = [fuzz.mutate(seed, "ply_ascii", random.Random(5)) for _ in range(3)]
    b = [fuzz.mutate(seed, "ply_ascii", random.Random(5)) for _ in range(3)]
    assert a == b and any(m != seed for m in a)


@pytest.mark.data
def test_a_laz_chunk_table_larger_than_the_file_is_refused(shared_data, tmp_path):
    """Found by the fuzzer: a LAZ whose chunk table declares billions of chunks made lazrs abort
    the process (SIGABRT, 'memory allocation of 41000626336 bytes failed')."""
    import laspy

    laz = tmp_path / "bad.laz"
    laspy.read(str(shared_data / "simple.las")).write(str(laz))
    data = bytearray(laz.read_bytes())
    with open(laz, "rb") as f:
        start = laspy.LasHeader.read_from(f).offset_to_point_data
    at = struct.unpack("<q", data[start : start + 8])[0]
    data[at + 4 : at + 8] = struct.pack("<I", 0xF000_0000)
    laz.write_bytes(bytes(data))
    res = _read_in_child(laz)
    assert res.returncode == 1, res.stderr  # an exception, not an abort (-6)
    assert res.stderr.strip().splitlines()[-1] == (
        f"lodbuilder.errors.FormatError: {laz}: the LAZ chunk table declares 4026531840 chunks for "
        f"1065 points in {len(data)} bytes; the file is damaged"
    )


@pytest.mark.data
def test_a_laz_chunk_size_beyond_the_points_is_refused(shared_data, tmp_path):
    """Found by the fuzzer (1 of 5,000 LAZ mutants: one byte of the laszip VLR's chunk size, 50,000
    -> 2,130,756,432): lazrs' parallel decompressor allocated 72 GB for one chunk and aborted."""
    import laspy

    laz = tmp_path / "bad.laz"
    laspy.read(str(shared_data / "simple.las")).write(str(laz), laz_backend=laspy.LazBackend.Lazrs)
    data = bytearray(laz.read_bytes())
    vlr = data.find(b"laszip encoded") + 52  # the laszip VLR's record data (after its 54-byte header)
    assert struct.unpack_from("<I", data, vlr + 12)[0] == 50_000
    data[vlr + 15] = 127
    laz.write_bytes(bytes(data))
    res = _read_in_child(laz)
    assert res.returncode == 1, res.stderr  # an exception, not an abort (-6)
    assert res.stderr.strip().splitlines()[-1] == (
        f"lodbuilder.errors.FormatError: {laz}: the LAZ header declares chunks of 2130756432 points "
        "(67.5 GiB each) for 1065 points; the file is damaged"
    )


@pytest.mark.data
@pytest.mark.parametrize("streamed", [False, True])
def test_a_laz_whose_items_have_no_size_is_a_format_error(shared_data, tmp_path, streamed):
    """Found by the fuzzer (1 of 5,000 LAZ mutants): lazrs panics on a point size of 0 ('attempt to
    calculate the remainder with a divisor of zero'); pyo3's PanicException is a BaseException, so it
    escaped as a traceback from the whole-file and the streaming reader."""
    import laspy

    laz = tmp_path / "bad.laz"
    laspy.read(str(shared_data / "simple.las")).write(str(laz), laz_backend=laspy.LazBackend.Lazrs)
    data = bytearray(laz.read_bytes())
    vlr = data.find(b"laszip encoded") + 52  # the laszip VLR's record data (after its 54-byte header)
    for k in range(struct.unpack_from("<H", data, vlr + 32)[0]):
        struct.pack_into("<H", data, vlr + 34 + 6 * k + 2, 0)  # every item's size
    laz.write_bytes(bytes(data))
    if streamed:
        code = (f"from lodbuilder.io.stream import open_stream\n"
                f"for c in open_stream({str(laz)!r}).chunks(): pass\n")
        res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                             env={**os.environ, "PYTHONPATH": str(REPO)})
    else:
        res = _read_in_child(laz)
    assert res.returncode == 1, res.stderr
    assert res.stderr.strip().splitlines()[-1] == (
        f"lodbuilder.errors.FormatError: {laz}: cannot be read as LAS (attempt to calculate the "
        "remainder with a divisor of zero); check or re-export the file"
    )


@pytest.mark.parametrize(
    "prop,value,shown",
    [
        ("float", "1e308", "1e+308"),
        ("uchar", "300", "300.0"),
        ("uchar", "-1", "-1.0"),
        ("int", "1.5", "1.5"),
        ("uchar", "nan", "nan"),
    ],
)
def test_ascii_ply_values_that_do_not_fit_their_type(tmp_path, prop, value, shown):
    """Found by the fuzzer: ascii values beyond their property's type became inf (with a
    RuntimeWarning) or wrapped integers (300 -> 44) without an error."""
    from lodbuilder.errors import FormatError
    from lodbuilder.io import read_scan

    p = tmp_path / "v.ply"
    p.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        f"property float z\nproperty {prop} a\nend_header\n0 0 0 1\n1 1 1 {value}\n"
    )
    dt = {"float": "float32", "uchar": "uint8", "int": "int32"}[prop]
    with pytest.raises(FormatError) as err:
        read_scan(p)
    assert str(err.value) == (
        f"{p}: PLY vertex 1 has a = {shown}, which its type {dt} cannot hold; re-export the scan"
    )


def _read_in_child(path, timeout=120):
    code = f"from lodbuilder.io import read_scan\nread_scan({str(path)!r})\n"
    return subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=timeout,  # a regression fails here instead of hanging the suite
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )


@pytest.mark.data
@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_a_vlr_count_the_file_cannot_hold_is_refused(shared_data, tmp_path, suffix):
    """Found by the fuzzer: one byte of the VLR count changed made laspy read billions of empty
    VLRs past the end of the file (the process spun for ever, growing)."""
    import laspy

    bad = tmp_path / f"bad{suffix}"
    laspy.read(str(shared_data / "simple.las")).write(str(bad))
    data = bytearray(bad.read_bytes())
    n_vlrs = struct.unpack_from("<I", data, 100)[0]
    data[103] = 0xC2
    bad.write_bytes(bytes(data))
    with open(bad, "rb") as f:
        f.seek(94)
        header_size, offset = struct.unpack("<HI", f.read(6))
    res = _read_in_child(bad)
    assert res.returncode == 1, res.stderr
    assert res.stderr.strip().splitlines()[-1] == (
        f"lodbuilder.errors.FormatError: {bad}: the LAS header declares {n_vlrs + 0xC2000000} "
        f"VLRs but only {offset - header_size} bytes lie between the header and the points; the "
        "file is damaged"
    )
