#!/usr/bin/env python3
"""Draws the robot model `rollbase urdf` generates, as parsed by urdf_parser_py (an independent
URDF parser), for docs/ros2.md: a top view and a side view with every link placed by forward
kinematics through the parsed joints (origins, axes, types) at a given joint state, the way
robot_state_publisher places them for RViz.

    rollbase urdf > /tmp/rollbase.urdf
    python3 scripts/draw-urdf.py /tmp/rollbase.urdf docs/img/urdf-model.png

Needs `pip install urdf-parser-py matplotlib numpy`. The joint state drawn: legs at the
platform's nominal extension (the prismatic joints' range midpoint is shown as a dashed
circle), steering angles as a base turning about a point ahead-left would set them, wheels at 0."""

import math
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Polygon  # noqa: E402
from urdf_parser_py.urdf import URDF  # noqa: E402


def rot(rpy):
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def axis_angle(axis, a):
    x, y, z = np.array(axis) / np.linalg.norm(axis)
    c, s, C = math.cos(a), math.sin(a), 1 - math.cos(a)
    return np.array([[c + x * x * C, x * y * C - z * s, x * z * C + y * s],
                     [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
                     [z * x * C - y * s, z * y * C + x * s, c + z * z * C]])


def fk(robot, q):
    """World pose (R, p) of every link for joint positions q (by joint name)."""
    poses = {robot.get_root(): (np.eye(3), np.zeros(3))}
    changed = True
    while changed:
        changed = False
        for j in robot.joints:
            if j.child in poses or j.parent not in poses:
                continue
            R, p = poses[j.parent]
            o = j.origin
            Rj, pj = rot(o.rpy if o else (0, 0, 0)), np.array(o.xyz if o else (0, 0, 0))
            R2, p2 = R @ Rj, p + R @ pj
            v = q.get(j.name, 0.0)
            if j.type == "prismatic":
                p2 = p2 + R2 @ (np.array(j.axis) * v)
            elif j.type in ("revolute", "continuous"):
                R2 = R2 @ axis_angle(j.axis, v)
            poses[j.child] = (R2, p2)
            changed = True
    return poses


def main(src, out):
    robot = URDF.from_xml_string(open(src, "rb").read())
    legs = [j for j in robot.joints if j.type == "prismatic"]
    q = {}
    for j in legs:
        q[j.name] = (j.limit.lower + j.limit.upper) / 2
    # Steering as for a turn about a point (x 0, y 1.2 m): each wheel perpendicular to its ray.
    poses0 = fk(robot, q)
    icr = np.array([0.0, 1.2])
    for j in robot.joints:
        if j.type == "continuous" and j.axis == [0.0, 0.0, 1.0]:
            R, p = poses0[j.parent]
            d = p[:2] - icr
            q[j.name] = math.atan2(d[0], -d[1])
    poses = fk(robot, q)
    fig, (top, side) = plt.subplots(1, 2, figsize=(10, 4.8), gridspec_kw={"width_ratios": [1, 1.1]})
    for ax, (i, k), title in ((top, (0, 1), "top view (x forward, y left)"), (side, (0, 2), "side view (x forward, z up)")):
        for link in robot.links:
            if link.name not in poses or not link.visuals:
                continue
            R, p = poses[link.name]
            for v in link.visuals:
                o = v.origin
                Rv = R @ rot(o.rpy if o else (0, 0, 0))
                pv = p + R @ np.array(o.xyz if o else (0, 0, 0))
                g = v.geometry
                if hasattr(g, "size"):
                    hx, hy, hz = (np.array(g.size) / 2)
                    corners = [np.array([sx * hx, sy * hy, sz * hz]) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
                elif hasattr(g, "radius"):
                    rr, hl = g.radius, g.length / 2
                    corners = [np.array([rr * math.cos(t), rr * math.sin(t), sz * hl]) for t in np.linspace(0, 2 * math.pi, 24) for sz in (-1, 1)]
                else:
                    continue
                pts = np.array([pv + Rv @ c for c in corners])[:, [i, k]]
                # Convex hull of the projection (gift wrapping; few points).
                hull = hull2d(pts)
                color = {"body": "#8c99b3", "leg": "#4d4d59", "tyre": "#1a1a1a"}.get(getattr(v.material, "name", ""), "#999")
                ax.add_patch(Polygon(hull, closed=True, facecolor=color, edgecolor="k", lw=0.6, alpha=0.85))
        for j in legs:
            R, p = poses[j.parent]
            o = np.array(j.origin.xyz)
            a = (R @ rot(j.origin.rpy))[:, 0]
            lo, hi = p + R @ o + a * j.limit.lower, p + R @ o + a * j.limit.upper
            ax.plot([lo[i], hi[i]], [lo[k], hi[k]], color="#d62728", lw=2.5, alpha=0.6)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3)
        ax.set_xlabel("x (m)")
        ax.set_ylabel(("y" if k == 1 else "z") + " (m)")
    top.plot(*icr, "x", color="#1f77b4")
    top.annotate("centre of rotation of the steering shown", icr, textcoords="offset points", xytext=(6, -4), fontsize=8, color="#1f77b4")
    for j in robot.joints:
        if j.type == "continuous" and j.axis == [0.0, 0.0, 1.0]:
            _, p = poses[j.child]
            top.annotate(j.name, p[:2], textcoords="offset points", xytext=(4, 10), fontsize=7)
    top.set_xlim(-0.7, 0.9)
    top.set_ylim(-0.55, 1.3)
    side.set_xlim(-0.6, 0.6)
    side.set_ylim(-0.02, 0.35)
    n = len(legs)
    fig.suptitle(f"rollbase urdf: {len(robot.links)} links, {len(robot.joints)} joints ({n} prismatic legs, red: their range) "
                 "— parsed by urdf_parser_py, placed by forward kinematics", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def hull2d(pts):
    pts = sorted(map(tuple, pts))

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower, upper = [], []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
