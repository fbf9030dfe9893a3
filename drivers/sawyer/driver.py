"""Sawyer driver: the contract over Zenoh with ROS 2 messages (CDR via rosbags).

backend "real": connects to ``params.zenoh_connect`` (a zenoh-bridge-ros2dds beside the
robot's ROS 2 side); subscribes ``sensor_msgs/JointState`` on the joint-states topic and
publishes ``intera_core_msgs/JointCommand`` (velocity mode) on the command topic, under
the keys the bridge uses (drivers/sawyer/ros.py).
backend "emulated": the same code against ``python -m hilstack.sim_backends.sawyer.emulator``, a
process playing the robot side on MuJoCo, started here on a loopback endpoint.

Zenoh's callback only queues the samples with their arrival times (no decoding there);
``read()`` decodes them. The joint states are the driver's one input
(:class:`hilstack.drivers.base.Freshness`): only a message that decodes, names every joint
of the arm with a position, velocity and effort each, all finite, refreshes it. A message
that does not decode or lacks a joint or a field is counted (``corrupt_frames``,
``joint_states_invalid_samples``) and flagged ``invalid_input``; one with NaN/inf is counted
(``joint_states_nonfinite_samples``) and flagged ``nonfinite_input``; neither is used. A
reading older than ``joint_states_stale_s`` is ``ok=False`` (``stale_telemetry``); no usable
joint states for ``link_timeout_periods`` control periods (robot, bridge or link frozen or
dead), or the emulator process gone, takes the error path (stop, UNCONFIGURED, LinkError).
``stop()``: zero velocity, then a position command at the measured pose (hold). The vendor
side stops the arm by itself when commands are more than 0.2 s apart.
"""

from __future__ import annotations

import collections
import json
import threading
import time

import numpy as np

from hilstack.configs.schema import ConfigError
from hilstack.drivers.base import Driver, Flag, Freshness, Health, Inputs, LinkError, Observation
from hilstack.drivers.emulator_process import EmulatorProcess, emulator_module
from hilstack.drivers.sawyer import ros
from hilstack.drivers.sawyer.config import JOINTS, SawyerParams, sawyer_spec

FIRST_STATE_TIMEOUT_S = 10.0
#: joint states queued between two reads (100 Hz stream, reads at >= 6.7 Hz); older ones are dropped and counted
INBOX_SIZE = 64


