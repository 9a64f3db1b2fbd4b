#!/usr/bin/python3
"""Writes the VTK-made volume fixtures of the io tests (needs Debian's python3-vtk9; run by
hand, not by the tests). One small unstructured grid with a hexahedron, a pyramid, a tetrahedron
and a wedge, point data temperature = 1 + x + 2y + 3z and velocity = (y, -x, z), written by
VTK's own writers in every encoding the readers accept."""
import os
import vtk

here = os.path.dirname(os.path.abspath(__file__))
points = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1),
          (0.5, 0.5, 2), (2, 0, 0), (2, 1, 0), (3, 0, 0), (2, 0, 1), (2, 1, 1), (3, 0, 1)]
cells = [(vtk.VTK_HEXAHEDRON, [0, 1, 2, 3, 4, 5, 6, 7]), (vtk.VTK_PYRAMID, [4, 5, 6, 7, 8]),
         (vtk.VTK_TETRA, [1, 9, 2, 5]), (vtk.VTK_WEDGE, [9, 10, 11, 12, 13, 14])]
grid = vtk.vtkUnstructuredGrid()
pts = vtk.vtkPoints()
temperature = vtk.vtkFloatArray()
temperature.SetName("temperature")
velocity = vtk.vtkDoubleArray()
velocity.SetName("velocity")
velocity.SetNumberOfComponents(3)
for x, y, z in points:
    pts.InsertNextPoint(x, y, z)
    temperature.InsertNextValue(1 + x + 2 * y + 3 * z)
    velocity.InsertNextTuple3(y, -x, z)
grid.SetPoints(pts)
for kind, ids in cells:
    grid.InsertNextCell(kind, len(ids), ids)
grid.GetPointData().AddArray(temperature)
grid.GetPointData().AddArray(velocity)

def xml(name, mode, compress, header64):
    w = vtk.vtkXMLUnstructuredGridWriter()
    w.SetFileName(os.path.join(here, name))
    w.SetInputData(grid)
    {"ascii": w.SetDataModeToAscii, "binary": w.SetDataModeToBinary, "appended": w.SetDataModeToAppended}[mode]()
    if mode == "appended":
        w.SetEncodeAppendedData(name.endswith("base64.vtu"))
    if compress:
        w.SetCompressorTypeToZLib()
    else:
        w.SetCompressorTypeToNone()
    w.SetHeaderTypeToUInt64() if header64 else w.SetHeaderTypeToUInt32()
    w.Write()

xml("mixed-ascii.vtu", "ascii", False, False)
xml("mixed-binary.vtu", "binary", False, False)
xml("mixed-binary-zlib.vtu", "binary", True, True)
xml("mixed-appended-zlib.vtu", "appended", True, True)
xml("mixed-appended-base64.vtu", "appended", False, False)
legacy = vtk.vtkUnstructuredGridWriter()
legacy.SetFileName(os.path.join(here, "mixed-binary.vtk"))
legacy.SetInputData(grid)
legacy.SetFileTypeToBinary()
legacy.Write()
