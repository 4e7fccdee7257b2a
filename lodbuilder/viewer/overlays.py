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

from .data import Legend, colormap

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
    pos.SetValue(0.84, 0.12)
    bar.SetWidth(0.14)
    bar.SetHeight(0.7)
    bar.SetBarRatio(0.25)
    for prop in (bar.GetTitleTextProperty(), bar.GetLabelTextProperty()):
        prop.SetColor(0.0, 0.0, 0.0)
        prop.SetFontSize(11)
        prop.SetBold(False)
        prop.SetItalic(False)
        prop.SetShadow(False)
    bar.SetVisibility(False)
    return bar


def set_scalar_bar(bar: vtkScalarBarActor, legend: Legend | None) -> None:
    """Show ``legend`` on ``bar``, or hide it (None: a mode without a scale)."""
    if legend is None:
        bar.SetVisibility(False)
        return
    bar.SetLookupTable(lookup_table(legend))
    bar.SetTitle(wrap_title(legend.title))
    bar.SetVisibility(True)


def wrap_title(title: str, width: int = 14) -> str:
    """Break a long title at spaces into lines of about ``width`` characters."""
    lines: list[str] = []
    for word in title.split():
        if lines and len(lines[-1]) + 1 + len(word) <= width:
            lines[-1] += " " + word
        else:
            lines.append(word)
    return "\n".join(lines)


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
