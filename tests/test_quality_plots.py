"""Quality plots: a PNG with both panels, written atomically; matplotlib only when plotting."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from lodbuilder.errors import InputError
from lodbuilder.quality import evaluate_prefixes


def test_plot_quality_writes_png(tmp_path, rng):
    from PIL import Image

    from lodbuilder import euclidean_fps
    from lodbuilder.quality.plots import plot_quality

    pts = rng.random((800, 3)) * np.array([1.0, 1.0, 0.1])
    o = euclidean_fps(pts)
    reps = evaluate_prefixes(pts, o.order, o.radius, sizes=[8, 40, 200, 800])
    out = plot_quality(reps, tmp_path / "q.png", radius=o.radius, title="random slab")
    img = np.asarray(Image.open(out).convert("L"), dtype=float)
    assert img.shape[1] > img.shape[0]  # two panels side by side
    assert img.std() > 5  # not a blank page
    assert [p.name for p in tmp_path.iterdir()] == ["q.png"]  # no temp file left behind
    one = plot_quality(reps, tmp_path / "one.png")
    assert np.asarray(Image.open(one)).shape[1] < img.shape[1]


def test_plot_quality_rejects_bad_output(tmp_path):
    from lodbuilder.quality.plots import plot_quality

    with pytest.raises(InputError, match=r"plot output .*q\.jpg must end in \.png"):
        plot_quality([], tmp_path / "q.jpg")
    with pytest.raises(InputError, match="no level to plot"):
        plot_quality([], tmp_path / "q.png")


def test_quality_import_is_light():
    code = (
        "import sys, lodbuilder.quality; "
        "bad = [m for m in ('matplotlib', 'pyvista', 'numba', 'dask') if m in sys.modules]; "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


def test_plot_axes_name_the_unit(tmp_path, rng, monkeypatch):
    import matplotlib.pyplot as plt

    from lodbuilder import euclidean_fps
    from lodbuilder.quality.plots import plot_quality

    figures = []
    close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig: (figures.append(fig), close(fig)))
    pts = rng.random((300, 3))
    o = euclidean_fps(pts)
    reps = evaluate_prefixes(pts, o.order, o.radius, sizes=[10, 100])
    plot_quality(reps, tmp_path / "m.png", radius=o.radius, units="metre")
    plot_quality(reps, tmp_path / "u.png", radius=o.radius)
    labels = [[(ax.get_xlabel(), ax.get_ylabel()) for ax in fig.axes] for fig in figures]
    assert labels[0] == [
        ("level size (points)", "distance (metre)"),
        ("rank (position in the ordering, 1-based)", "insertion radius (metre)"),
    ]
    assert labels[1][0][1] == "distance (scan units)"
    assert labels[1][1][1] == "insertion radius (scan units)"
