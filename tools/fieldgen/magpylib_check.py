#!/usr/bin/env python3
"""Cross-check millinav's closed-form coil model against magpylib.

Exports a rig's coils' filaments with `fieldgen coils --export-loops`, evaluates the
direct model at random workspace points with `fieldgen coils --probe`, builds the same loops as
magpylib `current.Circle` sources, and compares per coil and point:

  field    |B_ours - B_magpy| / |B_magpy|
  gradient ||G_ours - G_magpy||_F / ||G_magpy||_F  (magpylib gradient by central differences)

Prints the maximum relative errors and exits 1 if the field error exceeds --tol.

usage: magpylib_check.py --fieldgen PATH/TO/fieldgen --rig RIG.toml [--points 500] [--seed 1] [--tol 1e-6]
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

try:
    import magpylib as magpy
    from scipy.spatial.transform import Rotation
except ImportError as e:  # the Rust test checks for this first; be clear if run by hand
    sys.exit(f"magpylib_check: {e} (pip install magpylib)")


def rotation_z_to(axis):
    """Rotation taking +z (magpylib Circle axis) to `axis`."""
    a = np.asarray(axis, float)
    a /= np.linalg.norm(a)
    z = np.array([0.0, 0.0, 1.0])
    c = float(np.dot(z, a))
    v = np.cross(z, a)
    s = np.linalg.norm(v)
    if s < 1e-15:
        return Rotation.identity() if c > 0 else Rotation.from_rotvec([np.pi, 0.0, 0.0])
    return Rotation.from_rotvec(v / s * np.arctan2(s, c))


def coil_collection(coil):
    """One coil (per ampere) as a magpylib Collection of Circle loops."""
    rot = rotation_z_to(coil["axis"])
    loops = [
        magpy.current.Circle(
            current=coil["turns_per_loop"],  # 1 A through turns_per_loop turns
            diameter=2.0 * lp["radius_m"],
            position=lp["center_m"],
            orientation=rot,
        )
        for lp in coil["loops"]
    ]
    return magpy.Collection(*loops)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fieldgen", required=True, help="path of the fieldgen binary")
    ap.add_argument("--rig", required=True, help="rig file whose coils to check")
    ap.add_argument("--points", type=int, default=500)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--tol", type=float, default=1e-6, help="max allowed relative field error")
    ap.add_argument("--half-xy", type=float, default=0.05, help="workspace half-size x,y, m")
    ap.add_argument("--half-z", type=float, default=0.05, help="half-height z, m (workspace cube: 0.05)")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        loops_path = os.path.join(tmp, "loops.json")
        points_path = os.path.join(tmp, "points.json")
        probe_path = os.path.join(tmp, "probe.json")
        subprocess.run([args.fieldgen, "coils", "--rig", args.rig, "--export-loops", loops_path], check=True,
                       stdout=subprocess.DEVNULL)
        rng = np.random.default_rng(args.seed)
        pts = rng.uniform(-1.0, 1.0, size=(args.points, 3)) * [args.half_xy, args.half_xy, args.half_z]
        with open(points_path, "w") as f:
            json.dump({"points_m": pts.tolist()}, f)
        subprocess.run([args.fieldgen, "coils", "--rig", args.rig, "--probe", points_path, "--probe-out", probe_path],
                       check=True, stdout=subprocess.DEVNULL)
        with open(loops_path) as f:
            loops = json.load(f)
        with open(probe_path) as f:
            probe = json.load(f)

    ours_b = np.asarray(probe["field_t_per_a"])  # (points, coils, 3)
    ours_g = np.asarray(probe["gradient_t_per_am"]).reshape(len(pts), -1, 3, 3)  # [i, j] = dB_i/dx_j
    h = 1e-6
    worst_b = (0.0, None)
    worst_g = (0.0, None)
    for k, coil in enumerate(loops["coils"]):
        col = coil_collection(coil)
        b = magpy.getB(col, pts)  # T, SI units (magpylib >= 5)
        g = np.empty((len(pts), 3, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = h
            g[:, :, j] = (magpy.getB(col, pts + e) - magpy.getB(col, pts - e)) / (2 * h)
        eb = np.linalg.norm(ours_b[:, k] - b, axis=1) / np.linalg.norm(b, axis=1)
        eg = np.linalg.norm(ours_g[:, k] - g, axis=(1, 2)) / np.linalg.norm(g, axis=(1, 2))
        if eb.max() > worst_b[0]:
            worst_b = (float(eb.max()), (coil["name"], pts[eb.argmax()].tolist()))
        if eg.max() > worst_g[0]:
            worst_g = (float(eg.max()), (coil["name"], pts[eg.argmax()].tolist()))

    print(f"magpylib {magpy.__version__} cross-check: {len(loops['coils'])} coils "
          f"({sum(len(c['loops']) for c in loops['coils'])} loops) at {len(pts)} random points, "
          f"|x|,|y| <= {args.half_xy * 1e3:.0f} mm, |z| <= {args.half_z * 1e3:.0f} mm")
    print(f"  field    max relative error {worst_b[0]:.3e} (coil {worst_b[1][0]})")
    print(f"  gradient max relative error {worst_g[0]:.3e} (coil {worst_g[1][0]}; "
          f"magpylib side by central differences, h = {h:g} m)")
    ok = worst_b[0] <= args.tol and worst_g[0] <= max(args.tol, 1e-5)
    print("  PASS" if ok else f"  FAIL (tolerance {args.tol:g} field, {max(args.tol, 1e-5):g} gradient)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
