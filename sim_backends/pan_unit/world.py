"""The pan unit's world: a sensor head on a vertical hinge, turned by one simulated servo.

The MJCF is the whole robot: a base, the ``pan`` hinge (armature and damping of a small
geared servo) carrying a 0.1 kg head, and a torque motor ``pan`` on the hinge that the
servo's firmware drives (:class:`~hilstack.sim_backends.dynamixel.world.ServoWorld`).
"""

from __future__ import annotations

import math
import weakref

import mujoco

from hilstack.sim_backends.dynamixel.firmware import ServoPhysics
from hilstack.sim_backends.dynamixel.world import ServoWorld

MJCF = """
<mujoco model="pan_unit">
  <compiler angle="radian"/>
  <option timestep="0.001" gravity="0 0 -9.81"/>
  <worldbody>
    <geom name="base" type="cylinder" size="0.03 0.01" rgba="0.2 0.2 0.2 1"/>
    <body name="head" pos="0 0 0.02">
      <joint name="pan" type="hinge" axis="0 0 1" armature="0.005" damping="0.02" range="-3.1 3.1"/>
      <geom name="head" type="box" size="0.04 0.015 0.015" pos="0.01 0 0.015" mass="0.1" rgba="0.8 0.5 0.1 1"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="pan" joint="pan" gear="1" ctrllimited="false"/>
  </actuator>
</mujoco>
"""

#: bus name -> world (robots built in one process with one bus name share it)
_WORLDS: weakref.WeakValueDictionary[str, PanWorld] = weakref.WeakValueDictionary()


class PanWorld(ServoWorld):
    def __init__(self, pan_id: int = 1, half_range_rad: float = math.pi / 2):
        model = mujoco.MjModel.from_xml_string(MJCF)
        super().__init__(model, {"pan": (int(pan_id), ServoPhysics(), (-half_range_rad, half_range_rad))})


def shared_world(bus_name: str, pan_id: int = 1, half_range_rad: float = math.pi / 2) -> PanWorld:
    w = _WORLDS.get(bus_name)
    if w is None:
        w = _WORLDS[bus_name] = PanWorld(pan_id, half_range_rad)
    return w
