#!/usr/bin/env python3
"""How a mesh made from one sensor view looks from that sensor.

    bench/view_report.py MESH.ply --eye X,Y,Z [--fragment 0.01]

Prints the share of the mesh's area whose triangles face the eye (their normal, from the
winding, toward it), the components after merging vertices by position (as STL export does),
the share of the area in fragments (components under --fragment of the area), and the
boundary edges. Reads PLY as lsqsurf writes it (binary little endian or ascii, float x y z
first, faces as a list of int indices).
"""
import argparse
import sys

import numpy as np


def read_ply(path):
    with open(path, "rb") as f:
        data = f.read()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    fmt = header[1].split()[1]
    elements, current = [], None
    for line in header:
        words = line.split()
        if words[0] == "element":
            current = {"name": words[1], "count": int(words[2]), "props": []}
            elements.append(current)
        elif words[0] == "property":
            current["props"].append(words[1:])
    sizes = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4",
             "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1", "int32": "i4", "uint32": "u4",
             "float32": "f4", "float64": "f8", "int16": "i2", "uint16": "u2"}
    body = data[end:]
    vertices = faces = None
    if fmt == "ascii":
        rows = iter(body.decode("ascii").split("\n"))
        for e in elements:
            if e["name"] == "vertex":
                v = np.array([next(rows).split() for _ in range(e["count"])], dtype=np.float64)
                vertices = v[:, :3]
            elif e["name"] == "face":
                faces = np.array([[int(x) for x in next(rows).split()[1:4]] for _ in range(e["count"])])
            else:
                for _ in range(e["count"]):
                    next(rows)
        return vertices, faces
    offset = 0
    for e in elements:
        if e["name"] == "vertex":
            dtype = np.dtype([(p[1], "<" + sizes[p[0]]) for p in e["props"]])
            v = np.frombuffer(body, dtype=dtype, count=e["count"], offset=offset)
            offset += dtype.itemsize * e["count"]
            vertices = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
        elif e["name"] == "face":
            count_type, index_type = sizes[e["props"][0][1]], sizes[e["props"][0][2]]
            dtype = np.dtype([("n", "<" + count_type), ("i", "<" + index_type, 3)])
            f = np.frombuffer(body, dtype=dtype, count=e["count"], offset=offset)
            if np.any(f["n"] != 3):
                sys.exit("only triangle meshes")
            faces = f["i"].astype(np.int64)
            offset += dtype.itemsize * e["count"]
        else:
            sys.exit(f"cannot skip element {e['name']}")
    return vertices, faces


def components(faces, vertex_count):
    parent = np.arange(vertex_count)

    def find(x):
        root = x
        while parent[root] != root:
            root = parent[root]
        while parent[x] != root:
            parent[x], x = root, parent[x]
        return root

    for a, b, c in faces:
        ra, rb, rc = find(a), find(b), find(c)
        parent[rb] = ra
        parent[find(rc)] = ra
    return np.array([find(f[0]) for f in faces])


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mesh")
    parser.add_argument("--eye", required=True, help="the sensor's position, x,y,z")
    parser.add_argument("--fragment", type=float, default=0.01, help="components under this share of the area")
    args = parser.parse_args()
    eye = np.array([float(x) for x in args.eye.split(",")])
    vertices, faces = read_ply(args.mesh)
    vertices, merged = np.unique(vertices, axis=0, return_inverse=True)
    faces = merged.reshape(-1)[faces]
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    total = area.sum()
    facing = np.einsum("ij,ij->i", cross, eye - (a + b + c) / 3) > 0
    label = components(faces, len(vertices))
    _, which = np.unique(label, return_inverse=True)
    component_area = np.bincount(which, weights=area)
    fragments = component_area < args.fragment * total
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    print(f"triangles {len(faces)}  area facing the eye {area[facing].sum() / total:.4f}  "
          f"components {len(component_area)} ({int(np.count_nonzero(~fragments))} over {args.fragment:g} of the area)  "
          f"area in fragments {component_area[fragments].sum() / total:.4f}  boundary edges {int(np.count_nonzero(uses == 1))}")


if __name__ == "__main__":
    main()
