"""Archives that point outside themselves are refused by every command before any data is read.

HDF5 can make a reader open other files in three ways: external raw storage (a dataset whose
bytes live in another file, e.g. /etc/passwd), external links (a member that is an object of
another HDF5 file) and virtual datasets (a dataset mapped from datasets of other files). Each is
refused with one line and exit 2, no output file, and the archive left as it was.
"""

from __future__ import annotations

import io
import os

import h5py
import numpy as np
import pytest
from hostile import (
    SCAN,
    copy,
    external_link,
    external_storage,
    foreign_file,
    make_archive,
    small_ply,
    virtual,
)

import lodbuilder
from lodbuilder.archive.writer import add_importance
from lodbuilder.cli.main import main
from lodbuilder.errors import UnsafeArchiveError

SECRET = b"root:x:0:0:SECRET-LINE-FROM-OUTSIDE-THE-ARCHIVE\n" * 20
REFUSE = "lodbuilder reads nothing outside an archive; rebuild it with 'lodbuilder build'"
INTENSITY = f"/scans/{SCAN}/attributes/intensity"


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return make_archive(tmp_path_factory.mktemp("base") / "base.h5")


def commands(arc, d):
    """(command, argv, output it would write) for every command that opens an archive."""
    return {
        "info": (["info", arc], None),
        "validate": (["validate", arc], None),
        "slice": (["slice", arc, "--size", "50", "--extra", "-o", d / "x.csv"], d / "x.csv"),
        "view": (["view", arc, "--screenshot", d / "x.png"], d / "x.png"),
        "evaluate": (["evaluate", arc, "--json", d / "x.json"], d / "x.json"),
        "build": (["build", d / "in.ply", "-o", arc, "--no-progress"], None),
        "export": (["export", arc, "--size", "50", "-o", d / "x.copc.laz"], d / "x.copc.laz"),
    }


def _hostile(kind, base, d):
    """The hostile archive of one kind and the exact refusal it must give."""
    arc = copy(base, d / "hostile.h5")
    secret = d / "secret.txt"
    secret.write_bytes(SECRET)
    foreign = foreign_file(d / "foreign.h5")
    if kind == "external storage":
        external_storage(arc, secret)
        why = f"dataset {INTENSITY!r} stores its data in external file {str(secret)!r}"
    elif kind == "external storage, relative name":
        external_storage(arc, "secret.txt")
        why = f"dataset {INTENSITY!r} stores its data in external file 'secret.txt'"
    elif kind == "external storage of the points":
        external_storage(arc, secret, f"scans/{SCAN}/points")
        why = f"dataset '/scans/{SCAN}/points' stores its data in external file {str(secret)!r}"
    elif kind == "external link to a dataset":
        external_link(arc, foreign, "/data", INTENSITY[1:])
        why = f"{INTENSITY!r} is an external link to '/data' in file {str(foreign)!r}"
    elif kind == "external link to a scan":
        external_link(arc, base, f"/scans/{SCAN}", "scans/other")
        why = f"'/scans/other' is an external link to '/scans/{SCAN}' in file {str(base)!r}"
    elif kind == "external link to a missing file":
        external_link(arc, d / "nowhere.h5", "/data", INTENSITY[1:])
        why = f"{INTENSITY!r} is an external link to '/data' in file {str(d / 'nowhere.h5')!r}"
    elif kind == "virtual dataset":
        virtual(arc, foreign, "data", INTENSITY[1:])
        why = f"dataset {INTENSITY!r} is a virtual dataset (its data lives in other files)"
    elif kind == "virtual dataset of the points":
        virtual(arc, foreign, "points", f"scans/{SCAN}/points")
        why = f"dataset '/scans/{SCAN}/points' is a virtual dataset (its data lives in other files)"
    elif kind == "virtual dataset of the archive itself":
        virtual(arc, ".", f"/scans/{SCAN}/attributes/red", INTENSITY[1:])
        why = f"dataset {INTENSITY!r} is a virtual dataset (its data lives in other files)"
    else:  # pragma: no cover
        raise AssertionError(kind)
    return arc, f"archive {arc} is refused: {why}; {REFUSE}"


KINDS = [
    "external storage",
    "external storage, relative name",
    "external storage of the points",
    "external link to a dataset",
    "external link to a scan",
    "external link to a missing file",
    "virtual dataset",
    "virtual dataset of the points",
    "virtual dataset of the archive itself",
]


