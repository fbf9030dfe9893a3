"""VelociRoACH driver: the driver contract over the XBee/MAVLink radio link.

backend "real": the base-station XBee on ``params.port`` (API mode 1, ``params.baudrate``).
backend "emulated": the same code against the firmware emulator
(``python -m hilstack.sim_backends.velociroach.emulator``), started here as a separate process on a
pty it creates; its mocap pose arrives over UDP like a motion-capture stream would.

Threads: a reader thread drains the port, keeps the latest telemetry and pose, and sends
the heartbeat (1 Hz); ``read()`` only copies that under a lock, so it never blocks on I/O.
``write()`` packs and sends one command frame from the caller's thread.

State (24-D, see ``config.STATE_CHANNELS``): position and orientation from the mocap pose,
linear velocity by differencing the pose (low-pass filtered), angular velocity from the
gyro, crank angles/velocities, back-EMFs and battery voltage from telemetry.

Inputs and their deadlines (:class:`hilstack.drivers.base.Freshness`, local monotonic clock at
arrival): the pose (``pose_deadline_s``) and the telemetry (``telemetry_deadline_s``). A
stale input, or a sample with NaN/inf since the last read (not used: the last finite one is
kept), makes ``ok`` False with ``stale_pose`` / ``stale_telemetry`` / ``nonfinite_input``; the firmware's
fault bits are the flags of ``config.fault_flags``. No usable telemetry for
``link_timeout_periods`` control periods while the link is open (a frozen robot) takes the
error path: the stop is sent, the link closed, ``last_error`` says why.
"""

from __future__ import annotations

import json
import math
import threading
import time
from typing import Any

import numpy as np

from hilstack.bus.cycle import Rate
from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import (
    Driver,
    Flag,
    Freshness,
    Health,
    Inputs,
    LinkError,
    Observation,
    require_device,
)
from hilstack.drivers.emulator_process import EmulatorProcess, emulator_module
from hilstack.drivers.velociroach.config import VelociRoachParams, fault_flags, quat_to_rpy, velociroach_spec
from hilstack.drivers.velociroach.link import RadioLink
from hilstack.drivers.velociroach.mavlink import BASE_COMPID, BASE_SYSID, EncodeError, MavEncoder, mav

#: the base station's heartbeat rate (MAVLink convention: 1 Hz)
HEARTBEAT_PERIOD_S = 1.0
#: how many of the last commands sent are remembered (by cmd_seq) to know what the firmware runs
CMD_MEMORY = 256
#: velocity low-pass: time constant of the pose differencing filter
VEL_FILTER_TAU_S = 0.05


class PoseFilter:
    """Mocap pose -> position, filtered world-frame velocity, roll/pitch/yaw."""

    def __init__(self, tau_s: float = VEL_FILTER_TAU_S):
        self.tau_s = tau_s
        self.t_s: float | None = None
        self.pos = np.zeros(3)
        self.vel = np.zeros(3)
        self.rpy = (0.0, 0.0, 0.0)

    def update(self, t_s: float, pos: Any, quat_wxyz: Any) -> bool:
        """Fuse one sample; False when it is unusable (NaN/inf, zero quaternion) and skipped."""
        p = np.asarray(pos, dtype=np.float64).reshape(3)
        q = np.asarray(quat_wxyz, dtype=np.float64).reshape(4)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))) or np.linalg.norm(q) < 1e-6:
            return False  # a mocap dropout (NaN/zero quaternion) is skipped, not propagated
        if self.t_s is not None:
            dt = t_s - self.t_s
            if dt <= 0:
                return True  # duplicate or reordered sample: nothing new, nothing wrong
            raw = (p - self.pos) / dt
            a = dt / (self.tau_s + dt)
            self.vel = self.vel + a * (raw - self.vel)
        self.t_s = t_s
        self.pos = p
        self.rpy = quat_to_rpy(q / np.linalg.norm(q))
        return True


