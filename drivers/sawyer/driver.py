"""Sawyer driver: the contract over Zenoh with ROS 2 messages (CDR via rosbags).

backend "real": connects to ``params.zenoh_connect`` (a zenoh-bridge-ros2dds beside the
robot's ROS 2 side); subscribes ``sensor_msgs/JointState`` on the joint-states topic and
publishes ``intera_core_msgs/JointCommand`` (velocity mode) on the command topic, under
the keys the bridge uses (drivers/sawyer/ros.py).
backend "emulated": the same code against ``python -m hilstack.sim_backends.sawyer.emulator``, a
process playing the robot side on MuJoCo, started here on a loopback endpoint.

Zenoh's callback only stores the newest sample and its arrival time (no decoding there);
``read()`` decodes it. Readings older than ``joint_states_stale_s``, or lacking a joint, are
``ok=False`` with a flag. ``stop()``: zero velocity, then a position command at the
measured pose (hold). The vendor side stops the arm by itself when commands are more
than 0.2 s apart.
"""

from __future__ import annotations

import json
import threading
import time

import numpy as np

from hilstack.configs.schema import ConfigError, RobotConfig, parse_params
from hilstack.drivers.base import Driver, Health, LinkError, Observation
from hilstack.drivers.emulator_process import EmulatorProcess
from hilstack.drivers.sawyer import ros
from hilstack.drivers.sawyer.config import JOINTS, SawyerParams, sawyer_spec

FIRST_STATE_TIMEOUT_S = 10.0


