"""Fits of simple shapes to measured points (NumPy only): the 2-D outline maths and the circle and sphere fits
that perception (``deploy/perception.py``) and the obstacle kinds' own perception parts (``shapes.Perceived``)
share.  Moved here from perception so that a kind's fit, written beside its shape maths in ``shapes``, can use
them without the task layer importing the robot side."""

from __future__ import annotations

import math

import numpy as np


def convex_hull(xy: np.ndarray) -> np.ndarray:
    """Convex hull (K, 2), counter-clockwise (Andrew's monotone chain)."""
    pts = np.unique(np.asarray(xy, dtype=float), axis=0)
    if len(pts) < 3:
        return pts

    def half(points: np.ndarray) -> list[np.ndarray]:
        out: list[np.ndarray] = []
        for p in points:
            while len(out) >= 2:
                o, a = out[-2], out[-1]
                if (a[0] - o[0]) * (p[1] - o[1]) - (a[1] - o[1]) * (p[0] - o[0]) > 0:
                    break
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def min_area_rect(xy: np.ndarray) -> tuple[np.ndarray, tuple[float, float], float]:
    """Minimum-area rectangle around points (N, 2): centre (2,), side lengths (along the angle, across)
    and the angle of its first side (rad, in [−π/2, π/2)); rotating calipers over the hull's edges."""
    hull = convex_hull(xy)
    if len(hull) < 3:
        centre = hull.mean(axis=0) if len(hull) else np.zeros(2)
        return centre, (0.0, 0.0), 0.0
    edges = np.roll(hull, -1, axis=0) - hull
    angles = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), math.pi / 2))
    c, s = np.cos(angles), np.sin(angles)
    u = hull[:, 0][None] * c[:, None] + hull[:, 1][None] * s[:, None]  # (A, K) along
    v = -hull[:, 0][None] * s[:, None] + hull[:, 1][None] * c[:, None]  # across
    area = np.ptp(u, axis=1) * np.ptp(v, axis=1)
    i = int(np.argmin(area))
    mu, mv = (u[i].max() + u[i].min()) / 2, (v[i].max() + v[i].min()) / 2
    centre = np.array([mu * c[i] - mv * s[i], mu * s[i] + mv * c[i]])
    angle = float((angles[i] + math.pi / 2) % math.pi - math.pi / 2)
    return centre, (float(np.ptp(u[i])), float(np.ptp(v[i]))), angle


def polygon_area(poly: np.ndarray) -> float:
    """Area of a simple polygon (K, 2) (shoelace)."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def wrap(angle: float, period: float) -> float:
    """``angle`` wrapped into [−period/2, period/2)."""
    return float((angle + period / 2) % period - period / 2)


def fit_circle(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle (Kåsa's algebraic fit) through points (N, 2): centre, radius."""
    a = np.c_[2 * xy, np.ones(len(xy))]
    sol, *_ = np.linalg.lstsq(a, (xy**2).sum(axis=1), rcond=None)
    return sol[:2], math.sqrt(max(float(sol[2] + sol[:2] @ sol[:2]), 0.0))


def fit_sphere(pts: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares sphere (algebraic, then a few Gauss-Newton steps on the geometric distance)."""
    a = np.c_[2 * pts, np.ones(len(pts))]
    sol, *_ = np.linalg.lstsq(a, (pts**2).sum(axis=1), rcond=None)
    c = sol[:3]
    r = math.sqrt(max(sol[3] + c @ c, 1e-12))
    for _ in range(5):
        d = pts - c
        dist = np.linalg.norm(d, axis=1)
        dist = np.maximum(dist, 1e-9)
        jac = np.c_[-d / dist[:, None], -np.ones(len(pts))]
        step, *_ = np.linalg.lstsq(jac, -(dist - r), rcond=None)
        c, r = c + step[:3], r + step[3]
    return c, abs(float(r))
