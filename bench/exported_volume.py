#!/usr/bin/python3
"""Writes a volume mesh of the unit cube as other tools hand one over, for the volume bench.

    bench/exported_volume.py --points 60000 --variant delaunay -o delaunay.vtk
    build/release/bin/lsqsurf-volume-bench --cases franke-tets --mesh delaunay.vtk

Variants (every one a legacy VTK UNSTRUCTURED_GRID without point data; the bench samples its
analytic field at the vertices):
  delaunay    SciPy's (Qhull's) Delaunay tetrahedralization of random points, the cube's corners
              among them: cells in either vertex order, slivers on the hull.
  duplicates  the same, written in 8 blocks (by cell centre octant) that each repeat the points
              they use, as multi-block exporters do, plus 1000 points in no cell.
  quadratic   the same with a node at every edge's midpoint (VTK's quadratic tetrahedron, 24).
  clean       the same tetrahedralization as a careful writer leaves it, the reference for the
              others: every cell in VTK's order, the hull's flat slivers left out.
Needs python3-scipy (scripts/install-deps.sh --with-scipy).
"""
import argparse

import numpy as np
from scipy.spatial import Delaunay


def write_vtk(path, points, cells, cell_type):
    with open(path, "w") as out:
        out.write("# vtk DataFile Version 4.2\nexported volume\nASCII\nDATASET UNSTRUCTURED_GRID\n")
        out.write(f"POINTS {len(points)} double\n")
        np.savetxt(out, points, fmt="%.17g")
        width = cells.shape[1]
        out.write(f"CELLS {len(cells)} {len(cells) * (width + 1)}\n")
        np.savetxt(out, np.hstack([np.full((len(cells), 1), width), cells]), fmt="%d")
        out.write(f"CELL_TYPES {len(cells)}\n")
        np.savetxt(out, np.full(len(cells), cell_type), fmt="%d")


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=60000)
    parser.add_argument("--variant", choices=["delaunay", "duplicates", "quadratic", "clean"], default="delaunay")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("-o", "--output", required=True)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float)
    points = np.vstack([corners, rng.random((args.points - 8, 3))])
    cells = Delaunay(points).simplices
    if args.variant == "delaunay":
        write_vtk(args.output, points, cells, 10)
    elif args.variant == "clean":
        p = points[cells]
        volume = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6
        longest = np.max([np.linalg.norm(p[:, a] - p[:, b], axis=1) for a in range(4) for b in range(a + 1, 4)], axis=0)
        cells = cells[np.abs(volume) > 1e-6 * longest ** 3]
        volume = volume[np.abs(volume) > 1e-6 * longest ** 3]
        cells[volume < 0] = cells[volume < 0][:, [0, 2, 1, 3]]
        write_vtk(args.output, points, cells, 10)
    elif args.variant == "duplicates":
        octant = ((points[cells].mean(axis=1) > 0.5) * [1, 2, 4]).sum(axis=1)
        block_points, block_cells, offset = [], [], 0
        for block in range(8):
            mine = cells[octant == block]
            used, local = np.unique(mine, return_inverse=True)
            block_points.append(points[used])
            block_cells.append(local.reshape(mine.shape) + offset)
            offset += len(used)
        block_points.append(rng.random((1000, 3)) + 2.0)
        write_vtk(args.output, np.vstack(block_points), np.vstack(block_cells), 10)
    else:
        edges = [(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)]
        pairs = np.sort(np.stack([cells[:, [a, b]] for a, b in edges], axis=1).reshape(-1, 2), axis=1)
        unique, index = np.unique(pairs, axis=0, return_inverse=True)
        midpoints = 0.5 * (points[unique[:, 0]] + points[unique[:, 1]])
        nodes = np.hstack([cells, index.reshape(-1, 6) + len(points)])
        write_vtk(args.output, np.vstack([points, midpoints]), nodes, 24)


if __name__ == "__main__":
    main()
