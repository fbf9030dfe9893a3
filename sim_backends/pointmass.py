"""A MuJoCo point mass on a plane: the small sample robot that proves the platform.

State: x, y [m], vx, vy [m/s]. Action: force fx, fy [N]. Viscous floor drag.
"""

from __future__ import annotations

import mujoco
import numpy as np
from pydantic import Field

from hilstack.configs.schema import Params, PeriodS, finite
from hilstack.drivers.base import Health, Observation, RobotSpec, Space
from hilstack.sim_backends.base import LockstepSim

_XML = """
<mujoco model="pointmass">
  <option timestep="{dt}" integrator="implicitfast"/>
  <worldbody>
    <geom type="plane" size="2 2 0.1" rgba=".8 .8 .8 1"/>
    <body name="mass" pos="0 0 0.05">
      <joint name="x" type="slide" axis="1 0 0" damping="{damping}"/>
      <joint name="y" type="slide" axis="0 1 0" damping="{damping}"/>
      <geom type="sphere" size="0.05" mass="{mass}" rgba=".2 .4 .8 1" contype="0" conaffinity="0"/>
    </body>
  </worldbody>
  <actuator>
    <motor name="fx" joint="x" gear="1"/>
    <motor name="fy" joint="y" gear="1"/>
  </actuator>
</mujoco>
"""


#: MuJoCo time step of the sample robot [s]
PhysicsDtS = finite(ge=1e-5, le=0.01, source="≥ 10 µs: at most 10⁵ steps per 1 s period; ≤ 10 ms: a stable point mass")


#: the sample robot's force limit [N]
ForceN = finite(gt=0, le=100.0, source="≤ 100 N: 200 m/s² on the default 0.5 kg mass, past anything the 2 m arena holds")
#: its rate limit [N/s]
ForceRateNPerS = finite(gt=0, le=10000.0, source=(
    "the whole force range (±100 N) within one default 20 ms period: a larger rate limit never binds, it would be off"))


class PointMassParams(Params):
    mass_kg: float = Field(0.5, gt=0)
    damping_ns_per_m: float = Field(0.5, ge=0)
    max_force_n: ForceN = 2.0
    max_force_rate_n_per_s: ForceRateNPerS = 40.0
    period_s: PeriodS = 0.02
    physics_dt_s: PhysicsDtS = 0.002
    arena_m: float = Field(2.0, gt=0)


class PointMassSim(LockstepSim):
    params_type = PointMassParams

    def __init__(self, params: PointMassParams | None = None, source: str | None = None):
        super().__init__()
        self.source = source
        self.params = p = params or PointMassParams()
        f = p.max_force_n
        self.spec = RobotSpec(
            name="pointmass",
            state=Space.build([
                ("x", "m", -p.arena_m, p.arena_m),
                ("y", "m", -p.arena_m, p.arena_m),
                ("vx", "m/s", -np.inf, np.inf),
                ("vy", "m/s", -np.inf, np.inf),
            ]),
            action=Space.build([("fx", "N", -f, f), ("fy", "N", -f, f)]),
            period_s=p.period_s,
            action_rate_per_s=np.full(2, p.max_force_rate_n_per_s),
            safe_action=np.zeros(2),
            description="MuJoCo point mass on a plane (sample robot)",
        )
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self._seq = 0

    def _on_configure(self) -> None:
        p = self.params
        xml = _XML.format(dt=p.physics_dt_s, damping=p.damping_ns_per_m, mass=p.mass_kg)
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        self._substeps = max(1, round(p.period_s / p.physics_dt_s))

    def _on_cleanup(self) -> None:
        self.model = self.data = None

    def reset(self, x: float = 0.0, y: float = 0.0) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = (x, y)
        mujoco.mj_forward(self.model, self.data)
        self._rehold()  # mj_resetData zeroed the force: hold that

    def _read(self) -> Observation:
        d = self.data
        self._seq += 1
        state = np.array([d.qpos[0], d.qpos[1], d.qvel[0], d.qvel[1]])
        return Observation(t_s=float(d.time), state=state, seq=self._seq)

    def _hold_command(self, obs: Observation) -> np.ndarray:
        """The force the actuators apply now (what the "device" runs)."""
        return self.data.ctrl.copy()

    def _write(self, action: np.ndarray) -> None:
        self.data.ctrl[:] = action

    def _stop(self) -> None:
        if self.data is not None:
            self.data.ctrl[:] = 0.0

    def _advance(self, duration_s: float) -> None:
        n = max(1, round(duration_s / self.params.physics_dt_s))
        mujoco.mj_step(self.model, self.data, nstep=n)

    def _health(self) -> Health:
        return Health(ok=self.data is not None, extra={"sim_time_s": self.sim_time_s})

    def rollout_batch(self, commands: np.ndarray, threads: int = 1) -> np.ndarray:
        """States ``[B, T+1, 4]`` of ``B`` open-loop rollouts of ``commands`` ``[B, T, 2]``
        from the current state, through ``mujoco.rollout`` (sim_backends/batch.py), without
        the contract loop or the bus; this sim's own state does not move.

        The same states as ``write(commands[b, t]); tick()`` per period, when the commands
        are what the contract applies (inside the bounds and the rate limit:
        :func:`hilstack.sim_backends.batch.rate_bounded_walk`); commands outside them are
        refused, not limited."""
        from hilstack.sim_backends.batch import physics_state, rollout_held

        if self.data is None:
            raise RuntimeError("pointmass: rollout_batch() needs configure() first")
        c = np.asarray(commands, dtype=np.float64)
        sp = self.spec
        if c.ndim != 3 or c.shape[2] != 2:
            raise ValueError(f"pointmass: commands must be [B, T, 2], got shape {c.shape}")
        if not (np.all(np.isfinite(c)) and np.all(c >= sp.action.low) and np.all(c <= sp.action.high)):
            raise ValueError(f"pointmass: commands must be finite and within ±{self.params.max_force_n} N")
        full = rollout_held(self.model, physics_state(self.model, self.data), c, self._substeps, threads=threads)
        nq = self.model.nq
        return full[..., 1:1 + nq + self.model.nv]  # (time, qpos, qvel): x, y, vx, vy
