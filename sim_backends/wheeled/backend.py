"""MuJoCo skid-steer wheeled robot with per-wheel suspension on a heightfield (sim only).

Model (built as MJCF text from ``WheeledParams``):

* chassis: a box (``chassis_mass_kg``) on a free joint;
* four wheel units at (±``wheelbase_m``/2, ±``track_m``/2): each a strut body on a vertical
  **slide joint** (the suspension: ``stiffness_n_per_m``, ``damping_ns_per_m``, travel limited
  to ±``travel_m``) carrying a sphere wheel (radius ``wheel_radius_m``) on a hinge;
* actuators: a velocity servo per wheel (gain ``wheel_kv``, force limit ``wheel_torque_nm``);
  the left pair and the right pair take one command each (skid steering);
* terrain: a heightfield of ``terrain_size_m`` (a plane at its lowest height beyond it), smoothed Gaussian noise with RMS
  ``terrain_rms_m`` and correlation length ``terrain_corr_m``, seeded by ``seed``.

Spring rest length: the suspension's ``springref`` is set so that at rest on a plane the
nominal robot sits mid-travel; a stiffer spring then sits higher (its strut sags less).

State (24): x, y, z [m], roll, pitch, yaw [rad], body-frame linear velocity [m/s] (3),
body-frame angular velocity [rad/s] (3), suspension deflections [m] (4: fl, fr, rl, rr),
their rates [m/s] (4), wheel speeds [rad/s] (4). Action (2): left and right wheel speed [rad/s].
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from pydantic import Field

from hilstack.configs.schema import Params, PeriodS, finite
from hilstack.drivers.base import Health, Observation, RobotSpec, Space
from hilstack.sim_backends.base import LockstepSim

WHEELS = ("fl", "fr", "rl", "rr")

#: wheel speed command limit [rad/s]
WheelSpeedRadS = finite(gt=0, le=40.0, source=(
    "≤ 40 rad/s: 2.8 m/s on the default 7 cm wheels, past which the sim robot leaves a 10 m terrain in 4 s"))
#: MuJoCo time step [s]
PhysicsDtS = finite(ge=1e-4, le=0.005, source=(
    "≤ 5 ms: the stiffest suspension of the SIDM pairs (667x: 266800 N/m on a 0.4 kg wheel unit, ~130 Hz, "
    "overdamped) is stable at 2 ms with MuJoCo's implicit damping; ≥ 0.1 ms: at most 10³ steps per 0.1 s period"))
#: a wheel's force limit [N·m]
WheelTorqueNm = finite(gt=0, le=20.0, source="≤ 20 N·m: 280 N at a 7 cm wheel, 7 g on the default 4 kg robot")


class WheeledParams(Params):
    period_s: PeriodS = 0.1
    physics_dt_s: PhysicsDtS = 0.002
    max_wheel_speed_rad_s: WheelSpeedRadS = 20.0
    wheel_torque_nm: WheelTorqueNm = 3.0
    wheel_kv: float = Field(2.0, gt=0, le=100.0)
    chassis_mass_kg: float = Field(4.0, gt=0, le=100.0)
    wheel_mass_kg: float = Field(0.3, gt=0, le=10.0)
    wheelbase_m: float = Field(0.36, gt=0, le=2.0)
    track_m: float = Field(0.30, gt=0, le=2.0)
    wheel_radius_m: float = Field(0.07, gt=0, le=0.5)
    stiffness_n_per_m: float = Field(400.0, gt=0, le=1e6)
    damping_ns_per_m: float = Field(10.0, ge=0, le=1e5)
    travel_m: float = Field(0.04, gt=0, le=0.2)
    friction: float = Field(1.0, gt=0, le=3.0)
    terrain_size_m: float = Field(20.0, gt=1.0, le=100.0)
    terrain_cells: int = Field(256, ge=8, le=1024)
    terrain_rms_m: float = Field(0.02, ge=0, le=0.2)
    terrain_corr_m: float = Field(0.25, gt=0, le=5.0)
    seed: int = 0


def terrain_heights(p: WheeledParams) -> np.ndarray:
    """The heightfield [m], ``terrain_cells`` square, RMS ``terrain_rms_m``, min 0 (seeded)."""
    from scipy.ndimage import gaussian_filter

    n = p.terrain_cells
    raw = np.random.default_rng(p.seed).standard_normal((n, n))
    sigma = p.terrain_corr_m / (p.terrain_size_m / (n - 1))
    h = gaussian_filter(raw, sigma, mode="wrap")
    h = (h - h.mean()) / max(h.std(), 1e-12) * p.terrain_rms_m
    return h - h.min()


def _xml(p: WheeledParams, zmax: float) -> str:
    half = p.terrain_size_m / 2
    r = p.wheel_radius_m
    # preload: each spring's rest position is set so that at rest on a plane the strut sits
    # mid-travel whatever its stiffness (as a ride-height adjustment does)
    load_n = (p.chassis_mass_kg / 4 + 0.1) * 9.81
    springref = load_n / p.stiffness_n_per_m  # the spring's compression under the static load [m]
    units = []
    for name in WHEELS:
        sx = p.wheelbase_m / 2 * (1 if name[0] == "f" else -1)
        sy = p.track_m / 2 * (1 if name[1] == "l" else -1)
        units.append(f"""
      <body name="strut_{name}" pos="{sx} {sy} -0.03">
        <joint name="susp_{name}" type="slide" axis="0 0 1" range="{-p.travel_m} {p.travel_m}" limited="true"
               stiffness="{p.stiffness_n_per_m}" springref="{-springref}" damping="{p.damping_ns_per_m}"
               armature="0.001"/>
        <geom type="cylinder" size="0.01 0.03" mass="0.1" contype="0" conaffinity="0" group="1" rgba=".3 .3 .3 1"/>
        <body name="wheel_{name}" pos="0 0 -0.03">
          <joint name="spin_{name}" type="hinge" axis="0 1 0" damping="0.001"/>
          <geom type="sphere" size="{r}" mass="{p.wheel_mass_kg}" friction="{p.friction} 0.01 0.001"
                condim="3" contype="1" conaffinity="1" group="1" rgba=".1 .1 .1 1"/>
        </body>
      </body>""")
    acts = "\n".join(
        f'    <velocity name="v_{w}" joint="spin_{w}" kv="{p.wheel_kv}" forcelimited="true" '
        f'forcerange="{-p.wheel_torque_nm} {p.wheel_torque_nm}"/>' for w in WHEELS)
    return f"""
