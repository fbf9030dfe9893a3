"""The hand's reset station in the MuJoCo scene: a ramp that funnels dropped balls to a
pick-up spot, and the reset arm (sim_backends/reset_arm/model.py) beside it.

Geometry (world frame, m; the hand's palm centre is near (1.0, 0.91, 0.12) with the
fingers along -y): a plane under the hand tilted ``slope_rad`` down towards +x, with two
tall walls converging from the ramp's full width to a channel one ball wide, low channel
walls (``channel_wall_m`` high, below the balls' equator so the jaws pass above them)
and an end stop. A dropped ball rolls down to the stop: the **pick-up spot**; the second
ball queues behind it and rolls into the spot when the first is lifted. The scene's
floor moves down (``floor_z_m``) so that the ramp, not the floor, catches the balls.

Nothing here touches the hand or balls in the palm: the ramp is more than 0.1 m below
the hand and the arm is parked upright (q = 0) beside the ramp's low end, so the Baoding
task's physics is the same with and without the station (tests/reset/test_hand_station.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from hilstack.sim_backends.reset_arm.model import DEFAULT_GRIPPER_FORCE_N, add_arm


@dataclass(frozen=True)
class StationGeometry:
    #: the ramp's low end: the surface point under the end stop's inner face [m, world]
    stop_m: tuple[float, float, float] = (1.36, 0.95, -0.24)
    slope_rad: float = math.radians(12.0)
    length_m: float = 0.70           # along the slope, up from the stop
    width_m: float = 0.60            # at the top
    channel_half_width_m: float = 0.026
    channel_length_m: float = 0.16   # the straight part before the stop
    funnel_wall_m: float = 0.06      # wall height above the surface
    channel_wall_m: float = 0.006
    floor_z_m: float = -0.6
    arm_base_m: tuple[float, float, float] = (1.62, 0.95, -0.22)

    def _rot(self) -> np.ndarray:
        # ramp frame: x down the slope (toward the stop), z the surface normal
        c, s = math.cos(self.slope_rad), math.sin(self.slope_rad)
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])

    def spot_m(self, ball_radius_m: float, queue: int = 0) -> np.ndarray:
        """Centre of a ball resting at the pick-up spot [m, world]; ``queue`` 1: the ball behind it."""
        local = np.array([-ball_radius_m * (1 + 2 * queue), 0.0, ball_radius_m])
        return np.asarray(self.stop_m) + self._rot() @ local


def add_station(spec: mujoco.MjSpec, g: StationGeometry, gripper_force_n: float = DEFAULT_GRIPPER_FORCE_N) -> None:
    """Ramp, funnel, pick-up spot and the arm, added to the hand's scene."""
    floor = spec.geom("floor0")
    floor.pos = [floor.pos[0], floor.pos[1], g.floor_z_m]
    rot = g._rot()
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, rot.reshape(-1))
    ramp = spec.worldbody.add_body(name="ramp", pos=list(g.stop_m), quat=quat)
    grey = [0.6, 0.6, 0.65, 1.0]
    t = 0.01  # plate half-thickness
    L, W = g.length_m, g.width_m
    ramp.add_geom(name="ramp_surface", type=mujoco.mjtGeom.mjGEOM_BOX, size=[L / 2, W / 2, t],
                  pos=[-L / 2, 0, -t], rgba=grey, friction=[1.0, 0.005, 0.0001])
    ramp.add_geom(name="ramp_stop", type=mujoco.mjtGeom.mjGEOM_BOX, size=[t, 0.06, 0.04],
                  pos=[t, 0, 0.04], rgba=grey)
    c, cl = g.channel_half_width_m, g.channel_length_m
    for sign in (1.0, -1.0):
        # low channel walls along the last channel_length_m
        ramp.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[cl / 2, 0.005, g.channel_wall_m / 2],
                      pos=[-cl / 2, sign * (c + 0.005), g.channel_wall_m / 2], rgba=grey)
        # tall funnel walls from the top corners to the channel's mouth
        p0 = np.array([-L, sign * W / 2])
        p1 = np.array([-cl, sign * (c + 0.005)])
        mid, d = (p0 + p1) / 2, p1 - p0
        yaw = math.atan2(d[1], d[0])
        ramp.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[float(np.linalg.norm(d)) / 2 + 0.005, 0.005,
                                                          g.funnel_wall_m / 2],
                      pos=[mid[0], mid[1], g.funnel_wall_m / 2], euler=[0, 0, yaw], rgba=grey)
    ramp.add_site(name="pickup_spot", pos=[-0.02, 0, 0.02], size=[0.004, 0, 0], rgba=[0, 1, 0, 1])
    add_arm(spec.worldbody, spec, g.arm_base_m, gripper_force_n)
