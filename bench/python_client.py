#!/usr/bin/python3
"""The Python package against the CLI on the same job: wall time of a whole reconstruction (upload,
the job, download and decode), each a process of its own, interleaved on one server.

    bench/python_client.py --build build/release --python .venv/bin/python --runs 3

The cloud: --points points sampled uniformly by area from --mesh (default the shared spot, a
closed surface), given to the CLI as a binary PLY and to Python as a NumPy array. --python is an
interpreter that imports lsqsurf (a virtual environment with the package installed, README);
without it, Debian's python3 with PYTHONPATH=BUILD/python. Prints each run's seconds, the means
and their ratio, and whether the Python result is closed (Mesh.is_closed, outside the timing).
"""
import argparse
import os
import pathlib
import statistics
import subprocess
import tempfile
import time

import numpy as np

CHECKOUT = pathlib.Path(__file__).resolve().parent.parent


def read_obj(path):
    vertices, faces = [], []
    for line in open(path, encoding="utf-8"):
        item = line.split()
        if item and item[0] == "v":
            vertices.append([float(x) for x in item[1:4]])
        elif item and item[0] == "f":
            faces.append([int(x.split("/")[0]) - 1 for x in item[1:4]])
    return np.array(vertices), np.array(faces)


def sample(vertices, faces, count, seed):
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    area = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    chosen = rng.choice(len(faces), count, p=area / area.sum())
    root, v = np.sqrt(rng.random(count)), rng.random(count)
    return ((1 - root)[:, None] * a[chosen] + (root * (1 - v))[:, None] * b[chosen]
            + (root * v)[:, None] * c[chosen]).astype(np.float32)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build", default=str(CHECKOUT / "build" / "release"))
    parser.add_argument("--python", help="an interpreter that imports lsqsurf")
    parser.add_argument("--mesh", default=str(CHECKOUT.parent / "shared" / "data" / "meshes" / "spot.obj"))
    parser.add_argument("--points", type=int, default=100000)
    parser.add_argument("--methods", nargs="+", default=["pu", "iamls"])
    parser.add_argument("--runs", type=int, default=3)
    args = parser.parse_args()
    build = pathlib.Path(args.build).resolve()
    env = dict(os.environ)
    python = args.python
    if python is None:
        python = "/usr/bin/python3"
        env["PYTHONPATH"] = str(build / "python")

    with tempfile.TemporaryDirectory() as work:
        work = pathlib.Path(work)
        points = sample(*read_obj(args.mesh), args.points, seed=5)
        np.save(work / "cloud.npy", points)
        with open(work / "cloud.ply", "wb") as ply:
            ply.write(f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
                      "property float x\nproperty float y\nproperty float z\nend_header\n".encode())
            ply.write(points.astype("<f4").tobytes())
        server = subprocess.Popen([str(build / "bin" / "lsqsurfd"), "--listen", "127.0.0.1:0", "--data-dir",
                                   str(work / "data")], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        address = server.stdout.readline().split()[-1]
        try:
            for method in args.methods:
                cli = [str(build / "bin" / "lsqsurf"), "--server", address, "-q", "reconstruct",
                       str(work / "cloud.ply"), "--method", method, "-o", str(work / "out.ply")]
                script = (f"import numpy as np, lsqsurf\n"
                          f"mesh = lsqsurf.Client('{address}').reconstruct(np.load('{work / 'cloud.npy'}'), "
                          f"method='{method}')\n"
                          f"print(len(mesh.faces))\n")
                seconds = {"cli": [], "python": []}
                for _ in range(args.runs):
                    for name, command in (("cli", cli), ("python", [python, "-c", script])):
                        start = time.perf_counter()
                        subprocess.run(command, check=True, env=env, capture_output=True)
                        seconds[name].append(time.perf_counter() - start)
                check = (f"import numpy as np, lsqsurf\n"
                         f"mesh = lsqsurf.Client('{address}').reconstruct(np.load('{work / 'cloud.npy'}'), "
                         f"method='{method}')\n"
                         f"print(mesh.is_closed(), int(mesh.statistics['components']), len(mesh.faces))\n")
                closed = subprocess.run([python, "-c", check], check=True, env=env, capture_output=True,
                                        text=True).stdout.split()
                for name, times in seconds.items():
                    print(f"{method:6} {name:7} runs {' '.join(f'{t:.2f}' for t in times)} s, "
                          f"mean {statistics.mean(times):.3f} s")
                ratio = statistics.mean(seconds["python"]) / statistics.mean(seconds["cli"])
                print(f"{method:6} python/cli {ratio:.3f}; python result closed {closed[0]}, "
                      f"{closed[1]} component(s), {closed[2]} triangles")
        finally:
            server.terminate()
            server.wait()


if __name__ == "__main__":
    main()
