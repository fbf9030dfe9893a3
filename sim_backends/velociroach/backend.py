"""VelociRoACH MuJoCo backend: the driver contract in-process, in lockstep.

Each ``tick()`` advances one control period (0.1 s): 1 kHz firmware ticks
(:mod:`.firmware`), each followed by one MuJoCo step (``physics_dt_s`` = 1 ms) with the
motor voltage from the DC-motor/battery model. See docs/velociroach.md "Simulation".

Frames: world x/y on the ground (+x uphill on a slope), z up; body x forward, y left.
Quaternions are (w, x, y, z). The state is ``STATE_NAMES`` of drivers/velociroach/config.py:
pose (x, y, z and orientation) from the simulated mocap stream (rate, latency, noise,
dropout: the last good sample is held), world-frame velocity and body rates from the
simulator, crank angles/velocities from the (14-bit) encoders, back-EMF and battery voltage.

Public API for the emulator: ``VelociRoachSim(params)``, ``configure()``, ``reset()``,
``firmware``, ``advance(duration_s)``, ``telemetry()``, ``mocap_pose()``, ``sim_time_s``,
``set_perturbation(name, value)``, ``apply_perturbations(settings)`` (typed settings,
:mod:`hilstack.tasks.perturbations`).
"""

from __future__ import annotations

import copy
import ctypes
import math
from typing import Annotated, Any, Literal

import mujoco
import numpy as np
from pydantic import Field

from hilstack.configs.schema import ConfigError, Params, parse_model
from hilstack.drivers.base import Flag, Freshness, Health, Inputs, Observation
from hilstack.drivers.velociroach.config import VelociRoachParams, fault_flags, quat_to_rpy, velociroach_spec
from hilstack.sim_backends.base import LockstepSim
from hilstack.sim_backends.velociroach.firmware import (
    FAULT_LOW_BATTERY,
    FAULT_MOTOR,
    TICK_S,
    Firmware,
    FirmwareConfig,
    default_ff_v_per_rps,
)
from hilstack.sim_backends.velociroach.firmware import TICK_HZ as FW_TICK_HZ
from hilstack.sim_backends.velociroach.model import (
    LEG_NAMES,
    Geometry,
    GroundLook,
    build_mjcf,
    heightfield,
    initial_crank_angles_rad,
)

TWO_PI = 2.0 * math.pi
ENCODER_COUNTS = 1 << 14  # 14-bit magnetic crank encoders
_ENCODER_RES_RAD = TWO_PI / ENCODER_COUNTS

#: terrain presets: Coulomb friction, contact softness (solref time constant [s], damping ratio),
#: roughness (RMS height [m] of a seeded heightfield, 0 = plane) and its correlation length [m],
#: and how it looks to the chassis camera (colours of the ground texture; docs/mbrl.md, "Terrains
#: the robot can see")
TERRAINS: dict[str, dict[str, Any]] = {
    "carpet": {"friction": 1.0, "solref": (0.02, 1.0), "roughness_m": 0.0, "correlation_m": 0.0,
               "look": GroundLook(rgb=(0.45, 0.14, 0.12), mark_rgb=(0.28, 0.08, 0.07), marks=0.4)},
    "styrofoam": {"friction": 0.6, "solref": (0.005, 1.0), "roughness_m": 0.0, "correlation_m": 0.0,
                  "look": GroundLook(rgb=(0.90, 0.90, 0.87), mark_rgb=(0.78, 0.78, 0.75), marks=0.15)},
    "gravel": {"friction": 0.8, "solref": (0.006, 1.0), "roughness_m": 0.003, "correlation_m": 0.02,
               "look": GroundLook(rgb=(0.55, 0.53, 0.50), mark_rgb=(0.30, 0.29, 0.27), marks=0.45)},
    "turf": {"friction": 0.9, "solref": (0.015, 1.0), "roughness_m": 0.002, "correlation_m": 0.03,
             "look": GroundLook(rgb=(0.20, 0.50, 0.18), mark_rgb=(0.12, 0.35, 0.10), marks=0.4)},
}

#: rough terrain: map beyond ±period/2 so the robot (±7 cm) always stands on it
_WRAP_MARGIN_M = 0.25

_SIM_DIVERGED = Flag.SIM_DIVERGED.value

PERTURBATIONS = ("missing_leg", "payload_kg", "mocap_offset_m", "slope_deg", "heading_offset_deg", "terrain")


_Scale = Annotated[float, Field(gt=0, le=2, allow_inf_nan=False)]


