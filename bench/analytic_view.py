#!/usr/bin/python3
"""A depth camera's single view of an analytic scene (a ball and a box on a table), as an
organized PCD file such as PCL writes from a Kinect: 640 x 480 pixels, missing pixels as NaN,
the camera's position in VIEWPOINT, depth noise growing with the square of the range and
depth quantized in disparity steps (the layers stereo and structured-light sensors show).

    bench/analytic_view.py OUT.pcd [--eye X,Y,Z] [--noise 0.0012] [--disparity-step 0.125]

--noise is sigma at 1 m (model units are metres; 0 for exact depths), --disparity-step the
quantization in pixels of a 7.5 cm baseline at a focal length of 525 pixels (0 for none).
Pixels seen at more than 84 degrees from the surface normal are missing, as such sensors lose
them. The truth is analytic: --truth OUT.ply also writes the visible surfaces' exact points.
"""
import argparse

import numpy as np

WIDTH, HEIGHT, FOCAL, BASELINE = 640, 480, 525.0, 0.075
BALL_CENTRE, BALL_RADIUS = np.array([0.0, 0.0, 0.15]), 0.15
BOX_MIN, BOX_MAX = np.array([0.25, -0.05, 0.0]), np.array([0.45, 0.25, 0.25])
TABLE = 0.8  # Half the side of the table top, z = 0.


def cast(eye, target):
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0, 0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    u, v = np.meshgrid(np.arange(WIDTH) - (WIDTH - 1) / 2, (HEIGHT - 1) / 2 - np.arange(HEIGHT))
    rays = forward + (u[..., None] * right + v[..., None] * up) / FOCAL
    depth_axis = forward  # Depth is measured along the optical axis, as a depth camera does.
    rays = rays.reshape(-1, 3)
    t = np.full(len(rays), np.inf)
    normal = np.zeros_like(rays)
    # Table.
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = -eye[2] / rays[:, 2]
    hit = eye + tt[:, None] * rays
    ok = (tt > 0) & (np.abs(hit[:, 0]) < TABLE) & (np.abs(hit[:, 1]) < TABLE)
    t[ok], normal[ok] = tt[ok], [0, 0, 1.0]
    # Ball.
    oc = eye - BALL_CENTRE
    b = rays @ oc
    a = np.einsum("ij,ij->i", rays, rays)
    disc = b * b - a * (oc @ oc - BALL_RADIUS**2)
    with np.errstate(invalid="ignore"):
        tb = (-b - np.sqrt(disc)) / a
    ok = (disc > 0) & (tb > 0) & (tb < t)
    t[ok] = tb[ok]
    normal[ok] = (eye + tb[ok, None] * rays[ok] - BALL_CENTRE) / BALL_RADIUS
    # Box (slabs).
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (BOX_MIN - eye) / rays, (BOX_MAX - eye) / rays
    near, far = np.minimum(t1, t2), np.maximum(t1, t2)
    tn, tf = near.max(axis=1), far.min(axis=1)
    ok = (tn < tf) & (tn > 0) & (tn < t)
    t[ok] = tn[ok]
    axis = near[ok].argmax(axis=1)
    n = np.zeros((ok.sum(), 3))
    n[np.arange(len(axis)), axis] = -np.sign(rays[ok][np.arange(len(axis)), axis])
    normal[ok] = n
    points = eye + t[:, None] * rays
    depth = t * (rays @ depth_axis)
    cosine = np.abs(np.einsum("ij,ij->i", normal, rays)) / np.linalg.norm(rays, axis=1)
    return points, normal, depth, cosine, rays, depth_axis


def write_pcd(path, xyz, eye):
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n"
        f"COUNT 1 1 1\nWIDTH {WIDTH}\nHEIGHT {HEIGHT}\nVIEWPOINT {eye[0]} {eye[1]} {eye[2]} 1 0 0 0\n"
        f"POINTS {WIDTH * HEIGHT}\nDATA binary\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(xyz.astype("<f4").tobytes())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out")
    parser.add_argument("--eye", default="0.2,-1.1,0.75")
    parser.add_argument("--noise", type=float, default=0.0012)
    parser.add_argument("--disparity-step", type=float, default=0.125)
    parser.add_argument("--truth")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    eye = np.array([float(x) for x in args.eye.split(",")])
    points, normal, depth, cosine, rays, axis = cast(eye, np.array([0.1, 0.05, 0.1]))
    rng = np.random.default_rng(args.seed)
    seen = np.isfinite(depth) & (cosine > 0.1)
    depth[~seen] = 1.0  # Left out below; a finite stand-in keeps the arithmetic quiet.
    measured = depth + rng.normal(0, 1, len(depth)) * args.noise * depth**2
    if args.disparity_step > 0:
        disparity = FOCAL * BASELINE / measured
        disparity = np.round(disparity / args.disparity_step) * args.disparity_step
        measured = FOCAL * BASELINE / disparity
    along = rays @ axis
    xyz = eye + (measured / along)[:, None] * rays
    xyz[~seen] = np.nan
    write_pcd(args.out, xyz, eye)
    print(f"{int(seen.sum())} valid points of {len(seen)}; eye {args.eye}")
    if args.truth:
        with open(args.truth, "w") as f:
            kept = points[seen]
            f.write(f"ply\nformat ascii 1.0\nelement vertex {len(kept)}\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n")
            np.savetxt(f, kept, fmt="%.7g")


if __name__ == "__main__":
    main()
