"""Reference paths for path following, as waypoint polylines in metres.

Every path starts at the origin in the world (mocap) frame, with the robot expected to
start there facing +x. ``scale`` multiplies every coordinate: the defaults are sized for
the VelociRoACH (about 10 cm long, 0.3–1 m/s), i.e. a few body lengths per segment and a
few seconds to a few tens of seconds per path.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PATHS", "straight", "left", "right", "zigzag", "figure8", "make_path", "path_length", "fillet"]


def straight(scale: float = 1.0, length_m: float = 2.0, points: int = 9) -> np.ndarray:
    """A straight line along +x, ``length_m`` long. Returns ``[P, 2]`` metres."""
    x = np.linspace(0.0, length_m, points)
    return scale * np.stack([x, np.zeros_like(x)], axis=1)


def _turn(sign: float, scale: float, leg_m: float, radius_m: float, arc_points: int) -> np.ndarray:
    # forward leg, a 90° arc (left: counter-clockwise), forward leg in the new direction
    th = np.linspace(0.0, np.pi / 2, arc_points)
    arc = np.stack([leg_m + radius_m * np.sin(th), sign * radius_m * (1 - np.cos(th))], axis=1)
    start = np.array([[0.0, 0.0], [leg_m / 2, 0.0]])
    end = arc[-1] + np.array([[0.0, sign * leg_m / 2], [0.0, sign * leg_m]])
    return scale * np.concatenate([start, arc, end])


def left(scale: float = 1.0, leg_m: float = 0.6, radius_m: float = 0.4, arc_points: int = 9) -> np.ndarray:
    """Forward ``leg_m``, a 90° left turn of ``radius_m``, forward ``leg_m``. ``[P, 2]`` m."""
    return _turn(+1.0, scale, leg_m, radius_m, arc_points)


def right(scale: float = 1.0, leg_m: float = 0.6, radius_m: float = 0.4, arc_points: int = 9) -> np.ndarray:
    """Mirror image of :func:`left`. ``[P, 2]`` m."""
    return _turn(-1.0, scale, leg_m, radius_m, arc_points)


def zigzag(scale: float = 1.0, segment_m: float = 0.5, amplitude_m: float = 0.25, teeth: int = 4) -> np.ndarray:
    """Alternating ±``amplitude_m`` lateral offsets every ``segment_m`` along +x. ``[P, 2]`` m."""
    x = segment_m * np.arange(teeth + 1)
    y = np.zeros(teeth + 1)
    y[1::2] = amplitude_m
    y[2::2] = -amplitude_m
    return scale * np.stack([x, y], axis=1)


def figure8(scale: float = 1.0, size_m: float = 0.75, points: int = 65) -> np.ndarray:
    """Lemniscate of Gerono ``x = a sin t, y = a sin t cos t``, t ∈ [0, 2π], a = ``size_m``.

    Closed (last point = first); it starts at the origin heading 45° left of +x and
    crosses itself at the origin. ``[P, 2]`` m.
    """
    t = np.linspace(0.0, 2 * np.pi, points)
    xy = size_m * np.stack([np.sin(t), np.sin(t) * np.cos(t)], axis=1)
    xy[-1] = xy[0]
    return scale * xy


PATHS = {"straight": straight, "left": left, "right": right, "zigzag": zigzag, "figure8": figure8}


def make_path(name: str, scale: float = 1.0, **kwargs) -> np.ndarray:
    """A named path (``straight``, ``left``, ``right``, ``zigzag``, ``figure8``) as ``[P, 2]`` m."""
    key = name.replace("-", "").replace("_", "").lower()
    key = {"figureeight": "figure8"}.get(key, key)
    if key not in PATHS:
        raise KeyError(f"unknown path {name!r}; choose from {sorted(PATHS)}")
    return PATHS[key](scale=scale, **kwargs).astype(np.float32)


def path_length(waypoints: np.ndarray) -> float:
    """Total polyline length in metres."""
    return float(np.linalg.norm(np.diff(np.asarray(waypoints), axis=0), axis=1).sum())


def fillet(waypoints: np.ndarray, radius_m: float, max_step_rad: float = 0.2) -> np.ndarray:
    """The polyline with every corner replaced by a circular arc of ``radius_m`` tangent to
    both segments (``[Q, 2]`` m, same start and end). A robot with a bounded turn rate
    cannot follow a corner exactly; the arc is the feasible reference near it. The arc's
    tangent length ``r·tan(θ/2)`` is capped at half of each adjacent segment (the radius
    shrinks where segments are short); arcs are sampled every ``max_step_rad`` of turn.
    Corners turning less than 1e-3 rad are kept as they are.
    """
    wp = np.asarray(waypoints, dtype=np.float64)
    if radius_m <= 0 or len(wp) < 3:
        return wp.copy()
    out = [wp[0]]
    for i in range(1, len(wp) - 1):
        a, b, c = wp[i - 1], wp[i], wp[i + 1]
        u_in, u_out = b - a, c - b
        l_in, l_out = float(np.linalg.norm(u_in)), float(np.linalg.norm(u_out))
        u_in, u_out = u_in / l_in, u_out / l_out
        cross = u_in[0] * u_out[1] - u_in[1] * u_out[0]
        theta = float(np.arctan2(cross, float(u_in @ u_out)))  # signed turn, >0 = left
        if abs(theta) < 1e-3:
            out.append(b)
            continue
        d = min(radius_m * np.tan(abs(theta) / 2), l_in / 2, l_out / 2)
        r = d / np.tan(abs(theta) / 2)
        start = b - d * u_in
        normal = np.array([-u_in[1], u_in[0]]) * np.sign(theta)  # toward the arc's centre
        centre = start + r * normal
        n = max(2, int(np.ceil(abs(theta) / max_step_rad)) + 1)
        phi0 = np.arctan2(start[1] - centre[1], start[0] - centre[0])
        for phi in phi0 + np.sign(theta) * np.linspace(0.0, abs(theta), n):
            out.append(centre + r * np.array([np.cos(phi), np.sin(phi)]))
    out.append(wp[-1])
    pts = np.array(out)
    keep = np.r_[True, np.linalg.norm(np.diff(pts, axis=0), axis=1) > 1e-9]
    return pts[keep].astype(np.asarray(waypoints).dtype)
