"""Shadow Hand MuJoCo backend: the driver contract in-process, in lockstep.

Each ``tick()`` advances one control period (0.1 s) in 1 ms firmware ticks
(:mod:`.firmware`: 20 joint position loops, watchdog, e-stop, motor faults), each
followed by one MuJoCo step of the hand scene (:mod:`.model`). Targets are held
between writes (zero-order hold), as on the real hand.

State: 24 joint angles [rad] and velocities [rad/s] (``drivers/shadow_hand/config.py``).
``Observation.extras["balls_m"]`` holds the two ball positions [m, world frame] (the
camera tracker's job on a real rig) and ``flags["object_dropped"]`` the task's drop test.
With ``params.sim.tracker`` set, ``balls_m`` comes from the camera tracker on a rendered
stereo pair instead (truth in ``balls_true_m``, ``flags["stale_objects"]`` when a ball was
not confidently seen within ``stale_after_s``; docs/camera.md).

Public API for the emulator: ``ShadowHandSim(params)``, ``configure()``, ``reset()``,
``firmware``, ``advance(duration_s)``, ``joint_state()``, ``sim_time_s``.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import replace

import mujoco
import numpy as np
from pydantic import Field

from hilstack.configs.schema import ConfigError, Params, parse_model
from hilstack.drivers.base import Health, Observation
from hilstack.drivers.shadow_hand.config import (
    ACT_INDEX,
    COUPLED_JOINTS,
    HOLD_POSES,
    JOINT_NAMES,
    ShadowHandParams,
    joint_tracking_error,
    shadow_hand_spec,
    to_action,
    to_joint_rad,
)
from hilstack.sim_backends.base import LockstepSim
from hilstack.sim_backends.shadow_hand.firmware import TICK_S, FirmwareConfig, HandFirmware, effect_fields
from hilstack.sim_backends.shadow_hand.model import PHYSICS_DT_S, build_scene, index_scene
from hilstack.sim_backends.shadow_hand.station import StationGeometry
from hilstack.tasks.baoding import BaodingTask

#: configured hand sims with a reset station, by ``params.sim.world``: the reset arm's sim
#: backend (sim_backends/reset_arm/backend.py) joins the scene of the one it names
SCENES: weakref.WeakValueDictionary[str, ShadowHandSim] = weakref.WeakValueDictionary()

#: where the balls come to rest in the held hand, in the palm's frame (palm position, its
#: rotation): found once per scene settings by letting them settle (:meth:`ShadowHandSim._rest_balls`)
_BALL_REST: dict[str, np.ndarray] = {}

#: J0 ≈ this · J1 for the coupled distal joints (tendon coefficients 0.00805 / 0.00705)
COUPLING_RATIO = 0.00805 / 0.00705


class SimParams(Params):
    """``params.sim`` of the Shadow Hand sim backend (units in names)."""

    seed: int = 0
    palm_tilt_rad: float = Field(0.15, ge=-0.5, le=0.5, description="mount tilt about world x "
                                 "(+: fingertips down; at 0.15 the fingers slope 8.6° down from the wrist)")
    balls: bool = Field(True, description="put the two Baoding balls in the palm at reset")
    balls_settle_s: float = Field(10.0, ge=0, le=60, description="place the balls where they come to rest in the "
                                  "held hand after this long (found once per scene); 0: at the palm centre, "
                                  "where they roll away (and the pair turns by itself) in the first seconds")
    # the MJCF's servo gains (OpenAI's model): kp 5 N·m/rad wrist, 1 N·m/rad fingers; the
    # joints' own damping (0.5 / 0.1 N·m·s/rad) stays in the model
    kp_wrist_nm_per_rad: float = Field(5.0, gt=0)
    kp_finger_nm_per_rad: float = Field(1.0, gt=0)
    kd_nms_per_rad: float = Field(0.0, ge=0, description="extra derivative gain of the firmware loop")
    ki_wrist_nm_per_rad_s: float = Field(20.0, ge=0, description="integral gain (removes the sag under gravity)")
    ki_finger_nm_per_rad_s: float = Field(4.0, ge=0)
    # the targets' ellipse and rate: the reference code's (google-research/pddm baoding_env.py)
    ball_target_radius_m: float = Field(0.02, gt=0, description="targets' semi-axis across the palm [m]")
    ball_target_radius_v_m: float = Field(0.036, gt=0, description="targets' semi-axis along the fingers [m]")
    ball_target_rate_rad_s: float = Field(float(2 * np.pi / 6), description="target rotation rate (+: counter-"
                                          "clockwise): a turn per 6 s (60 steps)")
    tracker: dict | None = Field(None, description="camera tracker options (sim_backends/shadow_hand/cameras.py: "
                                                   "TrackerOptions): balls_m from rendered stereo images, not truth")
    reset_station: bool = Field(False, description="add the ramp and the reset arm to the scene (docs/reset.md)")
    world: str = Field("hand", description="name under which the reset arm's sim backend finds this scene")
    gripper_force_n: float = Field(10.0, gt=0, le=40, description="the reset arm's jaw force limit [N] (sim_backends/reset_arm/model.py)")
    effects: dict[str, float] = Field(default_factory=dict, description="for calibration: what the hand's drives "
                                      "have that the MuJoCo model lacks (joint_friction_nm, joint_damping_nm_s, "
                                      "input_delay_s; checked by sim_backends/shadow_hand/firmware.py)")
    mjcf: str | None = Field(None, description="the scene from this MJCF file (a calibrated one: `hil calibrate "
                                               "--model <hand config>` writes it) instead of the built one")


def parse_sim_params(sim: dict, source: str | None) -> SimParams:
    try:
        out = parse_model(SimParams, dict(sim), source)
    except ConfigError as e:
        raise ConfigError(source, [(f"params.sim.{f}" if f else "params.sim", m) for f, m in e.problems]) from None
    try:
        effect_fields(out.effects)
    except ValueError as e:
        raise ConfigError(source, [("params.sim.effects", str(e))]) from None
    if out.mjcf is not None and out.reset_station:
        raise ConfigError(source, [("params.sim.mjcf", "a calibrated scene has no reset station; "
                                                       "set reset_station: false")])
    return out


#: MJCF custom numeric: the drives' target delay [s] (hilstack.calibration.mjcf_robot writes it)
DELAY_NUMERIC = "hilstack_input_delay_s"
#: the joints `hil calibrate --model <hand config>` fits by default: the wrist (the largest loads)
CALIBRATION_JOINTS = ("WRJ1", "WRJ0")


def hold_pose_q(name: str = "cupped") -> np.ndarray:
    """A hold pose of ``HOLD_POSES`` for all 24 joints [rad] (coupled J0 follow their J1)."""
    q = np.zeros(len(JOINT_NAMES))
    for k, v in HOLD_POSES[name].items():
        q[JOINT_NAMES.index(k)] = v
    for c, p in COUPLED_JOINTS.items():
        q[JOINT_NAMES.index(c)] = COUPLING_RATIO * q[JOINT_NAMES.index(p)]
    return q


class ShadowHandSim(LockstepSim):
    """The Shadow Hand with two Baoding balls in MuJoCo behind the driver contract."""
    params_type = ShadowHandParams

    def __init__(self, params: ShadowHandParams | None = None, source: str | None = None):
        super().__init__()
        self.source = source
        self.params = p = params or ShadowHandParams()
        self.sim = parse_sim_params(p.sim, source)
        self.spec = shadow_hand_spec(p)
        self.hand = None
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self.firmware: HandFirmware | None = None
        self.task: BaodingTask | None = None
        self.divergences = 0
        self._seq = 0
        self._badqacc_seen = 0
        self._diverged_pending = False
        self._ticks_per_step = int(round(TICK_S / PHYSICS_DT_S))
        self.tracker = None  # HandTracker when params.sim.tracker is set
        self._tracker_opts = None
        if self.sim.tracker is not None:
            from hilstack.sim_backends.shadow_hand.cameras import TrackerOptions

            try:
                self._tracker_opts = parse_model(TrackerOptions, dict(self.sim.tracker), source)
            except ConfigError as e:
                raise ConfigError(source, [(f"params.sim.tracker.{f}", m) for f, m in e.problems]) from None
        #: held while the scene is stepped; another robot in the scene (the reset arm)
        #: reads and writes it under this lock, and waits on it for the clock to advance
        self.world_lock = threading.Condition()

    #: measured − commanded actuated joint angles (used by `hil drive`)
    tracking_error = staticmethod(joint_tracking_error)

    @classmethod
    def calibration_bench(cls, params: ShadowHandParams | None = None) -> dict:
        """What `hil calibrate --model <hand config>` needs (hilstack.calibration.mjcf_robot): the
        scene's MjSpec (``params.sim.mjcf`` if set), each actuated joint's firmware loop (position
        PID: kp [N·m/rad], ki [N·m/(rad·s)], kd [N·m·s/rad], torque limit [N·m]; the integral
        clamped at the torque limit), the joints fitted (:data:`CALIBRATION_JOINTS`, the wrist: a
        fit over all 20 is 10x slower), the state columns of their positions and velocities and
        of every motor's reported effort (appended by the excitation recorder after the 48 joint
        channels), and that actions are normalized position targets (``low``/``high``: their
        [-1, 1] range in rad)."""
        from hilstack.drivers.shadow_hand.config import (
            ACTUATED_JOINTS,
            JOINT_HIGH_RAD,
            JOINT_LOW_RAD,
            hold_pose_action,
        )
        from hilstack.sim_backends.shadow_hand.model import scene_spec

        p = params or ShadowHandParams()
        s = parse_sim_params(p.sim, None)
        spec = mujoco.MjSpec.from_file(str(s.mjcf)) if s.mjcf else scene_spec(s.palm_tilt_rad)
        m = spec.compile()
        lim = m.actuator_ctrlrange[:len(ACTUATED_JOINTS), 1]
        loops = {}
        for i, j in enumerate(ACTUATED_JOINTS):
            wrist = j.startswith("WR")
            loops[f"robot0:{j}"] = {
                "mode": "position", "actuator": m.actuator(i).name,
                "kp_nm_per_rad": s.kp_wrist_nm_per_rad if wrist else s.kp_finger_nm_per_rad,
                "ki_nm_per_rad_s": s.ki_wrist_nm_per_rad_s if wrist else s.ki_finger_nm_per_rad_s,
                "kd_nm_s": s.kd_nms_per_rad, "tau_max_nm": float(lim[i])}
        nj = len(JOINT_NAMES)
        act = [JOINT_NAMES.index(j) for j in ACTUATED_JOINTS]
        fit = [JOINT_NAMES.index(j) for j in CALIBRATION_JOINTS]
        return {"spec": spec, "joints": [f"robot0:{j}" for j in CALIBRATION_JOINTS], "loops": loops,
                "loop_joints": [f"robot0:{j}" for j in ACTUATED_JOINTS],
                "q": fit, "qd": [nj + k for k in fit], "current": list(range(2 * nj, 2 * nj + len(act))),
                "loop_q": act, "loop_qd": [nj + k for k in act],
                "state_joints": {f"robot0:{j}": (i, nj + i) for i, j in enumerate(JOINT_NAMES)},
                "action": "goal_position_normalized", "low": JOINT_LOW_RAD[ACT_INDEX].tolist(),
                "high": JOINT_HIGH_RAD[ACT_INDEX].tolist(), "drop_bodies": ["ball0", "ball1"],
                "delay_numeric": DELAY_NUMERIC,
                # an excitation (hilstack.calibration.robot_rig): the emulator runs this sim, so effects
                # go to params.sim on both backends; balls parked; targets on a multi-sine about the
                # hold pose (normalized units); the motors' efforts recorded after the joint channels
                "excite": {"place": {"sim": "sim", "emulated": "sim"}, "bench": {"balls": False},
                           "driver": {"objects_in_state": False},  # parked balls: the efforts follow the joints
                           "mid": hold_pose_action(p.hold_pose).tolist(), "command": "position", "amplitude": 0.25,
                           "extra_state": "effort_nm", "extra_names": [f"{j}_effort" for j in ACTUATED_JOINTS],
                           "extra_unit": "N·m",
                           # the hand's clock (HAND_STATUS.t_fw_ms) stamps one whole telemetry cycle: a
                           # reading that reached the host late is still a sample at its device time
                           "whole_reading_clock": True}}

    # ------------------------------------------------------------------ lifecycle
    def _on_configure(self) -> None:
        s = self.sim
        edit = None
        if self._tracker_opts is not None:
            from hilstack.sim_backends.shadow_hand.cameras import scene_edit

            edit = scene_edit()
        station = StationGeometry() if s.reset_station else None
        other = SCENES.get(s.world) if station is not None else None
        if other is not None and other is not self and other.data is not None:
            raise ConfigError(self.source, [("params.sim.world", f"a hand scene named {s.world!r} is already "
                                             "running in this process; give each its own world name")])
        if s.mjcf is not None:
            spec = mujoco.MjSpec.from_file(str(s.mjcf))
            if edit is not None:
                edit(spec)
            try:
                self.hand = h = index_scene(spec)
            except (ValueError, KeyError) as e:
                raise ConfigError(self.source, [("params.sim.mjcf", f"{s.mjcf}: not a hand scene ({e})")]) from None
        else:
            self.hand = h = build_scene(s.palm_tilt_rad, station, s.gripper_force_n, edit=edit)
        self.model = h.model
        effects = dict(s.effects)
        nid = mujoco.mj_name2id(h.model, mujoco.mjtObj.mjOBJ_NUMERIC, DELAY_NUMERIC)
        if nid >= 0 and "input_delay_s" not in effects:  # a calibrated MJCF's identified target delay
            effects["input_delay_s"] = float(h.model.numeric_data[h.model.numeric_adr[nid]])
        self.data = mujoco.MjData(h.model)
        n = len(h.act_joint)
        kp = np.full(n, s.kp_finger_nm_per_rad)
        kp[:2] = s.kp_wrist_nm_per_rad  # WRJ1, WRJ0
        ki = np.full(n, s.ki_finger_nm_per_rad_s)
        ki[:2] = s.ki_wrist_nm_per_rad_s
        self.firmware = HandFirmware(FirmwareConfig(
            kp_nm_per_rad=kp,
            kd_nms_per_rad=np.full(n, s.kd_nms_per_rad),
            ki_nm_per_rad_s=ki,
            torque_limit_nm=h.torque_limit_nm.copy(),
            joint_low_rad=h.joint_low[h.act_joint],
            joint_high_rad=h.joint_high[h.act_joint],
            watchdog_s=self.params.firmware_watchdog_s,
            **effect_fields(effects),
        ))
        self._act_qadr = h.qpos_adr[h.act_joint]
        self._act_dadr = h.dof_adr[h.act_joint]
        self._palm = h.model.body("robot0:palm").id
        if self._tracker_opts is not None:
            from hilstack.sim_backends.shadow_hand.cameras import HandTracker

            mujoco.mj_forward(self.model, self.data)
            self.tracker = HandTracker(self.model, self.data, self._tracker_opts, self.spec.period_s)
        self.reset()
        if station is not None:
            SCENES[s.world] = self

    def _on_cleanup(self) -> None:
        if self.tracker is not None:
            self.tracker.close()
            self.tracker = None
        if SCENES.get(self.sim.world) is self:
            del SCENES[self.sim.world]
        with self.world_lock:
            self.model = self.data = None
            self.world_lock.notify_all()

    def reset(self, q_rad: np.ndarray | None = None, **planar_pose: float) -> None:
        """Hand at ``q_rad`` (24 joint angles; default: the cupped hold pose), balls at
        rest in the palm, firmware rebooted holding that pose, task time 0.

        ``planar_pose``: a reset request's ``x``, ``y``, ``yaw`` (the supervisor's default
        start pose, made for mobile robots) do not apply to a hand fixed to its mount and
        are ignored; any other key is an error."""
        unknown = sorted(set(planar_pose) - {"x", "y", "yaw"})
        if unknown:
            raise TypeError(f"shadow hand reset: unknown pose keys {unknown} (a hand takes q_rad only)")
        with self.world_lock:
            self._reset(q_rad)
            self.world_lock.notify_all()
        self._rehold()  # the held command is now the new pose, not what was held before the reset

    def _reset(self, q_rad: np.ndarray | None) -> None:
        m, d, h = self.model, self.data, self.hand
        mujoco.mj_resetData(m, d)  # the reset arm, if any, goes back to its parked pose too
        self._badqacc_seen = 0
        q = hold_pose_q(self.params.hold_pose) if q_rad is None else np.asarray(q_rad, dtype=np.float64).reshape(
            len(JOINT_NAMES))
        d.qpos[h.qpos_adr] = np.clip(q, h.joint_low, h.joint_high)
        mujoco.mj_forward(m, d)
        palm = d.xpos[self._palm].copy()
        rot = d.xmat[self._palm].reshape(3, 3).copy()
        normal = -rot[:, 1]  # the palm faces its local -y
        center = palm + rot @ np.array([0.0, -0.03, 0.05])
        # the balls across the palm centre (where they start rolling), or where they rest
        balls = center + np.array([[-0.022, 0.0, 0.0], [0.022, 0.0, 0.0]])
        rest = self._rest_balls(q_rad, balls) if self.sim.balls else None
        if rest is not None:
            balls = palm + rest @ rot.T
        for i, adr in enumerate(h.ball_qpos_adr):
            if self.sim.balls:
                d.qpos[adr:adr + 3] = balls[i]
            else:  # parked far below the hand: out of the way, still simulated
                d.qpos[adr:adr + 3] = (5.0 * (i + 1), 5.0, -1.0)
            d.qpos[adr + 3:adr + 7] = (1.0, 0.0, 0.0, 0.0)
        mujoco.mj_forward(m, d)
        task = BaodingTask(center_m=center, axis=normal, radius_m=self.sim.ball_target_radius_m,
                           radius_v_m=self.sim.ball_target_radius_v_m, rate_rad_s=self.sim.ball_target_rate_rad_s)
        if rest is not None:  # the targets' ellipse about the resting pair, starting where it rests
            mid = balls.mean(0) - center
            task = replace(task, center_m=center + mid - normal * (mid @ normal))
            task = replace(task, phase0_rad=task.pair_phase(balls))
        self.task = task
        self.firmware.reset(d.qpos[self._act_qadr].copy())
        # the hand has been holding this pose: the loops' integrals carry the gravity load
        self.firmware.preload(d.qfrc_bias[self._act_dadr])
        self._seq = 0
        self._rehold()  # the firmware rebooted holding this pose: the contract's held command is it too
        if self.tracker is not None:
            self.tracker.start(self.sim_time_s)

    def place_balls(self) -> None:
        """The lab's hands (the emulator's lab fixture, drivers/fixture.py ``place``): both balls
        put down at rest where they rest in the palm of the hand holding its hold pose (the
        reset's resting place, in the palm's frame as it is now), or across the palm centre
        before any reset found it. The hand, its firmware and the clock run on untouched: a
        person puts the balls back, not the hand."""
        with self.world_lock:
            m, d, h = self.model, self.data, self.hand
            palm, rot = d.xpos[self._palm].copy(), d.xmat[self._palm].reshape(3, 3).copy()
            rest = _BALL_REST.get(self._rest_key())
            if rest is None:
                balls = palm + rot @ np.array([0.0, -0.03, 0.05]) + np.array([[-0.022, 0.0, 0.0], [0.022, 0.0, 0.0]])
            else:
                balls = palm + rest @ rot.T
            for i, (qa, da) in enumerate(zip(h.ball_qpos_adr, h.ball_dof_adr, strict=True)):
                d.qpos[qa:qa + 3] = balls[i]
                d.qpos[qa + 3:qa + 7] = (1.0, 0.0, 0.0, 0.0)
                d.qvel[da:da + 6] = 0.0
            mujoco.mj_forward(m, d)
            self.world_lock.notify_all()

    def _rest_key(self) -> str:
        """What the balls' resting place depends on: the scene's settings and the hold pose."""
        return self.params.hold_pose + self.sim.model_dump_json(exclude={"seed", "world", "tracker"})

    def _rest_balls(self, q_rad: np.ndarray | None, start_m: np.ndarray) -> np.ndarray | None:
        """(2, 3) where the balls come to rest in the hand holding its hold pose, in the palm's
        frame (offset from the palm body, its axes), or None (``balls_settle_s`` 0, or a reset
        to another pose). Placed across the palm centre the balls roll for a few seconds
        before they settle, and their rolling turns the pair ~60° with the hand still (the
        reference code starts from a keyframe with the balls at rest: google-research/pddm
        ``baoding_env.py``, ``init_qpos = key_qpos[0]``). Found once per scene settings by
        letting them settle from ``start_m`` (world) for ``balls_settle_s`` in the held hand
        (under the world lock)."""
        s = self.sim
        if s.balls_settle_s <= 0 or q_rad is not None:
            return None
        key = self._rest_key()
        if key not in _BALL_REST:
            m, d, h = self.model, self.data, self.hand
            for i, adr in enumerate(h.ball_qpos_adr):
                d.qpos[adr:adr + 3] = start_m[i]
                d.qpos[adr + 3:adr + 7] = (1.0, 0.0, 0.0, 0.0)
            mujoco.mj_forward(m, d)
            self.firmware.reset(d.qpos[self._act_qadr].copy())
            self.firmware.preload(d.qfrc_bias[self._act_dadr])
            self._advance_locked(s.balls_settle_s)
            palm, rot = d.xpos[self._palm].copy(), d.xmat[self._palm].reshape(3, 3).copy()
            _BALL_REST[key] = (self.balls_m() - palm) @ rot
            mujoco.mj_resetData(m, d)  # back to the reset's start: the hand at its pose, time 0
            self._badqacc_seen = 0
            d.qpos[h.qpos_adr] = np.clip(hold_pose_q(self.params.hold_pose), h.joint_low, h.joint_high)
            mujoco.mj_forward(m, d)
        return _BALL_REST[key]

    # ------------------------------------------------------------------ physics
    def advance(self, duration_s: float) -> None:
        """Integrate ``duration_s`` in 1 ms firmware ticks (one MuJoCo step each)."""
        with self.world_lock:
            self._advance_locked(duration_s)
            self.world_lock.notify_all()

    def _advance_locked(self, duration_s: float) -> None:
        m, d, fw = self.model, self.data, self.firmware
        qa, da = self._act_qadr, self._act_dadr
        n = int(round(duration_s / TICK_S))
        nh = len(self._act_qadr)  # the hand's motors come first; the reset arm's servos follow
        for _ in range(n):
            d.ctrl[:nh] = fw.tick(d.time, d.qpos[qa], d.qvel[da])
            for _ in range(self._ticks_per_step):
                mujoco.mj_step(m, d)
        bad = int(d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number)
        if bad > self._badqacc_seen:
            # MuJoCo reset the diverged state itself: flag the readings, do not hide it
            self.divergences += bad - self._badqacc_seen
            self._diverged_pending = True
        self._badqacc_seen = bad

    def _advance(self, duration_s: float) -> None:
        self.advance(duration_s)

    def joint_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(angles [rad] (24,), velocities [rad/s] (24,), motor efforts [N·m] (20,))."""
        d, h = self.data, self.hand
        return d.qpos[h.qpos_adr].copy(), d.qvel[h.dof_adr].copy(), self.firmware.effort_nm.copy()

    def balls_m(self) -> np.ndarray:
        """(2, 3) ball centre positions [m], world frame."""
        return np.stack([self.data.xpos[b].copy() for b in self.hand.ball_body])

    # ------------------------------------------------------------------ contract
    def _read(self) -> Observation:
        self._seq += 1
        q, qd, eff = self.joint_state()
        fw = self.firmware
        balls = self.balls_m()
        diverged, self._diverged_pending = self._diverged_pending, False
        dropped = bool(self.sim.balls and self.task.dropped(balls))
        flags = {
            "sim_diverged": diverged,
            "watchdog": fw.watchdog_tripped,
            "estop": fw.estop,
            "motor_fault": bool(fw.motor_fault_mask),
            "object_dropped": dropped,
        }
        extras = {"effort_nm": eff, "balls_m": balls, "ball_targets_m": self.task.targets(self.sim_time_s),
                  "mode": fw.mode, "motor_fault_mask": fw.motor_fault_mask}
        if self.tracker is not None:
            # the tracker's balls replace the truth; stale balls are flagged (the hand's own
            # reading stays ok, as on the real driver's ball streams)
            cam = self.tracker.observe(self.data, self.sim_time_s, self._seq)
            flags["stale_objects"] = cam.flag("stale_objects")
            extras.update(balls_m=self.tracker.balls_world(cam), balls_true_m=balls, ball_confidence=cam.state[6:],
                          balls_age_s=cam.extras["objects_age_s"], image=cam.extras["image"],
                          image_encoded=cam.extras["image_encoded"])
        return Observation(
            t_s=self.sim_time_s, seq=self._seq, ok=not diverged, flags=flags, extras=extras,
            # with a tracker, the state's balls are the tracked ones (what a real rig's planner sees)
            state=np.concatenate([q, qd] + ([np.asarray(extras["balls_m"]).reshape(-1)]
                                           if self.params.objects_in_state else [])),
        )

    def _hold_command(self, obs: Observation) -> np.ndarray:
        return to_action(obs.state[ACT_INDEX])

    def _write(self, action: np.ndarray) -> None:
        if not self.firmware.set_targets(0, to_joint_rad(action), self.sim_time_s):
            raise RuntimeError(f"firmware refused the targets (mode {self.firmware.mode}, e-stop {self.firmware.estop})")

    def _stop(self) -> np.ndarray | None:
        """Hold the measured position (firmware targets = measured angles); returns that action."""
        if self.data is None:
            return None
        q = self.data.qpos[self._act_qadr].copy()
        self.firmware.set_targets(0, q, self.sim_time_s)
        return to_action(q)

    def _health(self) -> Health:
        return Health(
            ok=self.data is not None, last_error=self.last_error,
            extra={"sim_time_s": self.sim_time_s, "faults": 0 if self.firmware is None else self.firmware.faults,
                   "sim_divergences": self.divergences, "backend": "sim"},
        )
