#!/usr/bin/env python3
"""Writes a table-top room as one OBJ for the sensor simulator: spot, homer and the bunny
standing on a floor at different ranges, in front of a back wall. A depth camera's view of it
(lsqsurf-sensor-sim depth room.obj --eye 0,1.2,2.2 --up 0,1,0, with --quantum for a stereo
rig's steps) is a scene scan with floors seen at a slant, depth edges between objects and the
wall, and noise that grows with range: what a single view of a real room holds.

    python3 bench/room_scene.py room.obj [--meshes DIR]   (DIR: the shared meshes)
"""
import argparse
from pathlib import Path

import numpy as np

# (mesh, where its base's centre stands on the floor y = 0, its largest extent)
OBJECTS = [("spot.obj", (-0.6, 0.0, 0.2), 0.5), ("homer.obj", (0.1, 0.0, -0.5), 0.7),
           ("stanford-bunny.obj", (0.7, 0.0, 0.6), 0.45)]


def read_obj(path):
    vertices, faces = [], []
    for line in open(path):
        if line.startswith("v "):
            vertices.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            corners = [int(c.split("/")[0]) - 1 for c in line.split()[1:]]
            faces.extend([corners[0], corners[k], corners[k + 1]] for k in range(1, len(corners) - 1))
    return np.array(vertices), np.array(faces, dtype=np.int64)


def grid(origin, du, dv, cells):
    """A planar grid of 2 cells² triangles, facing du × dv."""
    steps = np.linspace(0, 1, cells + 1)
    vertices = np.array([origin + a * du + b * dv for a in steps for b in steps])
    faces = []
    for a in range(cells):
        for b in range(cells):
            v = a * (cells + 1) + b
            faces += [[v, v + cells + 1, v + 1], [v + 1, v + cells + 1, v + cells + 2]]
    return vertices, np.array(faces, dtype=np.int64)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("output")
    parser.add_argument("--meshes", default=str(Path(__file__).resolve().parents[1] / "../shared/data/meshes"))
    args = parser.parse_args()
    parts = []
    for name, base, size in OBJECTS:
        v, f = read_obj(Path(args.meshes) / name)
        lo, hi = v.min(0), v.max(0)
        v = (v - (lo + hi) / 2) * (size / (hi - lo).max())
        v[:, 1] -= v[:, 1].min()
        parts.append((v + np.array(base), f))
    floor_origin = np.array([-1.5, 0.0, -1.2])
    parts.append(grid(floor_origin, np.array([0, 0, 2.7]), np.array([3.0, 0, 0]), 30))  # Up.
    parts.append(grid(floor_origin, np.array([3.0, 0, 0]), np.array([0, 1.5, 0]), 30))  # Toward +z.
    with open(args.output, "w") as out:
        first = 0
        for v, _ in parts:
            out.writelines("v %.6f %.6f %.6f\n" % tuple(p) for p in v)
        for v, f in parts:
            out.writelines("f %d %d %d\n" % tuple(t + first + 1) for t in f)
            first += len(v)


if __name__ == "__main__":
    main()