class SimParams(Params):
    """``params.sim`` of the VelociRoACH sim backend (units in names; sources in docs)."""

    seed: int = 0
    physics_dt_s: float = Field(0.001, gt=0, le=0.002, description="MuJoCo timestep; firmware runs at 1 kHz")
    # terrain
    terrain: Literal["carpet", "styrofoam", "gravel", "turf"] = "carpet"
    friction: float | None = Field(None, gt=0, description="override the preset's friction")
    solref: tuple[float, float] | None = Field(None, description="override the preset's contact solref")
    roughness_m: float | None = Field(None, ge=0, description="override the preset's RMS roughness")
    slope_deg: float = Field(0.0, ge=-30, le=30, description="ground slope, + is uphill along world +x")
    terrain_half_size_m: float = Field(2.0, gt=0, description="rough terrains: half the period of the (endless) map")
    terrain_cell_m: float = Field(0.01, gt=0)
    # camera
    camera_px: int = Field(0, ge=0, le=256, description="side of the square RGB image of the chassis camera "
                           "('front') in Observation.extras['image'] at every read (0: no images)")
    # body
    chassis_mass_kg: float = Field(0.030, gt=0)
    leg_mass_kg: float = Field(0.001, gt=0)
    leg_length_m: float = Field(0.010, gt=0, description="hip to foot centre (the crank's eccentricity)")
    foot_radius_m: float = Field(0.008, gt=0)
    phase_lr_deg: float = Field(180.0, description="right crank minus left crank at reset (180: alternating tripod)")
    # motor (per side)
    motor_resistance_ohm: float = Field(3.6, gt=0)
    motor_k_v_s_per_rad: float = Field(1.5e-3, gt=0, description="back-EMF constant = torque constant [N·m/A]")
    gear_ratio: float = Field(21.3, gt=0)
    gear_efficiency: float = Field(0.8, gt=0, le=1)
    rotor_inertia_kgm2: float = Field(1.0e-9, ge=0)
    current_limit_a: float = Field(1.5, gt=0, description="H-bridge current limit (crank torque limit)")
    leg_speed_scale: tuple[_Scale, _Scale] = Field(
        (1.0, 1.0), description="(left, right): the side's crank runs at this times its leg-velocity command "
        "(a miscalibrated drive side; leg_velocity mode only; 1 = nominal)")
    # battery (1-cell LiPo)
    battery_full_v: float = Field(4.2, gt=0)
    battery_empty_v: float = Field(3.5, gt=0)
    battery_capacity_mah: float = Field(300.0, gt=0)
    battery_resistance_ohm: float = Field(0.4, ge=0)
    battery_soc: float = Field(0.9, ge=0, le=1, description="state of charge at reset")
    idle_current_a: float = Field(0.08, ge=0, description="board + radio draw")
    # firmware
    kp_duty_per_rps: float = Field(0.05, ge=0)
    ki_duty_per_rev: float = Field(1.5, ge=0)
    kd_duty_per_rps2: float = Field(0.0, ge=0)
    ff_v_per_rps: float | None = Field(None, description="back-EMF feed-forward; default k·G·2π")
    max_duty: float = Field(1.0, gt=0, le=1)
    low_battery_v: float = Field(3.4, gt=0)
    overcurrent_a: float = Field(1.4, gt=0)
    # sensors
    mocap_rate_hz: float = Field(120.0, gt=0)
    mocap_latency_s: float = Field(0.005, ge=0)
    mocap_noise_m: float = Field(0.0003, ge=0)
    mocap_noise_rad: float = Field(0.002, ge=0)
    mocap_dropout: float = Field(0.0, ge=0, lt=1, description="probability a mocap sample is lost")
    gyro_noise_rps: float = Field(0.01, ge=0, description="rad/s, per telemetry sample")
    accel_noise_mps2: float = Field(0.05, ge=0)
    bemf_noise_v: float = Field(0.005, ge=0)
    vbat_noise_v: float = Field(0.002, ge=0)
    # payload towed behind the robot
    payload_friction: float = Field(0.5, ge=0, description="sliding friction of a towed payload")
    # calibration hook (hil calibrate writes it into sim_params.yaml, docs/calibration.md):
    # the initial value of the payload_kg perturbation, so a calibrated payload loads by config
    payload_kg: float = Field(0.0, ge=0, description="towed payload at start [kg] (perturbation payload_kg)")


def bit_generator_pointers(rng: np.random.Generator) -> tuple[int, int, int]:
    """``(state, next_uint64, next_double)`` addresses of a Generator's bit generator (numpy's
    public ctypes interface): the compiled loop draws from the same stream through them. The
    Generator must outlive their use."""
    c = rng.bit_generator.ctypes
    return (c.state_address, ctypes.cast(c.next_uint64, ctypes.c_void_p).value,
            ctypes.cast(c.next_double, ctypes.c_void_p).value)


def parse_sim_params(sim: dict, source: str | None) -> SimParams:
    """Validate ``params.sim``; errors name ``params.sim.<field>`` and the file."""
    try:
        return parse_model(SimParams, dict(sim), source)
    except ConfigError as e:
        raise ConfigError(source, [(f"params.sim.{f}" if f else "params.sim", m) for f, m in e.problems]) from None


