#!/usr/bin/python3
"""VTK's piecewise-linear answers on a volume mesh written by `lsqsurf-volume-bench --write`, in
the same run as ours: linear interpolation at random points (vtkProbeFilter), the linear
isosurface (vtkContour3DLinearGrid) and its first-order distance to the true level, and 512²
frames of the Bunyk ray caster (vtkUnstructuredGridVolumeRayCastMapper) on Mesa.

Needs Debian's python3-vtk9, python3-numpy and xvfb (VTK 9.1 there renders through X):
    xvfb-run -s '-screen 0 1024x1024x24' bench/vtk_volume_reference.py MESH.vtk {franke|ml}
Bench-only: nothing in the product or the tests depends on it."""
import math
import sys
import time

import numpy as np
import vtk
from vtkmodules.util import numpy_support


def franke(p):
    x, y, z = 9 * p[:, 0], 9 * p[:, 1], 9 * p[:, 2]
    return (0.75 * np.exp(-((x - 2) ** 2 + (y - 2) ** 2 + (z - 2) ** 2) / 4)
            + 0.75 * np.exp(-(x + 1) ** 2 / 49 - (y + 1) / 10 - (z + 1) / 10)
            + 0.5 * np.exp(-((x - 7) ** 2 + (y - 3) ** 2 + (z - 5) ** 2) / 4)
            - 0.2 * np.exp(-(x - 4) ** 2 - (y - 7) ** 2 - (z - 5) ** 2))


def marschner_lobb(p):
    r = np.hypot(p[:, 0], p[:, 1])
    return (1 - np.sin(np.pi * p[:, 2] / 2) + 0.25 * (1 + np.cos(2 * np.pi * 6 * np.cos(np.pi * r / 2)))) / 2.5


def gradient(f, p, h=1e-6):
    g = np.zeros_like(p)
    for a in range(3):
        d = np.zeros(3)
        d[a] = h
        g[:, a] = (f(p + d) - f(p - d)) / (2 * h)
    return g


def main():
    path, case = sys.argv[1], sys.argv[2]
    f, name, lo, hi, iso = ((franke, "franke", 0.0, 1.0, 0.35) if case == "franke"
                            else (marschner_lobb, "marschner_lobb", -1.0, 1.0, 0.5))
    reader = vtk.vtkUnstructuredGridReader()
    reader.SetFileName(path)
    reader.Update()
    grid = reader.GetOutput()
    grid.GetPointData().SetActiveScalars(name)
    print(f"{path}: {grid.GetNumberOfPoints()} points, {grid.GetNumberOfCells()} cells")

    # Linear interpolation at 1M random points inside the middle 80 % of the box.
    rng = np.random.default_rng(17)
    span = hi - lo
    pts = lo + 0.1 * span + 0.8 * span * rng.random((1_000_000, 3))
    probe_points = vtk.vtkPolyData()
    vp = vtk.vtkPoints()
    vp.SetData(numpy_support.numpy_to_vtk(pts, deep=True))
    probe_points.SetPoints(vp)
    probe = vtk.vtkProbeFilter()
    probe.SetInputData(probe_points)
    probe.SetSourceData(grid)
    start = time.perf_counter()
    probe.Update()
    seconds = time.perf_counter() - start
    values = numpy_support.vtk_to_numpy(probe.GetOutput().GetPointData().GetArray(name))
    err = values - f(pts)
    print(f"  linear interpolation (vtkProbeFilter): 1M points in {seconds:.2f} s, RMS {np.sqrt(np.mean(err ** 2)):.3g}"
          f" max {np.max(np.abs(err)):.3g}")

    contour = vtk.vtkContour3DLinearGrid()
    contour.SetInputData(grid)
    contour.SetValue(0, iso)
    contour.SetInputArrayToProcess(0, 0, 0, vtk.vtkDataObject.FIELD_ASSOCIATION_POINTS, name)
    start = time.perf_counter()
    contour.Update()
    seconds = time.perf_counter() - start
    v = numpy_support.vtk_to_numpy(contour.GetOutput().GetPoints().GetData()).astype(np.float64)
    d = np.abs(f(v) - iso) / np.linalg.norm(gradient(f, v), axis=1)
    print(f"  linear isosurface {iso} (vtkContour3DLinearGrid): {contour.GetOutput().GetNumberOfCells()} triangles in"
          f" {seconds * 1e3:.1f} ms, mean distance {d.mean():.3g} max {d.max():.3g}")

    # Bunyk ray casting, 512² frames.
    window = vtk.vtkRenderWindow()
    window.SetOffScreenRendering(1)
    window.SetSize(512, 512)
    renderer = vtk.vtkRenderer()
    window.AddRenderer(renderer)
    rng_lo, rng_hi = grid.GetPointData().GetArray(name).GetRange()
    color = vtk.vtkColorTransferFunction()
    color.AddRGBPoint(rng_lo, 0.2, 0.1, 0.5)
    color.AddRGBPoint(rng_hi, 1.0, 0.9, 0.2)
    opacity = vtk.vtkPiecewiseFunction()
    opacity.AddPoint(rng_lo, 0.0)
    opacity.AddPoint(rng_lo + 0.45 * (rng_hi - rng_lo), 0.0)
    opacity.AddPoint(rng_lo + 0.55 * (rng_hi - rng_lo), 0.3)
    opacity.AddPoint(rng_hi, 0.6)
    prop = vtk.vtkVolumeProperty()
    prop.SetColor(color)
    prop.SetScalarOpacity(opacity)
    prop.SetInterpolationTypeToLinear()
    mapper = vtk.vtkUnstructuredGridVolumeRayCastMapper()
    mapper.SetInputData(grid)
    volume = vtk.vtkVolume()
    volume.SetMapper(mapper)
    volume.SetProperty(prop)
    renderer.AddVolume(volume)
    renderer.ResetCamera()
    times = []
    for frame in range(4):
        renderer.GetActiveCamera().Azimuth(10)
        start = time.perf_counter()
        window.Render()
        times.append(time.perf_counter() - start)
    gl = [line.split(":", 1)[1].strip() for line in window.ReportCapabilities().splitlines()
          if line.startswith("OpenGL renderer string")]
    print(f"  512² Bunyk frames ({gl[0] if gl else 'unknown GL'}): first {times[0]:.2f} s,"
          f" then {', '.join(f'{t:.2f}' for t in times[1:])} s")


if __name__ == "__main__":
    main()