class SawyerDriver(Driver):
    def __init__(self, params: SawyerParams | None = None, backend: str = "real", source: str | None = None):
        super().__init__()
        self.params = params or SawyerParams()
        #: the controller holds position (after a stop) rather than following a velocity
        self._position_hold = False
        self.backend = backend
        self.source = source
        self.spec = sawyer_spec(self.params)
        self._lock = threading.Lock()
        self._latest: tuple[bytes, float] | None = None
        self._received = 0
        self._decode_errors = 0
        self._sent = 0
        self._session = None
        self._pub = None
        self._sub = None
        self._emu: EmulatorProcess | None = None
        self._state = np.full(21, np.nan)
        self._state_t: float | None = None
        self._stamp_s: float | None = None
        self._seq = 0
        self._last_error: str | None = None

    @classmethod
    def from_config(cls, cfg: RobotConfig) -> SawyerDriver:
        return cls(parse_params(cfg, SawyerParams), backend=cfg.backend, source=cfg.source)

    # ------------------------------------------------------------------ lifecycle
    def _on_configure(self) -> None:
        import zenoh

        p = self.params
        if self.backend == "emulated":
            mode, connect = "peer", [self._start_emulator()]
        else:
            if not p.zenoh_connect:
                raise ConfigError(self.source, [("params.zenoh_connect", "no Zenoh endpoint: set the address of the "
                                                 "zenoh-bridge-ros2dds, e.g. ['tcp/192.168.1.20:7447']")])
            mode, connect = p.zenoh_mode, list(p.zenoh_connect)
        c = zenoh.Config()
        c.insert_json5("mode", json.dumps(mode))
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("connect/endpoints", json.dumps(connect))
        if mode == "peer":
            c.insert_json5("listen/endpoints", json.dumps([]))
        self._session = zenoh.open(c)
        self._pub = self._session.declare_publisher(ros.bridge_key(p.joint_command_topic, p.namespace))
        self._sub = self._session.declare_subscriber(ros.bridge_key(p.joint_states_topic, p.namespace),
                                                     self._on_sample)
        deadline = time.monotonic() + FIRST_STATE_TIMEOUT_S
        while time.monotonic() < deadline:
            with self._lock:
                if self._latest is not None:
                    break
            if self._emu is not None and not self._emu.alive:
                raise LinkError(self._emu.failure(f"Sawyer emulator exited with code {self._emu.proc.returncode}"))
            time.sleep(0.01)
        else:
            where = "the emulator" if self.backend == "emulated" else f"{connect}"
            raise LinkError(f"sawyer: no {p.joint_states_topic} within {FIRST_STATE_TIMEOUT_S:.0f} s from {where}; "
                            "is the bridge running and the robot enabled?")
        self._decode()

    def _start_emulator(self) -> str:
        import socket

        with socket.socket() as s:  # a free loopback port for the emulator to listen on
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        endpoint = f"tcp/127.0.0.1:{port}"
        cfg = {"namespace": self.params.namespace, "joint_states_topic": self.params.joint_states_topic,
               "joint_command_topic": self.params.joint_command_topic}
        e = self.params.emulator
        self._emu = EmulatorProcess("hilstack.sim_backends.sawyer.emulator", ["--listen", endpoint, "--config", json.dumps(cfg)],
                                    start_timeout_s=e.start_timeout_s, keep_log=e.keep_log)
        self._emu.start()
        return endpoint

    def _on_cleanup(self) -> None:
        for obj in (self._sub, self._pub):
            try:
                if obj is not None:
                    obj.undeclare()
            except Exception:
                pass
        self._sub = self._pub = None
        if self._session is not None:
            try:
                self._session.close()
            except Exception:
                pass
            self._session = None
        if self._emu is not None:
            self._emu.stop()
            self._emu = None

    # ------------------------------------------------------------------ transport
    def _on_sample(self, sample) -> None:
        # Zenoh's thread: keep the newest bytes, nothing else
        raw = sample.payload.to_bytes()
        t = time.monotonic()
        with self._lock:
            self._latest = (raw, t)
            self._received += 1

    def _decode(self) -> None:
        with self._lock:
            latest = self._latest
        if latest is None or latest[1] == self._state_t:
            return
        raw, t = latest
        try:
            msg = ros.decode_joint_state(raw)
            index = {n: i for i, n in enumerate(msg.name)}
            idx = [index[j] for j in JOINTS]
        except Exception as e:  # a malformed or foreign message: counted, the last good state stays
            self._decode_errors += 1
            self._last_error = f"joint_states not usable: {type(e).__name__}: {e}"
            self._state_t = t
            return
        pos, vel, eff = (np.asarray(a, dtype=np.float64) for a in (msg.position, msg.velocity, msg.effort))
        s = np.full(21, np.nan)
        s[:7] = pos[idx]
        if len(vel) == len(msg.name):
            s[7:14] = vel[idx]
        if len(eff) == len(msg.name):
            s[14:21] = eff[idx]
        self._state = s
        self._state_t = t
        self._stamp_s = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9

    def _publish(self, mode: int, values: np.ndarray) -> None:
        if self._pub is None:
            raise LinkError("sawyer: not connected")
        self._pub.put(ros.encode_joint_command(mode, JOINTS, values))
        self._sent += 1

    # ------------------------------------------------------------------ contract
    def _age_s(self) -> float:
        return float("inf") if self._state_t is None else time.monotonic() - self._state_t

    def _read(self) -> Observation:
        self._decode()
        age = self._age_s()
        stale = not age < self.params.joint_states_stale_s
        finite = bool(np.all(np.isfinite(self._state)))
        self._seq += 1
        return Observation(t_s=self._state_t if self._state_t is not None else time.monotonic(),
                           state=self._state.copy(), seq=self._seq, ok=not stale and finite,
                           flags={"stale_telemetry": stale, "nonfinite_input": not finite},
                           extras={"joint_states_age_s": age, "robot_stamp_s": self._stamp_s})

    def _hold_command(self, obs: Observation) -> np.ndarray:
        if self._position_hold:  # after a stop the controller holds position: zero velocity
            return np.zeros(self.spec.action.dim)
        v = obs.state[7:14]
        if not np.all(np.isfinite(v)):
            raise LinkError("sawyer: joint_states without velocities; cannot hold the measured state")
        return np.clip(v, self.spec.action.low, self.spec.action.high)

    def _on_activate(self) -> None:
        self._publish(ros.VELOCITY_MODE, self._held)

    def _write(self, action: np.ndarray) -> None:
        self._publish(ros.VELOCITY_MODE, action)
        self._position_hold = False

    def _stop(self) -> None:
        if self._pub is None:
            return
        self._publish(ros.VELOCITY_MODE, np.zeros(7))
        self._decode()
        q = self._state[:7]
        if np.all(np.isfinite(q)):
            self._publish(ros.POSITION_MODE, q)
            self._position_hold = True

    def _health(self) -> Health:
        age = self._age_s()
        fresh = age < self.params.joint_states_stale_s
        with self._lock:
            received = self._received
        return Health(ok=bool(self._session is not None and fresh), link_quality=1.0 if fresh else 0.0,
                      frames_sent=self._sent, frames_received=received, corrupt_frames=self._decode_errors,
                      dropped_frames=0, latency_s=None, last_error=self._last_error or self.last_error,
                      extra={"backend": self.backend, "joint_states_age_s": age,
                             "keys": {"joint_states": ros.bridge_key(self.params.joint_states_topic,
                                                                     self.params.namespace),
                                      "joint_command": ros.bridge_key(self.params.joint_command_topic,
                                                                      self.params.namespace)}})