class VelociRoachDriver(Driver):
    params_type = VelociRoachParams

    def __init__(self, params: VelociRoachParams | None = None, backend: str = "real", source: str | None = None):
        super().__init__()
        self.params = params or VelociRoachParams()
        self.backend = backend
        self.source = source
        self.spec = velociroach_spec(self.params)
        self.link: RadioLink | None = None
        self.enc = MavEncoder(BASE_SYSID, BASE_COMPID)
        self._lock = threading.Lock()
        self._stop_evt = threading.Event()
        self._thread: threading.Thread | None = None
        self._hb_rate: Rate | None = None  # the heartbeat's deadline (reader thread)
        self._emu: EmulatorProcess | None = None
        #: UDP port of the emulator's lab fixture (backend emulated; drivers/fixture.py)
        self._fixture_port: int | None = None
        self._pose_client: Any = None
        self._pose = PoseFilter()
        self._pose_seen: Any = None  # the newest pose sample taken from the client
        self._tel: Any = None  # the newest telemetry with finite sensor values
        self._tel_t: float | None = None
        self._last_cmd_seq: int | None = None  # the firmware's echo of the last command it applied
        self.inputs = Inputs(
            Freshness("pose", self.params.pose_deadline_s, Flag.STALE_POSE),
            Freshness("telemetry", self.params.telemetry_deadline_s, Flag.STALE_TELEMETRY,
                      fail_after_s=self.params.link_timeout_periods * self.params.period_s),
        )
        self._hb_t: float | None = None
        self._robot_faults = 0
        self._status: list[str] = []
        self._gains_reply: dict[int, Any] = {}
        self._cmd_seq = 0
        self._cmd_sent_t: dict[int, float] = {}
        #: cmd_seq -> (mode, left, right) of the last CMD_MEMORY commands sent
        self._cmd_values: dict[int, tuple[str, float, float]] = {}
        self._latency_s: float | None = None
        self._reader_error: str | None = None
        self._seq = 0
        self._rid = 0

    # ------------------------------------------------------------------ lifecycle
    def _on_configure(self) -> None:
        p = self.params
        if self.backend != "emulated" and not p.port:
            raise ConfigError(self.source, [(
                "params.port", "no serial port: set params.port or pass --port; `hil find-port` lists candidates")])
        if self.backend != "emulated":
            require_device(p.port, self.source, "params.port", "the base-station XBee")
        # the pose: the emulator streams its sim's mocap here; a real rig points a mocap
        # bridge at params.mocap_udp_port
        pose_port = p.mocap_udp_port
        if self.backend == "emulated" and self.params.emulator.pose:
            pose_port = 0
        with self._lock:
            self.inputs.start(time.monotonic())
            self._tel = self._tel_t = self._last_cmd_seq = None
            self._pose = PoseFilter()
            self._pose_seen = None
        if pose_port is not None:
            from hilstack.drivers.mocap.udp import UdpPoseClient

            self._pose_client = UdpPoseClient("127.0.0.1" if self.backend == "emulated" else "0.0.0.0", pose_port)
        url = self._start_emulator() if self.backend == "emulated" else p.port
        self.link = RadioLink.open(url, p.baudrate, write_timeout_s=p.write_timeout_s, role="base",
                                   robot_addr64=p.robot_addr64, tlog=p.tlog)
        self._stop_evt.clear()
        self._reader_error = None
        self._thread = threading.Thread(target=self._reader, name="velociroach-link", daemon=True)
        self._thread.start()
        self._wait_first_contact()

    def _start_emulator(self) -> str:
        cfg = self.params.model_dump(mode="json")
        cfg["port"] = None
        cfg["tlog"] = None  # the driver writes the log, not the robot
        args = ["--print-pty", "--config", json.dumps(cfg)]
        if self._pose_client is not None and self.params.emulator.pose:  # pose: false, a mocap bridge sends it
            args += ["--pose-port", str(self._pose_client.port)]
        if self.params.emulator.lab_fixture:
            args += ["--fixture-port", "0"]
        self._emu = EmulatorProcess(emulator_module("velociroach"), args,
                                    start_timeout_s=self.params.emulator.start_timeout_s,
                                    keep_log=self.params.emulator.keep_log)
        ready = self._emu.start()
        # the lab fixture is beside the robot, not on its radio: the reset supervisor finds
        # it in the health (drivers/fixture.py)
        self._fixture_port = ready.get("fixture_port")
        return ready["pty"]

    def _wait_first_contact(self) -> None:
        """Heartbeat and telemetry from the robot, or a LinkError that says what to check."""
        timeout_s = self.params.emulator.connect_timeout_s if self.backend == "emulated" else 5.0
        deadline = time.monotonic() + timeout_s
        self._send(self.enc.heartbeat())
        while time.monotonic() < deadline:
            with self._lock:
                if self._reader_error:
                    raise LinkError(self._reader_error)
                if self._hb_t is not None and self._tel is not None:
                    return
            time.sleep(0.01)
        what = f"no {'heartbeat' if self._hb_t is None else 'telemetry'} from the robot within {timeout_s:g} s"
        if self._emu is not None:
            raise LinkError(self._emu.failure(what))
        raise LinkError(f"{what}; is the robot on, and the base-station XBee on {self.params.port} in API mode 1 at "
                        f"{self.params.baudrate} baud, talking to {self.params.robot_addr64}?")

    def _on_cleanup(self) -> None:
        self._stop_evt.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=1.0)
        self._thread = None
        if self.link is not None:
            self.link.close()
        if self._pose_client is not None:
            try:
                self._pose_client.close()
            except Exception:
                pass
            self._pose_client = None
        if self._emu is not None:
            self._emu.stop()
            self._emu = None

    # ------------------------------------------------------------------ reader thread
    def _reader(self) -> None:
        link = self.link
        assert link is not None
        # the base station's heartbeat: one scheduler (bus/cycle.py), a late one skips and counts
        self._hb_rate = hb = Rate(HEARTBEAT_PERIOD_S, time.monotonic() + HEARTBEAT_PERIOD_S)
        while not self._stop_evt.is_set():
            try:
                msgs = link.receive(timeout_s=0.01)
                now = time.monotonic()
                for m in msgs:
                    self._handle(m, now)
                if self._pose_client is not None:
                    self._poll_pose()
                if hb.due(now):
                    self._send(self.enc.heartbeat())
            except LinkError as e:
                with self._lock:
                    self._reader_error = str(e)
                return
            except Exception as e:  # a bug here must show up in health, not kill the link silently
                with self._lock:
                    self._reader_error = f"link reader crashed: {type(e).__name__}: {e}"
                return

    def _handle(self, m: Any, now: float) -> None:
        t = m.get_type()
        with self._lock:
            if t == "ROACH_TELEMETRY":
                finite = all(math.isfinite(v) for v in (*m.gyro, *m.accel, *m.crank_angle, *m.crank_vel, *m.bemf,
                                                        m.vbat, *m.duty))
                self.inputs["telemetry"].update(now, finite)
                if finite:  # a NaN packet is flagged and not used: the state keeps the last finite one
                    self._tel = m
                    self._tel_t = now
                self._robot_faults = m.faults
                self._last_cmd_seq = m.last_cmd_seq
                sent = self._cmd_sent_t.pop(m.last_cmd_seq, None)
                if sent is not None:
                    self._latency_s = now - sent
                    # anything older than the acknowledged command will not be echoed any more
                    for s in [s for s in self._cmd_sent_t if s < m.last_cmd_seq]:
                        del self._cmd_sent_t[s]
            elif t == "HEARTBEAT":
                self._hb_t = now
            elif t == "ROACH_STATUS_TEXT":
                self._status = (self._status + [m.text])[-10:]
            elif t == "ROACH_PID_GAINS":
                self._gains_reply[m.request_id] = m

    def _poll_pose(self) -> None:
        sample = self._pose_client.latest()
        if sample is not None and sample is not self._pose_seen:
            self._pose_seen = sample
            arrival = sample.received_s if sample.received_s is not None else time.monotonic()
            with self._lock:
                usable = self._pose.update(sample.t_s, sample.position_m, sample.quaternion_wxyz)
                self.inputs["pose"].update(arrival, usable)

    def _send(self, frame: bytes) -> None:
        if self.link is None:
            raise LinkError("link not open")
        self.link.send(frame)

    # ------------------------------------------------------------------ contract hooks
    def _check_link(self) -> None:
        """Raise LinkError (after taking the error path) if the reader thread failed or the
        robot froze: no usable telemetry for ``link_timeout_periods`` with the link open."""
        now = time.monotonic()
        with self._lock:
            err = self._reader_error
            gone = self.inputs.expired(now) if err is None else None
        if gone is not None:
            age = gone.age_s(now)
            since = "since the link came up" if age is None else f"for {age:.2f} s"
            err = (f"no usable {gone.name} from the robot {since} (limit: {self.params.link_timeout_periods} "
                   f"control periods of {self.params.period_s:g} s) while the link is open: robot frozen, "
                   "switched off or out of radio range")
        if err:
            self.fail_link(err)  # stop (sent while the port is open), close, UNCONFIGURED, raise

    def _read(self) -> Observation:
        self._check_link()
        now = time.monotonic()
        with self._lock:
            tel, tel_t = self._tel, self._tel_t
            pose = self._pose
            pos, vel, (roll, pitch, yaw) = pose.pos.copy(), pose.vel.copy(), pose.rpy
            pose_t = pose.t_s
            ok, flags = self.inputs.assess(now, report=True)
            faults, last_seq = self._robot_faults, self._last_cmd_seq
        s = np.zeros(self.spec.state.dim)
        s[0:3] = pos
        s[3:6] = vel
        s[6:12] = [math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)]
        if tel is not None:
            s[12:15] = tel.gyro
            al, ar = tel.crank_angle
            s[15:19] = [math.cos(al), math.sin(al), math.cos(ar), math.sin(ar)]
            s[19:21] = tel.crank_vel
            s[21:23] = tel.bemf
            s[23] = tel.vbat
        else:
            s[15], s[17] = 1.0, 1.0
        flags.update(fault_flags(faults))
        self._seq += 1
        return Observation(
            t_s=tel_t if tel_t is not None else now,
            state=s,
            seq=self._seq,
            ok=ok,
            flags=flags,
            extras={"faults": faults, "t_fw_ms": None if tel is None else tel.time_fw_ms,
                    # the command the firmware last applied (its echo) and the last one sent
                    "last_cmd_seq": last_seq, "cmd_seq_sent": self._cmd_seq,
                    "duty": None if tel is None else list(tel.duty), "pose_t_s": pose_t},
        )

    def _hold_command(self, obs: Observation) -> np.ndarray:
        """What the firmware runs now, from its telemetry: PWM mode reports its applied duty;
        in leg-velocity mode the setpoint is zero after a watchdog trip or before any
        command, and the value of the command it echoes (``last_cmd_seq``) when this driver
        sent it; otherwise (another session's command) the measured crank velocity."""
        sp = self.spec
        # a command still in flight (the stop of a deactivate just before) is what the
        # firmware runs a few ms from now: wait up to one period for its echo
        deadline = time.monotonic() + sp.period_s
        while True:
            with self._lock:
                tel, last_seq, faults = self._tel, self._last_cmd_seq, self._robot_faults
                sent = self._cmd_values.get(last_seq) if last_seq is not None else None
            if self._cmd_seq == 0 or last_seq == self._cmd_seq or time.monotonic() >= deadline:
                break
            time.sleep(0.005)
        if tel is None:
            return np.zeros(sp.action.dim)
        mode = self.params.action_mode
        if mode == "pwm":
            v = np.array(tel.duty, dtype=np.float64)
        elif faults & mav.ROACH_FAULT_WATCHDOG or last_seq == 0:
            v = np.zeros(2)
        elif sent is not None and sent[0] == mode:
            v = np.array(sent[1:])
        else:
            i = sp.state.index("crank_vel_l")
            v = obs.state[i:i + 2]
        return np.clip(v, sp.action.low, sp.action.high)

    def _write(self, action: np.ndarray) -> None:
        self._check_link()
        self._send_command(action)

    def _send_command(self, action: np.ndarray) -> None:
        """Pack and send one command frame; no health check (the error path uses it too)."""
        self._cmd_seq += 1
        seq = self._cmd_seq
        a, b = float(action[0]), float(action[1])
        mode = self.params.action_mode
        try:
            if mode == "leg_velocity":
                frame = self.enc.leg_velocity(seq, a, b, self.params.max_leg_vel_rps)
            else:
                frame = self.enc.pwm(seq, a, b)
        except EncodeError as e:
            # the base class validated already; reaching this is a bug upstream, never a send
            raise LinkError(f"refused to send a bad command: {e}") from None
        with self._lock:
            self._cmd_sent_t[seq] = time.monotonic()
            if len(self._cmd_sent_t) > CMD_MEMORY:  # never acknowledged (radio loss): forget the oldest
                del self._cmd_sent_t[min(self._cmd_sent_t)]
            self._cmd_values[seq] = (mode, a, b)
            if len(self._cmd_values) > CMD_MEMORY:
                del self._cmd_values[min(self._cmd_values)]
        self._send(frame)

    def _stop(self) -> None:
        """Send zero: whenever the port is open, also on the error path after a reader crash
        or a frozen robot (only a dead or closed port excuses it)."""
        if self.link is None or self.link.closed or self.link.dead:
            return
        self._send_command(np.zeros(2))

    def _health(self) -> Health:
        link = self.link
        now = time.monotonic()
        with self._lock:
            err = self._reader_error
            tel, hb_t = self._tel, self._hb_t
            status = list(self._status)
            latency = self._latency_s
            inputs_ok, _ = self.inputs.assess(now)
            ages = self.inputs.ages(now)
        if link is None:
            return Health(ok=False, link_quality=0.0, last_error=self.last_error or err)
        st = link.stats()
        extra = {k: v for k, v in st.items() if k not in ("frames_sent", "frames_received", "corrupt_frames",
                                                          "dropped_frames")}
        extra.update({
            **ages,
            "robot_faults": self._robot_faults,
            "robot_rx_good": None if tel is None else tel.rx_good,
            "robot_rx_corrupt": None if tel is None else tel.rx_corrupt,
            "status_text": status,
            "backend": self.backend,
            **(self._hb_rate.counts("heartbeat") if self._hb_rate else {}),
            **({"lab_fixture_port": self._fixture_port} if self._fixture_port else {}),
        })
        return Health(
            ok=bool(inputs_ok and err is None and not link.dead),
            link_quality=link.quality(self.params.telemetry_hz, now),
            frames_sent=st["frames_sent"],
            frames_received=st["frames_received"],
            corrupt_frames=st["corrupt_frames"],
            dropped_frames=st["dropped_frames"],
            latency_s=latency,
            last_heartbeat_s=None if hb_t is None else now - hb_t,
            last_error=err or link.last_error or self.last_error,
            extra=extra,
        )

    # ------------------------------------------------------------------ extras
    def set_pid_gains(self, kp: float, ki: float, kd: float, timeout_s: float = 1.0) -> tuple[float, float, float]:
        """Set the firmware's crank PID gains; returns the gains the robot reports."""
        self._rid = (self._rid + 1) % 65536
        self._send(self.enc.pid_set(self._rid, kp, ki, kd))
        return self._await_gains(self._rid, timeout_s)

    def get_pid_gains(self, timeout_s: float = 1.0) -> tuple[float, float, float]:
        self._rid = (self._rid + 1) % 65536
        self._send(self.enc.pid_get(self._rid))
        return self._await_gains(self._rid, timeout_s)

    def _await_gains(self, rid: int, timeout_s: float) -> tuple[float, float, float]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self._check_link()
            with self._lock:
                m = self._gains_reply.pop(rid, None)
            if m is not None:
                if m.result == 1:
                    raise ValueError(f"robot rejected the PID gains; it keeps {m.kp}, {m.ki}, {m.kd}")
                return m.kp, m.ki, m.kd
            time.sleep(0.005)
        raise LinkError(f"no PID gains answer from the robot within {timeout_s} s")

    @property
    def emulator(self) -> EmulatorProcess | None:
        """The emulator process of an emulated backend (tests kill it to simulate a lost device)."""
        return self._emu