class VelociRoachSim(LockstepSim):
    """The VelociRoACH in MuJoCo behind the driver contract."""
    params_type = VelociRoachParams

    #: run the firmware's leg-velocity PID inlined in the stepping loop (False: every tick
    #: through Firmware.tick; the same floats, about a third slower: tools/bench_sim.py)
    inline_firmware = True
    #: run the inlined loop compiled by numba when it is installed (the ``speed`` extra;
    #: compiled.py): the same floats; False: in Python (the emulator, which runs at 1x real
    #: time and must not stall on a first compile)
    compiled_firmware = True

    def __init__(self, params: VelociRoachParams | None = None, source: str | None = None):
        super().__init__()
        self.params = p = params or VelociRoachParams()
        self.source = source
        self.sim = parse_sim_params(p.sim, source)
        self.spec = velociroach_spec(p)
        s = self.sim
        self.firmware = Firmware(
            FirmwareConfig(
                kp_duty_per_rps=s.kp_duty_per_rps,
                ki_duty_per_rev=s.ki_duty_per_rev,
                kd_duty_per_rps2=s.kd_duty_per_rps2,
                ff_v_per_rps=s.ff_v_per_rps
                if s.ff_v_per_rps is not None
                else default_ff_v_per_rps(s.motor_k_v_s_per_rad, s.gear_ratio),
                max_duty=s.max_duty,
                watchdog_s=p.firmware_watchdog_s,
                low_battery_v=s.low_battery_v,
                overcurrent_a=s.overcurrent_a,
            )
        )
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self.perturbations: dict[str, Any] = {
            "missing_leg": None,
            "payload_kg": s.payload_kg,
            "mocap_offset_m": np.zeros(3),
            "slope_deg": s.slope_deg,
            "heading_offset_deg": 0.0,
            "terrain": None,  # None: params.sim.terrain; another preset takes effect at the next reset
        }
        self._built_terrain: str | None = None
        self._camera = None  # OffscreenRenderer of the chassis camera (camera_px > 0), made on first read
        self._seq = 0
        self.mocap_samples = 0
        self.mocap_dropped = 0
        self.divergences = 0  # MuJoCo integration blow-ups (it resets itself; readings flagged)
        self._badqacc_seen = 0
        self._diverged_pending = False
        # the inputs the state fuses, on sim time, with the same deadlines as the radio driver
        self.inputs = Inputs(
            Freshness("pose", p.pose_deadline_s, Flag.STALE_POSE),
            Freshness("telemetry", p.telemetry_deadline_s, Flag.STALE_TELEMETRY),
        )
        self._telemetry_input = self.inputs["telemetry"]
        self._pose_input = self.inputs["pose"]
        self._telemetry_index = self.spec.state.index("wx")  # the state from here on is telemetry
        self._fault_flags: dict[int, dict[str, bool]] = {}  # fault_flags of each bitmask seen

    def __deepcopy__(self, memo: dict[int, Any]) -> VelociRoachSim:
        """An independent sim at the same instant (planners and calibration copy one as an
        oracle): everything is copied, then the compiled loop's views of MjData are made anew
        on the copy's (copied as they were, they were arrays of their own, no longer MjData's:
        the copy's compiled loop stepped with a stale command and state). The chassis camera's
        GL context is not copied; the copy makes its own at its first image. (The addresses of
        the mocap noise stream are the copy's own at its first tick, ``_advance``.)"""
        new = type(self).__new__(type(self))
        memo[id(self)] = new
        for k, v in self.__dict__.items():
            if k not in ("_camera", "_views"):
                setattr(new, k, copy.deepcopy(v, memo))
        new._camera = None
        if new.data is not None:
            new._views = (new.data.qpos, new.data.qvel, new.data.ctrl)
        return new

    # ------------------------------------------------------------------ model
    def terrain_name(self) -> str:
        """The terrain the next reset builds: the ``terrain`` perturbation, else ``params.sim.terrain``."""
        return self.perturbations["terrain"] or self.sim.terrain

    def terrain(self) -> dict[str, Any]:
        """The effective terrain settings: the preset of :meth:`terrain_name`, with the
        ``params.sim`` overrides (friction, solref, roughness) when it is the configured one."""
        s = self.sim
        name = self.terrain_name()
        t = dict(TERRAINS[name])
        if name != s.terrain:
            return t
        if s.friction is not None:
            t["friction"] = s.friction
        if s.solref is not None:
            t["solref"] = tuple(s.solref)
        if s.roughness_m is not None:
            t["roughness_m"] = s.roughness_m
        return t

    def _on_configure(self) -> None:
        self._build()
        self.reset()
        self._load_kernel()

    def _load_kernel(self) -> None:
        """Load (or, with an empty cache, compile) the compiled loop now, for the argument types
        :meth:`_advance` passes, without running it: lazily, the first tick took 1.3 s with the
        cache warm (at load 3) and tens of seconds without, longer than a reset supervisor's 2 s
        state timeout when that tick came in answer to a reset."""
        kern = self._kernel()
        if kern is None:
            return
        import numba

        run, step_fn = kern
        args = (step_fn, self.model._address, self.data._address, *self._views, self._v_l, self._v_r, 1, 1,
                np.zeros(15), np.zeros(32), *self._rng_mocap_pointers, self._mocap_rows, self._mocap_ist,
                self._tile_offset)
        run.compile(tuple(numba.typeof(a) for a in args))

    def _build(self) -> None:
        """The MuJoCo model and data of the current terrain (:meth:`terrain_name`)."""
        s = self.sim
        k, gr, eta, r = s.motor_k_v_s_per_rad, s.gear_ratio, s.gear_efficiency, s.motor_resistance_ohm
        # crank torque = gain·V − damping·ω_crank (the DC motor through the gearbox)
        self._gain_nm_per_v = k * gr * eta / r
        self._damping_nms = k * k * gr * gr * eta / r
        self._bemf_v_per_rad_s = k * gr  # motor back-EMF per crank rad/s
        terr = self.terrain()
        hf = None
        if terr["roughness_m"] > 0:
            # a periodic map of period 2·terrain_half_size_m plus a margin on every side
            self._period_cells = int(round(2 * s.terrain_half_size_m / s.terrain_cell_m))
            self._margin_cells = int(math.ceil(_WRAP_MARGIN_M / s.terrain_cell_m))
            self._period_m = self._period_cells * s.terrain_cell_m
            n = self._period_cells + 2 * self._margin_cells + 1
            half = 0.5 * (n - 1) * s.terrain_cell_m
            # heights in [0, 1] scaled by zmax; RMS of a filtered Gaussian field ≈ zmax/6
            hf = (n, half, 6.0 * terr["roughness_m"])
        geom = Geometry(chassis_mass_kg=s.chassis_mass_kg, leg_mass_kg=s.leg_mass_kg, leg_length_m=s.leg_length_m,
                        foot_radius_m=s.foot_radius_m,
                        armature_kgm2=s.rotor_inertia_kgm2 * gr * gr)
        self._geometry = geom
        xml = build_mjcf(
            timestep_s=s.physics_dt_s,
            motor_gain_nm_per_v=self._gain_nm_per_v,
            motor_damping_nms=self._damping_nms,
            torque_limit_nm=k * gr * eta * s.current_limit_a,
            friction=terr["friction"],
            solref=terr["solref"],
            solimp=(0.9, 0.95, 0.001),
            slope_deg=self.perturbations["slope_deg"],
            hfield=hf,
            geometry=geom,
            look=terr["look"],
        )
        m = mujoco.MjModel.from_xml_string(xml)
        if hf is not None:
            z = heightfield(self._period_cells, self._margin_cells, terr["correlation_m"] / s.terrain_cell_m, s.seed)
            m.hfield_data[:] = z.ravel().astype(np.float32)
            self._hfield_zmax = hf[2]
        else:
            self._hfield_zmax = 0.0
        self.model = m
        self.data = mujoco.MjData(m)
        self._views = (self.data.qpos, self.data.qvel, self.data.ctrl)  # for the compiled loop
        self._q_l = [m.joint(f"hip_l{o}").qposadr[0] for o in "fma"]
        self._q_r = [m.joint(f"hip_r{o}").qposadr[0] for o in "fma"]
        self._v_l = m.joint("hip_lm").dofadr[0]
        self._v_r = m.joint("hip_rm").dofadr[0]
        self._chassis = m.body("chassis").id
        self._leg_geoms = {n: [g for g in range(m.ngeom) if m.geom(g).name.startswith(n + "_")] for n in LEG_NAMES}
        self._leg_contype = {g: int(m.geom_contype[g]) for gs in self._leg_geoms.values() for g in gs}
        self._sensor_flag = int(mujoco.mjtDisableBit.mjDSBL_SENSOR)
        m.opt.disableflags |= self._sensor_flag  # sensors are evaluated on demand in telemetry()
        self._apply_missing_leg()
        self._built_terrain = self.terrain_name()
        self._close_camera()  # its GL context holds the old model's textures

    def _on_cleanup(self) -> None:
        self._close_camera()
        self.model = self.data = None

    def _close_camera(self) -> None:
        if self._camera is not None:
            self._camera.close()
            self._camera = None

    def render_camera(self, px: int | None = None) -> np.ndarray:
        """(px, px, 3) uint8 RGB of the chassis camera ``front`` at the current state
        (default size ``params.sim.camera_px``); needs an offscreen GL (``MUJOCO_GL=egl``)."""
        px = int(px or self.sim.camera_px or 64)
        if self._camera is None or self._camera.height_px != px:
            from hilstack.sim_backends.rendering import OffscreenRenderer

            self._close_camera()
            self._camera = OffscreenRenderer(self.model, px, px)
        return self._camera.render(self.data, "front")

    def reset(self, x: float = 0.0, y: float = 0.0, yaw: float = 0.0) -> None:
        """Robot at (x, y) [m] heading ``yaw`` [rad], legs in tripod stance, battery at its
        initial charge, firmware rebooted, sensor noise streams reseeded; on the terrain the
        ``terrain`` perturbation names (the world is rebuilt when it changed)."""
        if self.terrain_name() != self._built_terrain:
            self._build()
        m, d, s = self.model, self.data, self.sim
        mujoco.mj_resetData(m, d)
        self._badqacc_seen = 0  # mj_resetData clears MuJoCo's warning counters
        ql, qr = initial_crank_angles_rad(math.radians(s.phase_lr_deg))
        for a in self._q_l:
            d.qpos[a] = ql
        for a in self._q_r:
            d.qpos[a] = qr
        # standing on the tripod pointing down: hip at spoke + foot radius above the ground
        g = self._geometry
        z0 = g.leg_length_m + g.foot_radius_m - g.hip_z_m + 0.001 + self._hfield_zmax
        d.qpos[0:3] = (x, y, z0)
        d.qpos[3:7] = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))
        self._tile_offset = np.zeros(3)
        self._wrap()
        mujoco.mj_forward(m, d)
        self.firmware.reset()
        ss = np.random.SeedSequence(s.seed)
        self._rng_mocap, self._rng_telem = (np.random.default_rng(c) for c in ss.spawn(2))
        self._rng_mocap_pointers = bit_generator_pointers(self._rng_mocap)  # the compiled loop draws from it too
        self._soc = s.battery_soc
        self._i_l = self._i_r = 0.0
        self._vbat = self._ocv()
        self._t = 0.0
        self._mocap_period = 1.0 / s.mocap_rate_hz
        self._mocap_next_t = 0.0
        # the mocap samples not delivered yet, oldest first: rows [head, tail) of a buffer that
        # the compiled loop writes too (arrival time, sample time, position, quaternion wxyz,
        # ok: not dropped, finite)
        self._mocap_rows = np.empty((64, 11))
        self._mocap_head = self._mocap_tail = 0
        self._mocap_bad_end = 0  # the row after the newest lost or non-finite sample (0: none queued)
        self._mocap_ist = np.zeros(4, dtype=np.int64)  # the compiled loop's tail, counts and bad end
        self._mocap_latest: tuple[float, tuple[float, ...], tuple[float, ...]] | None = None
        self._mocap_latest_ok = False
        self.inputs.start(self.sim_time_s)
        self._mocap_sample()
        self._mocap_next_t = self._mocap_period
        self._deliver_mocap(0.0 + s.mocap_latency_s)
        self._seq = 0
        self._rehold()  # the firmware rebooted: hold what it runs now (zero)

    def _wrap(self) -> None:
        """On a (periodic) heightfield, move the robot back by one terrain period when it
        nears an edge; ``_tile_offset`` keeps reported positions continuous."""
        if self._hfield_zmax <= 0.0:
            return  # an infinite plane
        period = self._period_m
        qpos = self.data.qpos
        for i in (0, 1):
            if qpos[i] > 0.5 * period:
                qpos[i] -= period
                self._tile_offset[i] += period
            elif qpos[i] < -0.5 * period:
                qpos[i] += period
                self._tile_offset[i] -= period

    def true_position_m(self) -> np.ndarray:
        """Ground-truth chassis position [m] in the world frame (continuous across wraps)."""
        return self.data.qpos[0:3] + self._tile_offset

    def _ocv(self) -> float:
        s = self.sim
        return s.battery_empty_v + (s.battery_full_v - s.battery_empty_v) * self._soc

    # ------------------------------------------------------------------ perturbations
    def set_perturbation(self, name: str, value: Any) -> None:
        """Switch a perturbation mid-run.

        * ``missing_leg``: a leg name (``lf lm la rf rm ra``), a list of them, or None.
        * ``payload_kg``: mass [kg] towed behind the robot (sliding friction ``payload_friction``).
        * ``mocap_offset_m``: a bias added to the mocap position (float: along x, or 3 floats).
        * ``slope_deg``: ground slope, + uphill along world +x (tilts gravity).
        * ``heading_offset_deg``: pose miscalibration, the reported heading minus the true
          one (the mocap orientation is rotated about world z; position and velocities stay
          true).
        * ``terrain``: a preset of :data:`TERRAINS` (None: ``params.sim.terrain``). The one
          perturbation that waits for the next :meth:`reset`: a new ground under a robot
          standing on the old one could put its feet inside it, so terrains change per episode.
        """
        if name not in PERTURBATIONS:
            raise KeyError(f"unknown perturbation {name!r}; known: {list(PERTURBATIONS)}")
        if name == "missing_leg":
            legs = [] if value in (None, "", []) else ([value] if isinstance(value, str) else list(value))
            bad = [n for n in legs if n not in LEG_NAMES]
            if bad:
                raise ValueError(f"unknown leg(s) {bad}; legs are {list(LEG_NAMES)}")
            self.perturbations[name] = legs or None
            self._apply_missing_leg()
        elif name == "payload_kg":
            if not (float(value) >= 0):
                raise ValueError(f"payload_kg must be >= 0, got {value!r}")
            self.perturbations[name] = float(value)
            if self.data is not None and value == 0:
                self.data.xfrc_applied[self._chassis] = 0.0
        elif name == "mocap_offset_m":
            v = np.asarray(value, dtype=float)
            self.perturbations[name] = np.array([float(v), 0.0, 0.0]) if v.ndim == 0 else v.reshape(3).copy()
        elif name == "slope_deg":
            self.perturbations[name] = float(value)
            if self.model is not None:
                a = math.radians(float(value))
                self.model.opt.gravity[:] = (-9.81 * math.sin(a), 0.0, -9.81 * math.cos(a))
        elif name == "terrain":
            if value not in (None, "") and value not in TERRAINS:
                raise ValueError(f"unknown terrain {value!r}; terrains are {list(TERRAINS)}")
            self.perturbations[name] = value or None
        elif name == "heading_offset_deg":
            if not math.isfinite(float(value)):
                raise ValueError(f"heading_offset_deg must be finite, got {value!r}")
            self.perturbations[name] = float(value)

    def apply_perturbations(self, settings: Any) -> None:
        """Set every perturbation from a :class:`hilstack.tasks.perturbations.PerturbationSettings`
        (validated; unset fields go back to none), mid-episode included."""
        for name, value in settings.as_backend().items():
            self.set_perturbation(name, value)

    def _apply_missing_leg(self) -> None:
        m = self.model
        if m is None:
            return
        missing = self.perturbations["missing_leg"] or []
        for n, gs in self._leg_geoms.items():
            for g in gs:
                m.geom_contype[g] = 0 if n in missing else self._leg_contype[g]
                m.geom_rgba[g, 3] = 0.15 if n in missing else 1.0

    # ------------------------------------------------------------------ integration
    def advance(self, duration_s: float) -> None:
        """Integrate physics and the 1 kHz firmware for ``duration_s`` [s] of sim time."""
        self._advance(duration_s)

    def _advance(self, duration_s: float) -> None:
        m, d, s, fw = self.model, self.data, self.sim, self.firmware
        n = max(1, round(duration_s / TICK_S))
        substeps = max(1, round(TICK_S / s.physics_dt_s))
        # hot loop: locals, Python floats (``.item``: numpy scalars are several times slower in
        # arithmetic), the firmware's velocity PID inlined while it runs (see tools/bench_sim.py)
        qvel, ctrl = d.qvel, d.ctrl
        vl_i, vr_i = self._v_l, self._v_r
        r_m = s.motor_resistance_ohm
        ke = self._bemf_v_per_rad_s
        i_max = s.current_limit_a
        r_b = s.battery_resistance_ohm
        cap_as = s.battery_capacity_mah * 3.6
        idle = s.idle_current_a
        v_empty, v_span = s.battery_empty_v, s.battery_full_v - s.battery_empty_v
        payload = self.perturbations["payload_kg"]
        soc, vbat = self._soc, self._vbat
        i_l, i_r = self._i_l, self._i_r
        step = mujoco.mj_step
        tick = fw.tick
        inv2pi = 1.0 / TWO_PI
        t = self._t
        mocap_next = self._mocap_next_t - 1e-9
        # The firmware's leg-velocity PID (Firmware.tick, same operations in the same order),
        # inlined for as long as nothing but the PID runs: leg-velocity mode, commanded, the
        # watchdog not tripped. A tick on which the watchdog would trip, and every tick after
        # it, goes through Firmware.tick. tests/velociroach: both paths give identical floats.
        fast = (self.inline_firmware and fw.mode == "leg_velocity" and fw.last_cmd_s is not None
                and not fw.watchdog_tripped)
        if fast:
            c = fw.config
            sp_l, sp_r = fw.setpoint_l, fw.setpoint_r
            kp, ki, ff_v = c.kp_duty_per_rps, c.ki_duty_per_rev, c.ff_v_per_rps
            kd = c.kd_duty_per_rps2 * FW_TICK_HZ
            lim = c.i_limit_duty / ki if ki > 0.0 else 0.0
            max_duty = c.max_duty
            last_cmd, wd = fw.last_cmd_s, c.watchdog_s  # trips on the first tick with now - last > wd
            int_l, int_r, pe_l, pe_r = fw._int_l, fw._int_r, fw._prev_e_l, fw._prev_e_r
            dl = dr = 0.0
            vin = vbat
            ci_l = ci_r = 0.0
            k_fast = 0
        done = 0
        kern = self._kernel() if fast and payload <= 0.0 else None
        if kern is not None:
            # the same loop compiled (compiled.py), the mocap samples and the terrain wrap
            # included; the rest of the period (watchdog) runs below
            run, step_fn = kern
            st = np.array([int_l, int_r, pe_l, pe_r, dl, dr, vin, ci_l, ci_r, soc, vbat, i_l, i_r, t,
                           self._mocap_next_t])
            h = self.perturbations["heading_offset_deg"]
            off = self.perturbations["mocap_offset_m"]
            cst = np.array([sp_l, sp_r, kp, ki, ff_v, kd, lim, max_duty, last_cmd, wd, r_m, ke, i_max, r_b, cap_as,
                            idle, v_empty, v_span, TICK_S, inv2pi,
                            self._mocap_period, self._period_m if self._hfield_zmax > 0.0 else 0.0, s.mocap_dropout,
                            s.mocap_latency_s, s.mocap_noise_m, s.mocap_noise_rad, h,
                            math.cos(0.5 * math.radians(h)), math.sin(0.5 * math.radians(h)), off[0], off[1], off[2]])
            ist = self._mocap_ist
            ist[1] = ist[2] = 0
            m_ptr, d_ptr = m._address, d._address
            rng_ptrs = self._rng_mocap_pointers
            if rng_ptrs[0] != self._rng_mocap.bit_generator.ctypes.state_address:  # a copied sim: its own stream
                rng_ptrs = self._rng_mocap_pointers = bit_generator_pointers(self._rng_mocap)
            # the same array objects every call: numba types a fresh view of MjData slowly (~0.1 ms)
            qp, qv, ct = self._views
            rows_needed = int((n - done) * TICK_S / self._mocap_period) + 2  # the samples due, and one
            while done < n:
                ist[0] = self._mocap_room(rows_needed)
                ist[3] = self._mocap_bad_end
                k = run(step_fn, m_ptr, d_ptr, qp, qv, ct, vl_i, vr_i, n - done, substeps, st, cst,
                        *rng_ptrs, self._mocap_rows, ist, self._tile_offset)
                self._mocap_tail, self._mocap_bad_end = int(ist[0]), int(ist[3])
                if k == 0:
                    break
                done += k
                k_fast += k
            int_l, int_r, pe_l, pe_r, dl, dr, vin, ci_l, ci_r, soc, vbat, i_l, i_r, t, self._mocap_next_t = st.tolist()
            self.mocap_samples += int(ist[1])
            self.mocap_dropped += int(ist[2])
            mocap_next = self._mocap_next_t - 1e-9
        for _ in range(n - done):
            wl = qvel.item(vl_i)
            wr = qvel.item(vr_i)
            if fast and t - last_cmd <= wd:
                vin, ci_l, ci_r = vbat, i_l, i_r
                vb = vbat if vbat > 1.0 else 1.0
                ff = ff_v / vb
                el = sp_l - wl * inv2pi
                er = sp_r - wr * inv2pi
                if ki > 0.0:
                    il = int_l + el * TICK_S
                    ir = int_r + er * TICK_S
                    int_l = lim if il > lim else (-lim if il < -lim else il)
                    int_r = lim if ir > lim else (-lim if ir < -lim else ir)
                dl = ff * sp_l + kp * el + ki * int_l + kd * (el - pe_l)
                dr = ff * sp_r + kp * er + ki * int_r + kd * (er - pe_r)
                pe_l, pe_r = el, er
                dl = max_duty if dl > max_duty else (-max_duty if dl < -max_duty else dl)
                dr = max_duty if dr > max_duty else (-max_duty if dr < -max_duty else dr)
                k_fast += 1
            else:
                if fast:  # hand the firmware its state back; Firmware.tick from here on
                    self._fw_writeback(k_fast, int_l, int_r, pe_l, pe_r, dl, dr, vin, ci_l, ci_r)
                    fast = False
                dl, dr = tick(t, wl * inv2pi, wr * inv2pi, vbat, i_l, i_r)
            # battery: open-circuit voltage minus the IR drop of the last tick's draw
            # (a 1 ms lag instead of solving the algebraic loop; the drop is small)
            i_tot = abs(i_l) + abs(i_r) + idle
            soc -= i_tot * TICK_S / cap_as
            if soc < 0.0:
                soc = 0.0
            vbat = v_empty + v_span * soc - r_b * i_tot
            vl, vr = dl * vbat, dr * vbat
            i_l = (vl - ke * wl) / r_m
            i_r = (vr - ke * wr) / r_m
            i_l = i_max if i_l > i_max else (-i_max if i_l < -i_max else i_l)
            i_r = i_max if i_r > i_max else (-i_max if i_r < -i_max else i_r)
            ctrl[0] = vl
            ctrl[1] = vr
            if payload > 0.0:
                self._tow(payload)
            step(m, d, substeps)
            t += TICK_S
            if t >= mocap_next:
                self._t = t
                self._wrap()
                self._mocap_sample()
                self._mocap_next_t += self._mocap_period
                mocap_next = self._mocap_next_t - 1e-9
        if fast:
            self._fw_writeback(k_fast, int_l, int_r, pe_l, pe_r, dl, dr, vin, ci_l, ci_r)
        self._t = t
        self._soc, self._vbat, self._i_l, self._i_r = soc, vbat, i_l, i_r
        # MuJoCo resets the state itself when the integration blows up; a reading taken
        # across such a reset is not physics. Count it and flag the readings (ok=False) so
        # recordings and datasets can drop those transitions instead of learning a teleport.
        bad = int(d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number)
        if bad > self._badqacc_seen:
            self._badqacc_seen = bad
            self.divergences += 1
            self._diverged_pending = True

    def _kernel(self):
        """The compiled loop (``(run, mj_step address)``), or None: not wanted, or no numba."""
        if not self.compiled_firmware:
            return None
        from hilstack.sim_backends.velociroach.compiled import kernel

        return kernel()

    def _fw_writeback(self, ticks: int, int_l: float, int_r: float, pe_l: float, pe_r: float, dl: float, dr: float,
                      vbat_v: float, current_l_a: float, current_r_a: float) -> None:
        """The firmware state after ``ticks`` inlined PID ticks, as Firmware.tick leaves it
        (its clock, integrals, last errors, duties and the last tick's fault bits)."""
        if ticks == 0:
            return
        fw, c = self.firmware, self.firmware.config
        fw.t_fw_ms += ticks
        fw._int_l, fw._int_r, fw._prev_e_l, fw._prev_e_r = int_l, int_r, pe_l, pe_r
        fw.duty_l, fw.duty_r = dl, dr
        faults = 0
        if vbat_v < c.low_battery_v:
            faults |= FAULT_LOW_BATTERY
        if abs(current_l_a) > c.overcurrent_a or abs(current_r_a) > c.overcurrent_a:
            faults |= FAULT_MOTOR
        fw.faults = faults

    def _tow(self, payload_kg: float) -> None:
        """Sliding friction of a towed payload, applied at the rear of the chassis (world frame)."""
        d = self.data
        v = d.qvel[0:2]
        speed = math.hypot(v[0], v[1])
        # tanh regularizes Coulomb friction at standstill (no chatter, no stiction)
        f = self.sim.payload_friction * payload_kg * 9.81 * math.tanh(speed / 0.02)
        if speed > 1e-9:
            fx, fy = -f * v[0] / speed, -f * v[1] / speed
        else:
            fx = fy = 0.0
        # lever arm: tow point at the rear of the chassis
        rm = d.xmat[self._chassis].reshape(3, 3)
        rx, ry, _ = rm @ np.array([-self._geometry.chassis_half_m[0], 0.0, 0.0])
        x = d.xfrc_applied[self._chassis]
        x[0], x[1], x[2] = fx, fy, 0.0
        x[3], x[4], x[5] = 0.0, 0.0, rx * fy - ry * fx

    # ------------------------------------------------------------------ sensors
    def _mocap_sample(self) -> None:
        """Take one mocap sample now; it is delivered ``mocap_latency_s`` later.

        Scalar math on Python floats on purpose: this runs at the mocap rate inside the stepping
        loop (numpy/mju per-call overhead was ~15% of the loop in the profile). The compiled loop
        (compiled.py) takes the same samples itself, with the same operations; both write one
        row of the mocap queue (``_mocap_rows``)."""
        s = self.sim
        q0, q1, q2, w, x, y, z = self.data.qpos[:7].tolist()
        self.mocap_samples += 1
        # draw every random number whether or not the sample drops, so that changing the
        # dropout probability does not change the noise sequence
        u = self._rng_mocap.random()
        n = self._rng_mocap.standard_normal(6).tolist()
        ok = u >= s.mocap_dropout
        if not ok:
            self.mocap_dropped += 1
        off = (self.perturbations["mocap_offset_m"] + self._tile_offset).tolist()
        sp, sr = s.mocap_noise_m, s.mocap_noise_rad
        pos = (q0 + off[0] + sp * n[0], q1 + off[1] + sp * n[1], q2 + off[2] + sp * n[2])
        if sr > 0.0:
            # small rotation noise (rotation vector sr·n[3:6], world frame) applied on the left
            vx, vy, vz = sr * n[3], sr * n[4], sr * n[5]
            ang = math.sqrt(vx * vx + vy * vy + vz * vz)
            k = math.sin(0.5 * ang) / ang if ang > 1e-12 else 0.5
            aw, ax, ay, az = math.cos(0.5 * ang), k * vx, k * vy, k * vz
            w, x, y, z = (
                aw * w - ax * x - ay * y - az * z,
                aw * x + ax * w + ay * z - az * y,
                aw * y - ax * z + ay * w + az * x,
                aw * z + ax * y - ay * x + az * w,
            )
        h = self.perturbations["heading_offset_deg"]
        if h != 0.0:
            # miscalibrated heading: rotate the reported orientation about world z (left product)
            hc, hs = math.cos(0.5 * math.radians(h)), math.sin(0.5 * math.radians(h))
            w, x, y, z = hc * w - hs * z, hc * x - hs * y, hc * y + hs * x, hc * z + hs * w
        isfinite = math.isfinite
        finite = all(isfinite(v) for v in pos) and isfinite(w) and isfinite(x) and isfinite(y) and isfinite(z)
        self._queue_mocap((self._t + s.mocap_latency_s, self._t, *pos, w, x, y, z, ok, finite))

    def _queue_mocap(self, row: tuple) -> None:
        """Queue one sample: (arrival time, sample time, x, y, z, qw, qx, qy, qz, ok, finite)."""
        i = self._mocap_room()
        self._mocap_rows[i] = row
        self._mocap_tail = i + 1
        if not (row[9] and row[10]):
            self._mocap_bad_end = i + 1

    def _mocap_room(self, rows_needed: int = 1) -> int:
        """The first free row of the mocap queue, with room for ``rows_needed`` samples after it
        (the queue moved to the front of its buffer, or the buffer grown)."""
        head, tail, rows = self._mocap_head, self._mocap_tail, self._mocap_rows
        if tail + rows_needed <= len(rows):
            return tail
        n = tail - head
        if n + rows_needed > len(rows):
            self._mocap_rows = np.empty((2 * (n + rows_needed), rows.shape[1]))
        self._mocap_rows[:n] = rows[head:tail]
        self._mocap_head, self._mocap_tail = 0, n
        self._mocap_bad_end = max(0, self._mocap_bad_end - head)
        return n

    def _deliver_mocap(self, now_s: float) -> None:
        """Hand every queued sample whose arrival time has come to the pose input, in order;
        the newest usable one becomes the pose the state reports."""
        head, tail = self._mocap_head, self._mocap_tail
        if head == tail:
            return
        rows = self._mocap_rows
        arrival, lim, end = rows.item, now_s + 1e-9, tail
        while end > head and arrival(end - 1, 0) > lim:  # arrival times only grow: the due ones come first
            end -= 1
        if end == head:
            return
        self._mocap_head = end
        pose = self._pose_input
        if self._mocap_bad_end <= head:  # all kept and finite: the newest sample is the one that counts
            last = rows[end - 1].tolist()
            self._mocap_latest_ok = True
            pose.update(min(last[0], now_s), True)
            self._mocap_latest = (last[1], tuple(last[2:5]), tuple(last[5:9]))
            return
        for t_arrive, ts, p0, p1, p2, w, x, y, z, ok, finite in rows[head:end].tolist():
            self._mocap_latest_ok = ok = bool(ok)
            if ok:
                pose.update(min(t_arrive, now_s), bool(finite))
                if finite:
                    self._mocap_latest = (ts, (p0, p1, p2), (w, x, y, z))

    def mocap_pose(self) -> tuple[float, np.ndarray, np.ndarray] | None:
        """The newest delivered mocap sample: (t_s sample time, position [m] world,
        quaternion wxyz), or None when the newest sample was dropped (or none yet)."""
        self._deliver_mocap(self.sim_time_s)
        if not self._mocap_latest_ok or self._mocap_latest is None:
            return None
        ts, pos, q = self._mocap_latest
        return ts, np.array(pos), np.array(q)

    def _crank_angles(self) -> tuple[float, float]:
        """Encoder readings [rad] in [0, 2π), quantized to 14 bits (fore-leg hinge = crank)."""
        qpos = self.data.qpos
        res = _ENCODER_RES_RAD
        return (math.floor((qpos.item(self._q_l[0]) % TWO_PI) / res) * res,
                math.floor((qpos.item(self._q_r[0]) % TWO_PI) / res) * res)

    def telemetry(self) -> dict:
        """One telemetry packet as the firmware would send it (body-frame IMU, SI units)."""
        m, d, s = self.model, self.data, self.sim
        rng = self._rng_telem
        m.opt.disableflags &= ~self._sensor_flag
        mujoco.mj_forward(m, d)
        m.opt.disableflags |= self._sensor_flag
        gyro = d.sensordata[0:3] + rng.standard_normal(3) * s.gyro_noise_rps
        accel = d.sensordata[3:6] + rng.standard_normal(3) * s.accel_noise_mps2
        wl, wr = float(d.qvel[self._v_l]), float(d.qvel[self._v_r])
        bemf = np.array([wl, wr]) * self._bemf_v_per_rad_s + rng.standard_normal(2) * s.bemf_noise_v
        fw = self.firmware.snapshot()
        return {
            "t_fw_ms": fw["t_fw_ms"],
            "gyro_rps": [float(v) for v in gyro],
            "accel_mps2": [float(v) for v in accel],
            "crank_angle_rad": list(self._crank_angles()),
            "crank_vel_rps": [wl / TWO_PI, wr / TWO_PI],
            "bemf_v": [float(v) for v in bemf],
            "vbat_v": float(self._vbat + rng.standard_normal() * s.vbat_noise_v),
            "duty": [float(v) for v in fw["duty"]],
            "faults": fw["faults"],
            "current_a": [self._i_l, self._i_r],
        }

    # ------------------------------------------------------------------ contract
    def _state(self) -> np.ndarray:
        d = self.data
        self._deliver_mocap(self.sim_time_s)
        if self._mocap_latest is None:
            pos, q = self.true_position_m().tolist(), d.qpos[3:7].tolist()
        else:
            _, pos, q = self._mocap_latest
        roll, pitch, yaw = quat_to_rpy(q)
        cl, cr = self._crank_angles()
        qvel = d.qvel
        vx, vy, vz, wx, wy, wz = qvel[:6].tolist()
        wl, wr = qvel.item(self._v_l), qvel.item(self._v_r)
        k = self._bemf_v_per_rad_s
        cos, sin = math.cos, math.sin
        # Python floats in, one array out (numpy scalars in the list cost as much again)
        return np.array([
            pos[0], pos[1], pos[2],
            vx, vy, vz,
            cos(roll), sin(roll), cos(pitch), sin(pitch), cos(yaw), sin(yaw),
            wx, wy, wz,
            cos(cl), sin(cl), cos(cr), sin(cr),
            wl / TWO_PI, wr / TWO_PI,
            k * wl, k * wr,
            self._vbat,
        ])

    def _read(self) -> Observation:
        self._seq += 1
        fw = self.firmware
        now = self.sim_time_s
        state = self._state()
        # telemetry is computed on demand in the sim: fresh, unless the physics produced NaN
        self._telemetry_input.update(now, bool(np.isfinite(state[self._telemetry_index:]).all()))
        ok, flags = self.inputs.assess(now, report=True)
        diverged, self._diverged_pending = self._diverged_pending, False
        flags[_SIM_DIVERGED] = diverged
        faults = fw.faults
        ff = self._fault_flags.get(faults)
        if ff is None:
            ff = self._fault_flags[faults] = fault_flags(faults)
        flags.update(ff)
        extras = {"duty": (fw.duty_l, fw.duty_r), "t_fw_ms": fw.t_fw_ms}
        if self.sim.camera_px:
            extras["image"] = self.render_camera()
        return Observation(t_s=now, state=state, seq=self._seq, flags=flags, ok=ok and not diverged,
                           extras=extras)

    def _hold_command(self, obs: Observation) -> np.ndarray:
        """What the firmware runs now: its setpoint (zero after a watchdog trip or a reboot)
        in leg-velocity mode, its applied duty in PWM mode; the measured crank velocity
        only if the firmware runs PWM while the driver commands leg velocity."""
        fw = self.firmware
        if self.params.action_mode == "pwm":
            v = np.array([fw.duty_l, fw.duty_r])
        elif fw.mode == "leg_velocity":
            sl, sr = self.sim.leg_speed_scale  # the command that gives this setpoint
            v = np.array([fw.setpoint_l / sl, fw.setpoint_r / sr])
        else:
            i = self.spec.state.index("crank_vel_l")
            v = obs.state[i:i + 2]
        return np.clip(v, self.spec.action.low, self.spec.action.high)

    def _write(self, action: np.ndarray) -> None:
        if self.params.action_mode == "leg_velocity":
            sl, sr = self.sim.leg_speed_scale
            self.firmware.set_leg_velocity(action[0] * sl, action[1] * sr, self.sim_time_s)
        else:
            self.firmware.set_pwm(action[0], action[1], self.sim_time_s)

    def _stop(self) -> None:
        if self.data is None:
            return
        if self.params.action_mode == "leg_velocity":
            self.firmware.set_leg_velocity(0.0, 0.0, self.sim_time_s)
        else:
            self.firmware.set_pwm(0.0, 0.0, self.sim_time_s)

    def _health(self) -> Health:
        ok = self.data is not None
        n = max(1, self.mocap_samples)
        if ok:
            self._deliver_mocap(self.sim_time_s)
        inputs_ok = ok and self.inputs.assess(self.sim_time_s)[0]
        return Health(
            ok=inputs_ok,
            link_quality=1.0 - self.mocap_dropped / n,
            dropped_frames=self.mocap_dropped,
            last_error=self.last_error,
            extra={"sim_time_s": self.sim_time_s, "faults": self.firmware.faults, "sim_divergences": self.divergences,
                   **self.inputs.ages(self.sim_time_s)},
        )