<mujoco model="wheeled">
  <option timestep="{p.physics_dt_s}" integrator="implicitfast"/>
  <asset>
    <hfield name="terrain" nrow="{p.terrain_cells}" ncol="{p.terrain_cells}" size="{half} {half} {max(zmax, 1e-4)} 0.1"/>
  </asset>
  <worldbody>
    <light pos="0 0 5" dir="0 0 -1"/>
    <geom name="floor" type="plane" size="0 0 1" contype="1" conaffinity="3" rgba=".4 .4 .4 1"/>
    <geom name="ground" type="hfield" hfield="terrain" contype="1" conaffinity="3" rgba=".55 .5 .4 1" friction="{p.friction} 0.01 0.001"/>
    <body name="chassis" pos="0 0 0.3">
      <freejoint name="root"/>
      <geom type="box" size="{p.wheelbase_m / 2 + 0.02} {max(p.track_m / 2 - p.wheel_radius_m - 0.01, 0.02)} 0.04" mass="{p.chassis_mass_kg}"
            contype="2" conaffinity="0" group="1" rgba=".2 .4 .8 1"/>{"".join(units)}
    </body>
  </worldbody>
  <actuator>
{acts}
  </actuator>
</mujoco>
"""


def _quat_to_rpy(q: np.ndarray) -> tuple[float, float, float]:
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


class WheeledSim(LockstepSim):
    """The wheeled robot (module docstring) behind the driver contract, in lockstep."""
    params_type = WheeledParams

    def __init__(self, params: WheeledParams | None = None, source: str | None = None):
        super().__init__()
        self.source = source
        self.params = p = params or WheeledParams()
        if not (p.wheelbase_m / 2 + p.wheel_radius_m < p.terrain_size_m / 4):
            raise ValueError("WheeledParams: the robot must be small against terrain_size_m")
        inf = np.inf
        names = ([("x", "m", -inf, inf), ("y", "m", -inf, inf), ("z", "m", -inf, inf),
                  ("roll", "rad", -math.pi, math.pi), ("pitch", "rad", -math.pi, math.pi),
                  ("yaw", "rad", -math.pi, math.pi)]
                 + [(f"v{a}", "m/s", -inf, inf) for a in "xyz"] + [(f"w{a}", "rad/s", -inf, inf) for a in "xyz"]
                 + [(f"susp_{w}", "m", -p.travel_m, p.travel_m) for w in WHEELS]
                 + [(f"susp_rate_{w}", "m/s", -inf, inf) for w in WHEELS]
                 + [(f"wheel_{w}", "rad/s", -inf, inf) for w in WHEELS])
        v = p.max_wheel_speed_rad_s
        self.spec = RobotSpec(
            name="wheeled",
            state=Space.build(names),
            action=Space.build([("left", "rad/s", -v, v), ("right", "rad/s", -v, v)]),
            period_s=p.period_s,
            action_rate_per_s=np.full(2, 2 * v / p.period_s),  # any command within one period
            safe_action=np.zeros(2),
            description="MuJoCo skid-steer robot with spring-damper suspension on a heightfield (SIDM's setting)",
        )
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self._seq = 0

    def _on_configure(self) -> None:
        p = self.params
        h = terrain_heights(p)
        self._heights = h
        zmax = float(h.max())
        self.model = mujoco.MjModel.from_xml_string(_xml(p, zmax))
        self.model.hfield_data[:] = (h / max(zmax, 1e-4)).ravel() if zmax > 0 else 0.0
        self.data = mujoco.MjData(self.model)
        self._qadr = {w: (self.model.jnt_qposadr[self.model.joint(f"susp_{w}").id],
                          self.model.jnt_dofadr[self.model.joint(f"susp_{w}").id],
                          self.model.jnt_dofadr[self.model.joint(f"spin_{w}").id]) for w in WHEELS}
        self.reset()

    def _on_cleanup(self) -> None:
        self.model = self.data = None

    def ground_height_m(self, xy: np.ndarray) -> np.ndarray:
        """Terrain height [m] at world points ``xy`` [N, 2] (bilinear in the heightfield)."""
        from scipy.ndimage import map_coordinates

        p = self.params
        n = p.terrain_cells
        half = p.terrain_size_m / 2
        xy = np.asarray(xy, float).reshape(-1, 2)
        col = (xy[:, 0] + half) / (2 * half) * (n - 1)
        row = (xy[:, 1] + half) / (2 * half) * (n - 1)
        return map_coordinates(self._heights, [row, col], order=1, mode="nearest")

    def terrain_patch_m(self, offsets_xy: np.ndarray) -> np.ndarray:
        """Ground heights [m] at ``offsets_xy`` [N, 2] in the chassis' yaw frame, minus the
        chassis height: what the robot would see of the ground around it."""
        d = self.data
        yaw = _quat_to_rpy(d.qpos[3:7])[2]
        c, s = math.cos(yaw), math.sin(yaw)
        xy = d.qpos[0:2] + np.asarray(offsets_xy) @ np.array([[c, s], [-s, c]])
        return self.ground_height_m(xy) - d.qpos[2]

    def reset(self, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, settle_s: float = 0.5) -> None:
        """Put the robot at (x, y) with heading ``yaw`` above the ground, let it settle
        (``settle_s`` with the wheels held), zero the clock's reading of the settling."""
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        ground = float(self.ground_height_m(np.array([[x, y]]))[0])
        d.qpos[0:3] = (x, y, ground + self.params.wheel_radius_m + 0.12)
        d.qpos[3:7] = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
        d.ctrl[:] = 0.0
        mujoco.mj_forward(m, d)
        mujoco.mj_step(m, d, nstep=max(1, round(settle_s / self.params.physics_dt_s)))
        d.time = 0.0
        self._rehold()

    def _read(self) -> Observation:
        d = self.data
        self._seq += 1
        q = d.qpos[3:7]
        rpy = _quat_to_rpy(q)
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, q)
        rot = rot.reshape(3, 3)
        v_body = rot.T @ d.qvel[0:3]
        w_body = d.qvel[3:6]  # a free joint's angular velocity is in the body frame
        susp = [d.qpos[self._qadr[w][0]] for w in WHEELS]
        rate = [d.qvel[self._qadr[w][1]] for w in WHEELS]
        spin = [d.qvel[self._qadr[w][2]] for w in WHEELS]
        state = np.concatenate([d.qpos[0:3], rpy, v_body, w_body, susp, rate, spin])
        return Observation(t_s=float(d.time), state=state, seq=self._seq)

    def _hold_command(self, obs: Observation) -> np.ndarray:
        return self.data.ctrl[[0, 2]].copy()

    def _write(self, action: np.ndarray) -> None:
        left, right = float(action[0]), float(action[1])
        self.data.ctrl[:] = (left, right, left, right)  # fl, fr, rl, rr

    def _stop(self) -> None:
        if self.data is not None:
            self.data.ctrl[:] = 0.0

    def _advance(self, duration_s: float) -> None:
        n = max(1, round(duration_s / self.params.physics_dt_s))
        mujoco.mj_step(self.model, self.data, nstep=n)

    def _health(self) -> Health:
        return Health(ok=self.data is not None, extra={"sim_time_s": self.sim_time_s})
