#!/usr/bin/python3
"""Writes closed ground-truth meshes with thin parts, for lsqsurf-bench --data DIR.

    bench/thin_shapes.py -o /tmp/thin
    build/release/bin/lsqsurf-bench --data /tmp/thin --models hand plate ring \\
        --sizes 200000 --method pu --no-normals --noise 0 0.001

  hand   a palm with five fingers (radii 0.6 % to 1.2 % of the diagonal), two of them a finger's
         width apart, and a horn narrowing to a tip: marching cubes (scikit-image) of the union's
         distance field on a 512^3 lattice.
  plate  a rectangular plate whose thickness is 0.2 % of its diagonal (exact, 12 triangles).
  ring   a torus whose tube radius is 1 % of its diagonal (exact up to its 2048 x 64 facets).
Needs python3-skimage and python3-numpy (scripts/install-deps.sh --with-scipy).
"""
import argparse
import os

import numpy as np
from skimage.measure import marching_cubes


def capsule(points, a, b, radius):
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip(((points - a) @ ab) / (ab @ ab), 0, 1)
    return np.linalg.norm(points - (a + t[..., None] * ab), axis=-1) - radius


def cone(points, a, b, ra, rb):
    """A round cone from a (radius ra) to b (radius rb), approximated by a capsule of varying radius."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip(((points - a) @ ab) / (ab @ ab), 0, 1)
    return np.linalg.norm(points - (a + t[..., None] * ab), axis=-1) - (ra + t * (rb - ra))


def hand_distance(points):
    palm = np.linalg.norm(points / np.array([0.22, 0.28, 0.08]), axis=-1) - 1.0
    palm *= 0.08  # Roughly a distance near the surface.
    d = palm
    fingers = [([-0.15, 0.2, 0], [-0.2, 0.45, 0], 0.010),
               ([-0.06, 0.24, 0], [-0.07, 0.5, 0], 0.012),
               ([-0.03, 0.24, 0], [-0.035, 0.5, 0.0], 0.009),  # A finger's width from the last one.
               ([0.06, 0.24, 0], [0.09, 0.48, 0], 0.008),
               ([0.17, 0.05, 0], [0.38, 0.2, 0.05], 0.007)]
    for a, b, r in fingers:
        d = np.minimum(d, capsule(points, a, b, r))
    d = np.minimum(d, cone(points, [0.0, -0.2, 0.05], [0.05, -0.45, 0.25], 0.03, 0.004))  # The horn.
    return d


def write_obj(path, vertices, faces):
    with open(path, "w") as out:
        np.savetxt(out, vertices, fmt="v %.9g %.9g %.9g")
        np.savetxt(out, faces + 1, fmt="f %d %d %d")


def hand(path, n):
    lo, hi = np.array([-0.35, -0.55, -0.15]), np.array([0.45, 0.6, 0.35])
    step = (hi - lo).max() / (n - 1)
    axes = [lo[k] + step * np.arange(int(np.ceil((hi[k] - lo[k]) / step)) + 1) for k in range(3)]
    field = np.empty([len(a) for a in axes], dtype=np.float32)
    for i, x in enumerate(axes[0]):
        y, z = np.meshgrid(axes[1], axes[2], indexing="ij")
        field[i] = hand_distance(np.stack([np.full_like(y, x), y, z], axis=-1))
    vertices, faces, _, _ = marching_cubes(field, 0.0, spacing=(step, step, step))
    # scikit-image winds its triangles to face the falling field: outwards for a distance field.
    write_obj(path, vertices + lo, faces)


def plate(path):
    w, h = 0.6, 0.4
    t = 0.002 * np.sqrt(w * w + h * h) / np.sqrt(1 - 0.002 ** 2)  # 0.2 % of the plate's own diagonal.
    v = np.array([[x, y, z] for z in (-t / 2, t / 2) for y in (-h / 2, h / 2) for x in (-w / 2, w / 2)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = np.array([f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))])
    write_obj(path, v, faces)


def ring(path, big=0.4, small=0.012, nu=2048, nv=64):
    u, v = np.meshgrid(np.arange(nu) * 2 * np.pi / nu, np.arange(nv) * 2 * np.pi / nv, indexing="ij")
    x = np.stack([(big + small * np.cos(v)) * np.cos(u), (big + small * np.cos(v)) * np.sin(u), small * np.sin(v)], -1)
    index = np.arange(nu * nv).reshape(nu, nv)
    a, b = index, np.roll(index, -1, axis=0)
    c, d = np.roll(b, -1, axis=1), np.roll(a, -1, axis=1)
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    write_obj(path, x.reshape(-1, 3), faces)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-o", "--output", required=True, help="folder for hand.obj, plate.obj, ring.obj")
    parser.add_argument("--lattice", type=int, default=512, help="marching cubes lattice of the hand")
    args = parser.parse_args()
    os.makedirs(args.output, exist_ok=True)
    hand(os.path.join(args.output, "hand.obj"), args.lattice)
    plate(os.path.join(args.output, "plate.obj"))
    ring(os.path.join(args.output, "ring.obj"))


if __name__ == "__main__":
    main()
