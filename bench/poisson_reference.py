#!/usr/bin/python3
"""Screened Poisson (Open3D's, after Kazhdan and Hoppe 2013) on oriented points, as a reference.

    bench/poisson_reference.py POINTS.ply -o MESH.ply [--depth 10] [--trim 0.0]

POINTS.ply carries the normals to use (lsqsurf-sensor-sim prepare writes a scan with the
normals a surface job gives it, so both methods start from the same ones). --trim drops the
vertices whose sample density lies below that quantile, as Open3D's own examples do to cut the
surface Poisson closes over unseen parts; 0 keeps the watertight surface. Prints the time taken.
Needs python3-open3d (scripts/install-deps.sh --with-poisson).
"""
import argparse
import sys
import time

import numpy as np
import open3d as o3d


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("points")
    parser.add_argument("-o", "--output", required=True)
    parser.add_argument("--depth", type=int, default=10)
    parser.add_argument("--scale", type=float, default=1.1)
    parser.add_argument("--trim", type=float, default=0.0, help="density quantile below which vertices go")
    args = parser.parse_args()
    cloud = o3d.io.read_point_cloud(args.points)
    if not cloud.has_normals():
        sys.exit(f"{args.points} has no normals")
    start = time.monotonic()
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        cloud, depth=args.depth, scale=args.scale, linear_fit=False)
    if args.trim > 0:
        density = np.asarray(density)
        mesh.remove_vertices_by_mask(density < np.quantile(density, args.trim))
    seconds = time.monotonic() - start
    mesh.compute_vertex_normals()
    if not o3d.io.write_triangle_mesh(args.output, mesh):
        sys.exit(f"cannot write {args.output}")
    print(f"poisson_seconds {seconds:.2f}")
    print(f"vertices {len(mesh.vertices)}")


if __name__ == "__main__":
    main()
