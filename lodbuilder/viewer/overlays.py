"""What the viewer draws besides the points: the scalar bar of a colour mode, the CRS label, and
the shading of points by their normals. Imports VTK (only the viewer imports this module).

Shading instead of eye-dome lighting: VTK's EDL pass multiplies every colour by a depth-edge
term that, on splats as wide as the level's spacing, is an edge almost everywhere (measured: the
mean RGB of a coloured level fell to 40-75 % of its brightness, 165 -> 67 on frag_115), and in a
two-pane window it blanks the pane rendered before it (pyvista issue #256), so it worked on one
pane only. Lighting the points with PCA normals of the scan is a plain actor property: it keeps
the colours' hue (ambient + diffuse = 1: a point facing the light keeps its colour), works on both
panes, and shows the shape the way a surface does.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from vtkmodules.vtkCommonCore import vtkLookupTable
from vtkmodules.vtkRenderingAnnotation import vtkScalarBarActor

from .data import Categories, Legend, colormap

#: lighting of shaded points: ambient + diffuse = 1 keeps a colour where the normal faces the light
AMBIENT, DIFFUSE = 0.35, 0.65
#: flip a normal to face the viewer (PCA normals have no orientation; points have no back face)
_FACE_VIEWER = (
    "//VTK::Normal::Impl\n"
    "  if (normalVCVSOutput.z < 0.0) { normalVCVSOutput = -normalVCVSOutput; }\n"
)


def lookup_table(legend: Legend) -> vtkLookupTable:
    """A VTK lookup table mapping values like :meth:`Legend.normalise` + :func:`colormap` do."""
    lut = vtkLookupTable()
    lut.SetNumberOfTableValues(256)
    lut.SetRange(legend.lo, legend.hi if legend.hi > legend.lo else legend.lo + 1.0)
    if legend.log:
        lut.SetScaleToLog10()
    lut.Build()
    rgb = colormap(np.linspace(0.0, 1.0, 256)) / 255.0
    for i, (r, g, b) in enumerate(rgb):
        lut.SetTableValue(i, float(r), float(g), float(b), 1.0)
    return lut


def scalar_bar() -> vtkScalarBarActor:
    """A vertical scalar bar at the right edge of its pane, black text, hidden until set."""
    bar = vtkScalarBarActor()
    bar.SetOrientationToVertical()
    bar.SetNumberOfLabels(5)
    bar.SetLabelFormat("%.3g")
    bar.SetUnconstrainedFontSize(True)
    bar.SetTextPositionToPrecedeScalarBar()
    pos = bar.GetPositionCoordinate()
    pos.SetCoordinateSystemToNormalizedViewport()
    pos.SetValue(0.70, 0.08)
    bar.SetWidth(0.29)
    bar.SetHeight(0.72)
    bar.SetBarRatio(0.12)
    bar.SetTitleRatio(0.25)
    bar.SetVerticalTitleSeparation(6)
    for prop in (bar.GetTitleTextProperty(), bar.GetLabelTextProperty()):
        prop.SetColor(0.0, 0.0, 0.0)
        prop.SetFontSize(11)
        prop.SetBold(False)
        prop.SetItalic(False)
        prop.SetShadow(False)
    bar.SetVisibility(False)
    return bar


def legend_box() -> Any:
    """A box of named colour swatches (categories) at the top right of its pane, hidden until
    set."""
    from vtkmodules.vtkRenderingAnnotation import vtkLegendBoxActor

    box = vtkLegendBoxActor()
    pos = box.GetPositionCoordinate()
    pos.SetCoordinateSystemToNormalizedViewport()
    box.SetBorder(True)
    box.SetBox(True)
    box.GetBoxProperty().SetColor(1.0, 1.0, 1.0)
    box.SetUseBackground(True)
    box.SetBackgroundColor(1.0, 1.0, 1.0)
    box.SetBackgroundOpacity(0.85)
    box.ScalarVisibilityOn()  # swatches take their own colours, the names the text's
    prop = box.GetEntryTextProperty()
    prop.SetColor(0.0, 0.0, 0.0)
    prop.SetFontSize(12)
    prop.SetBold(False)
    prop.SetItalic(False)
    prop.SetShadow(False)
    box.SetVisibility(False)
    return box


def _swatch(rgb: tuple[int, int, int] | None) -> Any:
    """A square coloured ``rgb`` by its own cell scalars (the entry's text stays black), or an
    empty symbol (None: the title line)."""
    from vtkmodules.vtkCommonCore import vtkUnsignedCharArray
    from vtkmodules.vtkCommonDataModel import vtkPolyData
    from vtkmodules.vtkFiltersSources import vtkRegularPolygonSource

    if rgb is None:
        return vtkPolyData()
    square = vtkRegularPolygonSource()
    square.SetNumberOfSides(4)
    square.Update()
    poly = square.GetOutput()
    colours = vtkUnsignedCharArray()
    colours.SetNumberOfComponents(3)
    for _ in range(poly.GetNumberOfCells()):
        colours.InsertNextTuple3(*rgb)
    poly.GetCellData().SetScalars(colours)
    return poly


def set_scalar_bar(bar: vtkScalarBarActor, legend: Legend | Categories | None,
                   box: Any = None) -> None:
    """Show ``legend`` on ``bar`` (a scale with a one-line title: titles are kept short, e.g.
    ``radius (foot, log)``), or categories as named swatches in ``box`` (the title first), or
    hide both (None: a mode without a legend)."""
    bar.SetVisibility(False)
    if box is not None:
        box.SetVisibility(False)
    if isinstance(legend, Categories):
        if box is None:
            return
        n = len(legend.values)
        box.SetNumberOfEntries(n + 1)
        box.SetEntry(0, _swatch(None), legend.title, (0.0, 0.0, 0.0))
        for i, (name, rgb) in enumerate(zip(legend.names, legend.colours, strict=True)):
            box.SetEntry(i + 1, _swatch(rgb), name, (0.0, 0.0, 0.0))
        height = min(0.9, 0.032 * (n + 1))
        width = min(0.3, 0.03 + 0.0085 * max(len(t) for t in (legend.title, *legend.names)))
        box.GetPositionCoordinate().SetValue(0.99 - width, 0.93 - height)
        box.GetPosition2Coordinate().SetCoordinateSystemToNormalizedViewport()
        box.GetPosition2Coordinate().SetValue(width, height)
        box.SetVisibility(True)
        return
    if legend is None:
        return
    bar.SetLookupTable(lookup_table(legend))
    bar.SetTitle(legend.title)
    bar.SetVisibility(True)


def set_shading(actor: Any, on: bool) -> None:
    """Light ``actor``'s points with the normals of its mesh (on), or draw them flat (off).

    VTK lights points only when the mesh has normals and the interpolation is not flat; the
    shader replacement turns each normal toward the viewer, and exists only while lit (the
    unlit shader has no normal to turn)."""
    prop = actor.GetProperty()
    shader = actor.GetShaderProperty()
    shader.ClearAllFragmentShaderReplacements()
    if on:
        prop.SetInterpolationToGouraud()
        prop.SetAmbient(AMBIENT)
        prop.SetDiffuse(DIFFUSE)
        prop.SetSpecular(0.0)
        shader.AddFragmentShaderReplacement("//VTK::Normal::Impl", True, _FACE_VIEWER, False)
    else:
        prop.SetInterpolationToFlat()
        prop.SetAmbient(0.0)
        prop.SetDiffuse(1.0)