class SawyerDriver(Driver):
    params_type = SawyerParams

    def __init__(self, params: SawyerParams | None = None, backend: str = "real", source: str | None = None):
        super().__init__()
        self.params = params or SawyerParams()
        #: the controller holds position (after a stop) rather than following a velocity
        self._position_hold = False
        self.backend = backend
        self.source = source
        self.spec = sawyer_spec(self.params)
        self._lock = threading.Lock()
        self._inbox: collections.deque[tuple[bytes, float]] = collections.deque()
        self._received = 0
        self._dropped = 0
        self._decode_errors = 0
        self._nonfinite = 0
        self.inputs = Inputs(Freshness.fail_after_periods(
            "joint_states", self.params.joint_states_stale_s, Flag.STALE_TELEMETRY,
            self.params.link_timeout_periods, self.params.period_s))
        self._sent = 0
        self._session = None
        self._pub = None
        self._sub = None
        self._emu: EmulatorProcess | None = None
        self._state = np.full(21, np.nan)
        self._state_t: float | None = None
        self._stamp_s: float | None = None
        self._seq = 0

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
        with self._lock:
            self._inbox.clear()
        self._state = np.full(21, np.nan)
        self._state_t = self._stamp_s = None
        self.inputs.start(time.monotonic())
        self._session = zenoh.open(c)
        self._pub = self._session.declare_publisher(ros.bridge_key(p.joint_command_topic, p.namespace))
        self._sub = self._session.declare_subscriber(ros.bridge_key(p.joint_states_topic, p.namespace),
                                                     self._on_sample)
        deadline = time.monotonic() + FIRST_STATE_TIMEOUT_S
        while time.monotonic() < deadline:
            self._decode()
            if self._state_t is not None:
                break
            if self._emu is not None and not self._emu.alive:
                raise LinkError(self._emu.failure(f"Sawyer emulator exited with code {self._emu.proc.returncode}"))
            time.sleep(0.01)
        else:
            where = "the emulator" if self.backend == "emulated" else f"{connect}"
            raise LinkError(f"sawyer: no usable {p.joint_states_topic} within {FIRST_STATE_TIMEOUT_S:.0f} s from "
                            f"{where} ({self._received} received, {self._decode_errors} invalid, {self._nonfinite} "
                            "with NaN/inf); is the bridge running and the robot enabled?")

    def _start_emulator(self) -> str:
        from hilstack.bus.ports import free_endpoint

        # the emulator's loopback endpoint, below the ephemeral range (bus/ports.py): a bind(0)
        # port could be taken by any Zenoh session's ephemeral listener or outgoing link while
        # the emulator starts (seconds on a loaded machine)
        endpoint = free_endpoint()
        cfg = {"namespace": self.params.namespace, "joint_states_topic": self.params.joint_states_topic,
               "joint_command_topic": self.params.joint_command_topic}
        e = self.params.emulator
        self._emu = EmulatorProcess(emulator_module("sawyer"), ["--listen", endpoint, "--config", json.dumps(cfg)],
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
        # Zenoh's thread: queue the bytes with their arrival time, nothing else
        raw = sample.payload.to_bytes()
        t = time.monotonic()
        with self._lock:
            if len(self._inbox) >= INBOX_SIZE:
                self._inbox.popleft()
                self._dropped += 1
            self._inbox.append((raw, t))
            self._received += 1

    def _decode(self) -> None:
        """Take every queued joint state into the input: the usable ones refresh it (the
        newest becomes the state), the others are counted and flagged, never used."""
        with self._lock:
            batch = list(self._inbox)
            self._inbox.clear()
        fresh = self.inputs["joint_states"]
        for raw, t in batch:
            try:
                msg = ros.decode_joint_state(raw)
                s = self._complete(msg)
            except Exception as e:  # malformed, foreign or incomplete: counted, the last good state stays
                self._decode_errors += 1
                fresh.reject(f"joint_states not usable: {type(e).__name__}: {e}")
                continue
            finite = bool(np.all(np.isfinite(s)))
            fresh.update(t, finite)
            if not finite:
                self._nonfinite += 1
                continue
            self._state, self._state_t = s, t
            self._stamp_s = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9

    @staticmethod
    def _complete(msg) -> np.ndarray:
        """The 21-D state from a JointState that names every joint of the arm with a position,
        a velocity and an effort each; ValueError naming what is missing otherwise."""
        names = list(msg.name)
        missing = [j for j in JOINTS if j not in names]
        if missing:
            raise ValueError(f"no {missing} in the message (it names {names[:10]})")
        short = [f for f in ("position", "velocity", "effort") if len(getattr(msg, f)) != len(names)]
        if short:
            raise ValueError(f"{short} do not have one value per name ({len(names)})")
        idx = [names.index(j) for j in JOINTS]
        return np.concatenate([np.asarray(getattr(msg, f), dtype=np.float64)[idx]
                               for f in ("position", "velocity", "effort")])

    def _publish(self, mode: int, values: np.ndarray) -> None:
        if self._pub is None:
            raise LinkError("sawyer: not connected")
        self._pub.put(ros.encode_joint_command(mode, JOINTS, values))
        self._sent += 1

    # ------------------------------------------------------------------ contract
    def _age_s(self) -> float:
        return float("inf") if self._state_t is None else time.monotonic() - self._state_t

    def _check_link(self) -> None:
        """The emulator process gone (killed, crashed): the error path at once, with its log."""
        emu = self._emu
        if emu is not None and emu.proc is not None and not emu.alive:
            self.fail_link(emu.failure(f"sawyer: the emulator exited with code {emu.proc.returncode}"))

    def _refresh_inputs(self) -> None:
        self._decode()

    def _read(self) -> Observation:
        self._check_link()
        self._decode()
        now = time.monotonic()
        ok, flags = self.inputs.assess(now, report=True)
        self._seq += 1
        return Observation(t_s=self._state_t if self._state_t is not None else now,
                           state=self._state.copy(), seq=self._seq, ok=ok, flags=flags,
                           extras={"joint_states_age_s": self._age_s(), "robot_stamp_s": self._stamp_s})

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
        self._check_link()
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
        now = time.monotonic()
        ok, _ = self.inputs.assess(now)
        fresh = not self.inputs["joint_states"].stale(now)
        with self._lock:
            received, dropped = self._received, self._dropped
        return Health(ok=bool(self._session is not None and ok), link_quality=1.0 if fresh else 0.0,
                      frames_sent=self._sent, frames_received=received, corrupt_frames=self._decode_errors,
                      dropped_frames=dropped, latency_s=None, last_error=self.last_error,
                      extra={"backend": self.backend, **self.inputs.ages(now),
                             "keys": {"joint_states": ros.bridge_key(self.params.joint_states_topic,
                                                                     self.params.namespace),
                                      "joint_command": ros.bridge_key(self.params.joint_command_topic,
                                                                      self.params.namespace)}})