@pytest.mark.parametrize(
    "cmd", ["info", "validate", "slice", "view", "evaluate", "build", "export"]
)
@pytest.mark.parametrize("kind", KINDS)
def test_every_command_refuses(base, tmp_path, capsys, monkeypatch, kind, cmd):
    arc, message = _hostile(kind, base, tmp_path)
    small_ply(tmp_path / "in.ply")
    before = arc.read_bytes()
    listing = sorted(os.listdir(tmp_path))
    argv, out = commands(arc, tmp_path)[cmd]
    monkeypatch.chdir(tmp_path)  # a relative external name would resolve here
    rc = main([str(a) for a in argv])
    stdout, err = capsys.readouterr()
    assert rc == 2, (rc, stdout, err)
    assert err.splitlines() == [f"lodbuilder {cmd}: error: {message}"]
    assert "SECRET" not in stdout + err
    assert out is None or not out.exists()
    assert sorted(os.listdir(tmp_path)) == listing  # nothing written, not even a temporary
    assert arc.read_bytes() == before


def test_the_secret_really_is_reachable_through_plain_h5py(base, tmp_path, monkeypatch):
    """The hostile archive is what the finding says: plain h5py reads the foreign bytes."""
    arc, _ = _hostile("external storage", base, tmp_path)
    monkeypatch.chdir(tmp_path)
    with h5py.File(arc, "r") as f:
        assert SECRET[:40] in f[INTENSITY][()].tobytes()


def test_refused_before_anything_is_read(base, tmp_path, monkeypatch):
    """Reading the external file would fail differently (it is a directory): the refusal comes
    from the metadata alone."""
    arc = copy(base, tmp_path / "hostile.h5")
    (tmp_path / "dir").mkdir()
    external_storage(arc, tmp_path / "dir")
    with pytest.raises(UnsafeArchiveError, match="stores its data in external file"):
        lodbuilder.open_archive(arc)


def test_api_refuses_and_adding_to_it_is_refused(base, tmp_path):
    arc, message = _hostile("external link to a dataset", base, tmp_path)
    before = arc.read_bytes()
    with pytest.raises(UnsafeArchiveError) as err:
        lodbuilder.open_archive(arc)
    assert str(err.value) == message
    with pytest.raises(UnsafeArchiveError):
        add_importance(arc, SCAN, "x", np.zeros(300))
    assert arc.read_bytes() == before


def test_a_name_with_a_newline_stays_on_one_line(base, tmp_path, capsys):
    arc = copy(base, tmp_path / "hostile.h5")
    external_storage(arc, "/tmp/evil\nlodbuilder info: fake second line")
    rc = main(["info", str(arc)])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.splitlines()) == 1
    assert "'/tmp/evil\\nlodbuilder info: fake second line'" in err


def test_collection_build_into_a_hostile_archive_is_refused(base, tmp_path, capsys):
    arc, message = _hostile("virtual dataset", base, tmp_path)
    a, b = small_ply(tmp_path / "a.ply"), small_ply(tmp_path / "b.ply")
    before = arc.read_bytes()
    rc = main(["build", str(a), str(b), "-o", str(arc), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and err.splitlines() == [f"lodbuilder build: error: {message}"]
    assert arc.read_bytes() == before


def test_slice_all_scans_refuses(base, tmp_path, capsys):
    arc, message = _hostile("external link to a scan", base, tmp_path)
    out = tmp_path / "all.ply"
    rc = main(["slice", str(arc), "--all-scans", "--rho", "0.1", "-o", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.splitlines() == [f"lodbuilder slice: error: {message}"]
    assert not out.exists()


@pytest.mark.parametrize("kind", ["external storage", "external link to a scan", "virtual dataset"])
def test_checks_work_on_file_objects(base, tmp_path, kind):
    """Remote archives are read through file objects (fsspec): the same refusal, naming the URL."""
    import fsspec

    from lodbuilder.archive.safety import check_file, open_h5

    arc, message = _hostile(kind, base, tmp_path)
    fs = fsspec.filesystem("memory")
    fs.pipe("/bucket/hostile.h5", arc.read_bytes())
    url = "memory://bucket/hostile.h5"
    with fs.open("/bucket/hostile.h5", "rb") as fobj:
        f = open_h5(fobj, url)
        try:
            with pytest.raises(UnsafeArchiveError) as err:
                check_file(f, url)
        finally:
            f.close()
    assert str(err.value) == message.replace(str(arc), url)
    assert check_file(open_h5(io.BytesIO(base.read_bytes()), "mem.h5"), "mem.h5") > 10


def test_a_looping_heap_is_refused_through_a_file_object(base, tmp_path):
    from hostile import vlen_strings

    from lodbuilder.archive.safety import open_h5
    from lodbuilder.errors import CorruptArchiveError

    data = bytearray(vlen_strings(copy(base, tmp_path / "old.h5")).read_bytes())
    at = data.index(b"GCOL")
    p = 16
    while int.from_bytes(data[at + p : at + p + 2], "little"):
        p += 16 + ((int.from_bytes(data[at + p + 8 : at + p + 16], "little") + 7) & ~7)
    data[at + p + 8 : at + p + 16] = bytes(8)  # the free space claims size 0
    f = open_h5(io.BytesIO(bytes(data)), "remote.h5")
    with pytest.raises(CorruptArchiveError, match="remote.h5 is damaged: its global heap at byte"):
        dict(f.attrs)
    f.close()
