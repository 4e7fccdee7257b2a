"""The README's pictures of gap filling: a scan with holes, its level, the filled level.

    python tools/fill_pictures.py --out docs/img            # bun_zipper.ply, rho 2 mm, seed 3

Holes are punched as in tools/bench_fill.py (every point inside balls of radius 3-5 rho removed);
the archive is built, the level at rho sliced and filled, and the three are rendered side by side
off screen (PyVista; set VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow without a display).
The punched scan is drawn as its mesh (the faces whose corners all survive), under the points of
the level; measured points are blue, synthetic points red. Writes fill_bunny.png, and
fill_limits.png: a *synthetic* flat patch with the four cases of what is and is not filled.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_fill import build, punch
from scipy.spatial import cKDTree

HERE = Path(__file__).resolve().parent


def render(panels, out: Path, camera, surface=None, size=(1500, 500)) -> Path:
    """Panels side by side, cameras linked: each a title and layers of (points, colour, size);
    ``surface`` (a mesh of the punched scan) is drawn under every panel, culling back faces so
    that a hole shows as a hole."""
    import pyvista as pv

    pl = pv.Plotter(off_screen=True, shape=(1, len(panels)), window_size=list(size), border=False)
    pl.set_background("white")
    for i, (title, layers, shade) in enumerate(panels):
        pl.subplot(0, i)
        if surface is not None:
            actor = pl.add_mesh(surface, color=shade, smooth_shading=True)
            actor.prop.backface_culling = True
        for pts, colour, px in layers:
            if len(pts):
                pl.add_points(
                    np.ascontiguousarray(pts),
                    color=colour,
                    point_size=px,
                    render_points_as_spheres=True,
                )
        pl.add_text(title, position="upper_edge", font_size=11, color="black")
        pl.camera_position = camera
    pl.link_views()
    pl.render()
    pl.screenshot(str(out))
    pl.close()
    small_png(out)
    return out


def small_png(path: Path) -> None:
    """Rewrite a PNG with a 256-colour palette (a third of the bytes, no visible change)."""
    from PIL import Image

    Image.open(path).convert("RGB").quantize(256).save(path, optimize=True)


def punched_mesh(path: Path, keep: np.ndarray):
    """The scan's mesh without the faces that touch a removed point (None without faces)."""
    import pyvista as pv

    mesh = pv.read(str(path))
    if not mesh.n_cells:
        return None
    faces = mesh.faces.reshape(-1, 4)[:, 1:]
    ok = keep[faces].all(axis=1)
    out = pv.PolyData(mesh.points, np.c_[np.full(ok.sum(), 3), faces[ok]].ravel())
    return out.clean()


def outward_normals(path: Path) -> np.ndarray:
    """Per point outward normals of the scan: its mesh's, consistently oriented, when the PLY has
    faces; else PCA normals turned away from the scan's centre."""
    import pyvista as pv

    mesh = pv.read(str(path))
    if mesh.n_cells:
        mesh = mesh.compute_normals(consistent_normals=True, auto_orient_normals=True)
        return np.asarray(mesh.point_data["Normals"], dtype=np.float64)
    from lodbuilder.features.geometry import pca_normals

    pts = np.asarray(mesh.points, dtype=np.float64)
    n = pca_normals(pts, k=16)
    n[np.einsum("ij,ij->i", n, pts - pts.mean(axis=0)) < 0] *= -1.0
    return n


def view_direction(hole_normals: np.ndarray) -> np.ndarray:
    """Of 12 directions around the y axis (up; 20 degrees above the horizon), the one that faces
    most punched holes (their outward normal within 60 degrees of it)."""
    hole_n = hole_normals
    el = np.radians(20.0)
    best, best_n = np.array([0.0, np.sin(el), np.cos(el)]), -1
    for az in np.radians(np.arange(0, 360, 30)):
        d = np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
        n = int((hole_n @ d > 0.5).sum())
        if n > best_n:
            best, best_n = d, n
    return best


