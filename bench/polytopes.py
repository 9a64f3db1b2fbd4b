#!/usr/bin/python3
"""Writes exact convex polytopes (flat faces, sharp edges and corners) for lsqsurf-bench --data DIR.

    bench/polytopes.py -o /tmp/poly
    build/release/bin/lsqsurf-bench --data /tmp/poly --models hull8 hull12 hull40 dodecahedron wedge pyramid \\
        --sizes 200000 --method pu --face-normals

  hullN         the convex hull of N random points on an ellipsoid (seeded): corners of 3 to 7
                faces, dihedral angles from nearly flat to acute. hull8 is flat, with ridges of
                27° to 33° and faces 2° apart.
  dodecahedron  the regular one: 20 corners of 3 faces at 116.6°.
  wedge         a triangular prism with a 20° ridge: the sharpest edge a support has to split.
  pyramid       a pentagonal pyramid with sides at 40° to its base: an apex of five faces and
                acute (50°) base edges and corners.
Needs python3-scipy and python3-numpy (scripts/install-deps.sh --with-scipy).
"""
import argparse
import os

import numpy as np
from scipy.spatial import ConvexHull


def write_hull(path, points):
    hull = ConvexHull(points)
    faces = hull.simplices.copy()
    # Qhull does not orient its facets: turn each one to face away from the centroid.
    centre = points[hull.vertices].mean(axis=0)
    a, b, c = (points[faces[:, k]] for k in range(3))
    outward = np.einsum("ij,ij->i", np.cross(b - a, c - a), a - centre) > 0
    faces[~outward] = faces[~outward][:, ::-1]
    used = np.unique(faces)
    remap = np.full(len(points), -1)
    remap[used] = np.arange(len(used))
    with open(path, "w") as out:
        np.savetxt(out, points[used], fmt="v %.12g %.12g %.12g")
        np.savetxt(out, remap[faces] + 1, fmt="f %d %d %d")


def random_hull(n, seed):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * np.array([0.5, 0.4, 0.3])


def dodecahedron():
    phi = (1 + 5 ** 0.5) / 2
    cube = [[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    rest = []
    for s in (-1, 1):
        for t in (-1, 1):
            rest += [[0, s / phi, t * phi], [s / phi, t * phi, 0], [t * phi, 0, s / phi]]
    return 0.3 * np.array(cube + rest, dtype=float)


def wedge():
    half = np.tan(np.radians(10))  # Half of the 20° ridge angle.
    tri = [[0, 0.3], [-0.3 * half, 0], [0.3 * half, 0]]
    return np.array([[x, y, z] for z in (-0.25, 0.25) for y, x in [(p[1], p[0]) for p in tri]], dtype=float)


def pyramid():
    angles = 2 * np.pi * np.arange(5) / 5
    base = np.stack([0.4 * np.cos(angles), 0.4 * np.sin(angles), np.full(5, -0.15)], axis=1)
    # The apex above the base's centre where the sides rise at 40° from the base's inscribed circle.
    apex_height = 0.4 * np.cos(np.pi / 5) * np.tan(np.radians(40))
    return np.vstack([base, [[0, 0, -0.15 + apex_height]]])


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", required=True, help="folder for the .obj files")
    args = parser.parse_args()
    os.makedirs(args.output, exist_ok=True)
    write_hull(os.path.join(args.output, "hull8.obj"), random_hull(8, 3))
    write_hull(os.path.join(args.output, "hull12.obj"), random_hull(12, 12))
    write_hull(os.path.join(args.output, "hull40.obj"), random_hull(40, 40))
    write_hull(os.path.join(args.output, "dodecahedron.obj"), dodecahedron())
    write_hull(os.path.join(args.output, "wedge.obj"), wedge())
    write_hull(os.path.join(args.output, "pyramid.obj"), pyramid())


if __name__ == "__main__":
    main()
