#!/usr/bin/env python3
"""Draws vessel_mask.png, the canal mask of the vessel8 rig (../vessel8.toml).

A 3D-printed vessel phantom seen from the top camera (800 x 640 px at 0.125 mm/px, a
100 x 80 mm view centred on the workspace origin): a curved main vessel, 10 mm wide, enters
at the left image edge and leaves at the right one; a side branch, 8 mm wide, leaves it
downward at the bend and ends in a flat cap inside the view, where a printed top-side fitting
takes the flow out of the control plane (the rig's `branch-outlet`).

Reproducible with numpy and zlib only (no image library):

    python3 fieldmaps/rigs/vessel8/draw_mask.py [out.png]

White (255) = canal, black (0) = wall, 8-bit grayscale. Coordinates in mm, x right, y up,
the same as the rig file. Change a number here, rerun, and update the rig file's ports,
zones and route if the outline moved.
"""

import struct
import sys
import zlib
from pathlib import Path

import numpy as np

WIDTH_PX, HEIGHT_PX = 800, 640
MM_PER_PX = 0.125
ORIGIN_MM = (-50.0, 40.0)  # outer corner of pixel (0, 0), top-left

# Main vessel: cubic Bezier centreline, horizontal where it crosses the image edges (x = ±50),
# so the inlet and outlet tubes meet it square to the edge.
MAIN = [(-60.0, -22.0), (-15.0, -22.0), (15.0, 18.0), (60.0, 18.0)]
MAIN_WIDTH_MM = 10.0
# Side branch: leaves the main vessel at its midpoint (0, -2) mm, ends running straight down.
BRANCH = [(0.0, -2.0), (12.0, -14.0), (25.0, -16.0), (25.0, -30.0)]
BRANCH_WIDTH_MM = 8.0
BRANCH_END_Y_MM = -30.0  # flat end cap of the branch (the branch outlet's mouth sits on it)


def bezier(ctrl, n=400):
    """n points on the cubic Bezier curve with control points ctrl."""
    p = np.asarray(ctrl, dtype=float)
    t = np.linspace(0.0, 1.0, n)[:, None]
    return ((1 - t) ** 3) * p[0] + 3 * ((1 - t) ** 2) * t * p[1] + 3 * (1 - t) * t**2 * p[2] + t**3 * p[3]


def distance_to_polyline(x, y, pts):
    """Distance (mm) from every (x, y) to the polyline through pts."""
    best = np.full(x.shape, np.inf)
    for a, b in zip(pts[:-1], pts[1:]):
        ab = b - a
        t = ((x - a[0]) * ab[0] + (y - a[1]) * ab[1]) / max(ab @ ab, 1e-12)
        t = np.clip(t, 0.0, 1.0)
        dx = x - (a[0] + t * ab[0])
        dy = y - (a[1] + t * ab[1])
        best = np.minimum(best, np.hypot(dx, dy))
    return best


def draw():
    cols = np.arange(WIDTH_PX)
    rows = np.arange(HEIGHT_PX)
    x = ORIGIN_MM[0] + (cols[None, :] + 0.5) * MM_PER_PX
    y = ORIGIN_MM[1] - (rows[:, None] + 0.5) * MM_PER_PX
    x, y = np.broadcast_arrays(x, y)
    main = distance_to_polyline(x, y, bezier(MAIN)) <= 0.5 * MAIN_WIDTH_MM
    branch = (distance_to_polyline(x, y, bezier(BRANCH)) <= 0.5 * BRANCH_WIDTH_MM) & (
        y >= BRANCH_END_Y_MM
    )
    return np.where(main | branch, 255, 0).astype(np.uint8)


def write_png(path, img):
    """8-bit grayscale PNG, filter 0 on every row."""
    h, w = img.shape
    raw = b"".join(b"\x00" + img[r].tobytes() for r in range(h))

    def chunk(tag, data):
        c = struct.pack(">I", len(data)) + tag + data
        return c + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n"
    png += chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 9))
    png += chunk(b"IEND", b"")
    Path(path).write_bytes(png)


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).with_name("vessel_mask.png")
    img = draw()
    write_png(out, img)
    print(f"wrote {out} ({img.shape[1]}x{img.shape[0]} px, {int((img > 0).sum())} canal px)")