def limits_picture(out: Path, work: Path) -> str:
    """What is filled and what is not, on a *synthetic* flat patch seen from above: an enclosed
    hole (filled), a bite out of the border (open), a hole wider than 12 rho (open) and a hole
    whose rim lies partly on a plate 3 rho above the patch (rough: its rim lies at two depths,
    like an occlusion shadow's). Writes fill_limits.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import lodbuilder
    from lodbuilder.fill import SYNTHETIC, fill_level

    rho = 0.03
    rng = np.random.default_rng(4)
    side = 300
    g = np.stack(np.meshgrid(np.arange(2 * side), np.arange(side)), -1).reshape(-1, 2).astype(float)
    g = (g + rng.uniform(-0.3, 0.3, g.shape)) / side  # a jittered grid on [0, 2] x [0, 1]
    holes = {
        "filled": ((0.3, 0.5), 4 * rho),
        "open: it reaches\nthe scan's border": ((0.75, 0.0), 5 * rho),
        "open: wider\nthan 12 rho": ((1.1, 0.55), 8 * rho),
        "rough: part of its rim\nlies on a plate\n3 rho above": ((1.65, 0.5), 4 * rho),
    }
    keep = np.ones(len(g), dtype=bool)
    for c, r in holes.values():
        keep &= np.hypot(g[:, 0] - c[0], g[:, 1] - c[1]) > r
    # a plate 3 rho above the patch, over the upper part of the last hole
    on_plate = (g[:, 0] > 1.5) & (g[:, 0] < 1.95) & (g[:, 1] > 0.58) & (g[:, 1] < 0.95)
    pts = np.r_[
        np.c_[g[keep], np.zeros(keep.sum())], np.c_[g[on_plate], np.full(on_plate.sum(), 3 * rho)]
    ]
    path = work / "limits.h5"
    build(pts, {}, "patch", path)
    with lodbuilder.open_archive(path) as arc:
        filled = fill_level(arc.scan(), rho)
    lev = filled.level
    syn = lev.attributes[SYNTHETIC] == 1
    plate = lev.points[:, 2] > rho
    fig, ax = plt.subplots(figsize=(10, 5.2), dpi=100)
    ax.scatter(*lev.points[~syn & ~plate, :2].T, s=4, c="#4a76a8", lw=0, label="level at rho")
    ax.add_patch(plt.Rectangle((1.5, 0.58), 0.45, 0.37, color="#cfe8c4", lw=0, zorder=0))
    ax.scatter(*lev.points[plate, :2].T, s=5, c="#38761d", lw=0, label="plate, 3 rho above")
    ax.scatter(*lev.points[syn, :2].T, s=10, c="#d62020", lw=0, label="synthetic")
    for text, (c, r) in holes.items():
        ax.add_patch(plt.Circle(c, r, fill=False, ls="--", lw=0.8, color="0.35"))
        y = c[1] + r + 0.03
        ax.text(
            c[0],
            y,
            text,
            ha="center",
            va="bottom",
            fontsize=9.5,
            bbox={"facecolor": "white", "edgecolor": "0.6", "boxstyle": "round,pad=0.3"},
        )
    ax.set_xlim(-0.03, 2.03)
    ax.set_ylim(-0.03, 1.03)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=3, fontsize=9, frameon=False)
    ax.set_title(
        f"a synthetic flat patch seen from above, rho = {rho:g}: what 'slice --fill' fills",
        fontsize=11,
    )
    fig.tight_layout()
    fig.savefig(out / "fill_limits.png")
    plt.close(fig)
    small_png(out / "fill_limits.png")
    return filled.report.table()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scan", default=str(HERE.parent.parent / "shared" / "data" / "bun_zipper.ply"))
    p.add_argument("--rho", type=float, default=0.002)
    p.add_argument("--holes", type=int, default=5)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--out", default="docs/img")
    args = p.parse_args(argv)
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import lodbuilder
    from lodbuilder.fill import SYNTHETIC, fill_level
    from lodbuilder.io import read_scan

    scan = read_scan(args.scan)
    keep, centres, _ = punch(scan.points, args.rho, args.holes, args.seed, radii=(3.0, 5.0))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "holes.h5"
        build(scan.points[keep], {}, scan.name, path)
        with lodbuilder.open_archive(path) as arc:
            view = arc.scan()
            level = view.level(rho=args.rho)
            filled = fill_level(view, args.rho)
            pts = view.points()
    lev = filled.level
    syn = lev.attributes[SYNTHETIC] == 1
    centre = pts.mean(axis=0)
    normals = outward_normals(Path(args.scan))
    tree = cKDTree(scan.points)
    eye_dir = view_direction(normals[tree.query(centres)[1]])
    diag = float(np.linalg.norm(np.ptp(pts, axis=0)))
    eye = centre + 1.9 * diag * eye_dir
    camera = [tuple(eye), tuple(centre), (0.0, 1.0, 0.0)]

    def front(p: np.ndarray) -> np.ndarray:
        """Points facing the camera (by their nearest scan point's normal): the far side, seen
        through a hole, is not drawn."""
        return np.einsum("ij,ij->i", normals[tree.query(p)[1]], eye - p) > 0

    surface = punched_mesh(Path(args.scan), keep)
    blue, red = "#4a76a8", "#d62020"
    panels = [
        (f"scan with holes: {len(pts):,} points", [] if surface else [(pts, blue, 2)], "#9db4cf"),
        (
            f"level at rho = {args.rho:g}: {level.size:,} points",
            [(level.points[front(level.points)], blue, 6)],
            "#e8e8e8",
        ),
        (
            f"filled: + {int(syn.sum())} synthetic points (red)",
            [
                (lev.points[~syn & front(lev.points)], blue, 6),
                (lev.points[syn & front(lev.points)], red, 7),
            ],
            "#e8e8e8",
        ),
    ]
    path = render(panels, out / "fill_bunny.png", camera, surface)
    print(f"wrote {path}: {filled.summary(len(pts))}")
    print(filled.report.table())
    with tempfile.TemporaryDirectory() as tmp:
        print(limits_picture(out, Path(tmp)))
    print(f"wrote {out / 'fill_limits.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
