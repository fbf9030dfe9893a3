"""VelociRoACH firmware emulator: a process that behaves like the robot on the radio link.

It owns one end of a serial link (a pty it creates with ``--print-pty``, or an existing
device with ``--pty PATH``) and stands in for "base-station XBee + air + robot XBee +
dsPIC firmware": it receives the PC's XBee TX64 requests, answers with RX64 frames, and
runs the firmware (1 kHz PID, watchdog, telemetry; ``firmware.py`` of the sim backend)
on the MuJoCo model in real time. The robot's mocap pose is served over UDP
(``hilstack.drivers.mocap.udp.PoseStreamServer``) like a motion-capture system would.

    python -m hilstack.sim_backends.velociroach.emulator --print-pty --pose-port 0 --config '{"telemetry_hz": 100}'

On start it prints one JSON line on stdout, ``{"pty": ..., "pose_port": ..., "pid": ...}``,
then stays quiet on stdout (logs go to stderr). It stops on SIGTERM/SIGINT or when the
process that started it dies (bus/lifetime.py).

Fault injection (for tests of the driver's fault handling), as flags or in the config's
``emulator`` section: ``--corrupt-every N`` (every N-th frame sent is broken, alternating
a bad XBee checksum and a bad MAVLink CRC), ``--garbage`` (noise bytes between frames),
``--silence-after S`` (radio outage S seconds after the first command: nothing is sent or
received any more; the firmware keeps running, so its watchdog stops the motors, and the
mocap stream, a separate system, keeps going). Only in the config's ``emulator`` section
(:class:`hilstack.drivers.velociroach.config.VelociRoachEmulatorParams`): ``pose_silence_after_s`` (the mocap
stream stops S seconds after the first command, the radio keeps going) and
``nonfinite_telemetry_every`` (every N-th telemetry packet carries NaN sensor values) and
``start_upside_down`` (the robot starts on its back, as after a flip).

Lab fixture (``--fixture-port``, drivers/fixture.py): a UDP service beside the
robot, not on its radio, that puts a robot lying on its back or side upright where it
lies. It stands in for the lab's hands: the MuJoCo roach cannot right itself from its
back (docs/reset.md), and the reset supervisor calls it only when its own ``self_right``
step failed. Its port is in the ready line (``fixture_port``).
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import random
import signal
import sys
import time
import tty
from pathlib import Path
from typing import Any

from hilstack.bus.cycle import Rate
from hilstack.bus.lifetime import exit_with_parent
from hilstack.drivers.fixture import FixtureService, service_socket
from hilstack.drivers.velociroach.config import VelociRoachParams, quat_to_rpy
from hilstack.drivers.velociroach.link import FdPort, RadioLink, open_serial, xbee_rx64
from hilstack.drivers.velociroach.mavlink import ROBOT_COMPID, ROBOT_SYSID, EncodeError, MavEncoder, mav
from hilstack.sim_backends.base import RealtimePacer

DEFAULT_PHYSICS = "hilstack.sim_backends.velociroach.backend:VelociRoachSim"
#: firmware PID rate: physics advances in whole milliseconds
FW_DT_S = 0.001
#: never integrate more than this per loop: if the CPU falls behind, sim time slips
#: instead of the loop spiralling (reported as ``realtime_slip_s``)
MAX_CATCHUP_S = 0.05

FAULT_WATCHDOG = mav.ROACH_FAULT_WATCHDOG
FAULT_RX_CORRUPT = mav.ROACH_FAULT_RX_CORRUPT


def log(msg: str) -> None:
    print(f"[velociroach-emulator {os.getpid()}] {msg}", file=sys.stderr, flush=True)


class LabFixture(FixtureService):
    """The lab-fixture service (drivers/fixture.py) on the emulator's MuJoCo model:
    like a person in the lab it picks the robot up and sets it down on its legs at the
    same spot and heading, at rest. The firmware, battery and clock run on untouched."""

    #: upright enough to leave alone: both roll and pitch within acos(0.8) ≈ 37° of level
    UPRIGHT_COS = 0.8
    #: set down this far above the standing height [m]: it drops onto its legs
    DROP_M = 0.003

    ops = ("right",)

    def __init__(self, sim: Any, sock: Any):
        super().__init__(sock)
        self.sim = sim
        # right after reset the robot stands on its tripod (feet straight down, the
        # lowest a foot reaches): no crank angle puts a foot below the ground from here
        self.stand_z_m = float(sim.data.qpos[2])
        self.recoveries = 0

    def upright(self) -> bool:
        roll, pitch, _ = quat_to_rpy(self.sim.data.qpos[3:7])
        return math.cos(roll) >= self.UPRIGHT_COS and math.cos(pitch) >= self.UPRIGHT_COS

    def heading_rad(self) -> float:
        """Heading of the body's forward axis on the ground [rad, world frame]: defined on
        the back or side too, where ZYX Euler yaw jumps."""
        w, x, y, z = (float(v) for v in self.sim.data.qpos[3:7])
        return math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))

    def place(self, upside_down: bool = False) -> None:
        """The robot at rest at its (x, y) and heading, on its legs (or on its back)."""
        import mujoco

        d = self.sim.data
        yaw = self.heading_rad()
        cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
        # yaw about world z, then (upside down) half a turn about the body's x axis
        d.qpos[3:7] = (0.0, cy, sy, 0.0) if upside_down else (cy, 0.0, 0.0, sy)
        d.qpos[2] = self.stand_z_m + (0.03 if upside_down else self.DROP_M)
        d.qvel[0:6] = 0.0  # the free joint: linear and angular velocity
        mujoco.mj_forward(self.sim.model, d)

    def right(self) -> bool:
        """Put the robot on its legs unless it stands upright; True when it acted."""
        if self.upright():
            return False
        self.place()
        self.recoveries += 1
        log(f"lab fixture: robot put back on its legs (recovery {self.recoveries})")
        return True

    def act(self, op: str) -> tuple[bool, str]:  # noqa: ARG002 - its one op
        acted = self.right()
        return acted, "put back on its legs" if acted else "already upright"


def load_physics(target: str, params: VelociRoachParams):
    mod, _, cls = target.partition(":")
    physics = getattr(importlib.import_module(mod), cls)(params)
    if hasattr(physics, "compiled_firmware"):
        physics.compiled_firmware = False  # 1x real time: Python keeps up, and a first compile would stall it
    return physics


class Emulator:
    def __init__(self, params: VelociRoachParams, link: RadioLink, physics: Any, pose_server: Any = None,
                 *, corrupt_every: int = 0, garbage: bool = False, silence_after_s: float | None = None,
                 realtime_factor: float = 1.0, pose_hz: float = 100.0, seed: int = 0,
                 pose_silence_after_s: float | None = None, nonfinite_telemetry_every: int = 0,
                 fixture: LabFixture | None = None):
        self.p = params
        self.fixture = fixture
        self.link = link
        self.sim = physics
        self.pose_server = pose_server
        self.enc = MavEncoder(ROBOT_SYSID, ROBOT_COMPID)
        self.corrupt_every = int(corrupt_every)
        self.garbage = garbage
        self.silence_after_s = silence_after_s
        self.pose_silence_after_s = pose_silence_after_s
        self.nonfinite_telemetry_every = int(nonfinite_telemetry_every)
        self.telemetry_sent = 0
        self.rtf = realtime_factor
        self.pose_period_s = 1.0 / pose_hz
        self.rng = random.Random(seed)
        self.running = True
        self.tel_rate: Rate | None = None
        self.pose_rate: Rate | None = None
        self.last_cmd_seq = 0
        self.last_cmd_t: float | None = None
        self.first_cmd_t: float | None = None
        self.watchdog_tripped = False
        self.rx_corrupt_reported = 0
        self.frames_out = 0
        self.injected_corrupt = 0
        self.injected_garbage = 0
        self.realtime_slip_s = 0.0
        self.mode = "leg_velocity"

    # ------------------------------------------------------------------ tx
    def _after_first_cmd(self, delay_s: float | None) -> bool:
        return (delay_s is not None and self.first_cmd_t is not None
                and time.monotonic() - self.first_cmd_t > delay_s)

    @property
    def silent(self) -> bool:
        return self._after_first_cmd(self.silence_after_s)

    def send(self, frame: bytes) -> None:
        if self.silent:
            return
        self.frames_out += 1
        if self.garbage and self.frames_out % 7 == 0:
            # noise as a radio would produce it between frames (no start delimiter in it,
            # so each burst is exactly one "garbage" event on the other side)
            noise = bytes(self.rng.choice([b for b in range(256) if b != 0x7E]) for _ in range(self.rng.randint(1, 9)))
            self.link.send_raw(noise)
            self.injected_garbage += 1
        if self.corrupt_every and self.frames_out % self.corrupt_every == 0:
            self.injected_corrupt += 1
            if self.injected_corrupt % 2:
                raw = bytearray(xbee_rx64(self.link.robot_addr, frame))
                raw[-1] ^= 0x5A  # bad XBee checksum
            else:
                bad = bytearray(frame)
                bad[-3] ^= 0x01  # payload bit flip: valid XBee frame, bad MAVLink CRC
                raw = bytearray(xbee_rx64(self.link.robot_addr, bytes(bad)))
            self.link.send_raw(bytes(raw))
            return
        self.link.send(frame)

    # ------------------------------------------------------------------ rx
    def handle(self, m: Any, now: float) -> None:
        t = m.get_type()
        fw = self.sim.firmware
        if t in ("ROACH_LEG_VELOCITY_CMD", "ROACH_PWM_CMD"):
            if t == "ROACH_LEG_VELOCITY_CMD":
                lim, a, b = self.p.max_leg_vel_rps, m.left_rps, m.right_rps
            else:
                lim, a, b = 1.0, m.duty_left, m.duty_right
            if not (math.isfinite(a) and math.isfinite(b) and abs(a) <= lim * 1.0001 and abs(b) <= lim * 1.0001):
                # the firmware never trusts the wire: out of range means ignored, and said so
                self.send(self.enc.status_text(mav.ROACH_SEVERITY_ERROR, self.faults(),
                                               f"rejected {t[6:]} {a:.3g},{b:.3g}"))
                return
            if t == "ROACH_LEG_VELOCITY_CMD":
                fw.set_leg_velocity(a, b, self.sim.sim_time_s)
                self.mode = "leg_velocity"
            else:
                fw.set_pwm(a, b, self.sim.sim_time_s)
                self.mode = "pwm"
            self.last_cmd_seq = m.cmd_seq
            self.last_cmd_t = now
            if self.first_cmd_t is None:
                self.first_cmd_t = now
        elif t == "ROACH_PID_GAINS_SET":
            ok = all(math.isfinite(v) and v >= 0 for v in (m.kp, m.ki, m.kd))
            if ok:
                fw.set_gains(m.kp, m.ki, m.kd)
            kp, ki, kd = self.gains()
            res = mav.ROACH_RESULT_ACCEPTED if ok else mav.ROACH_RESULT_REJECTED
            self.send(self.enc.pid_gains(m.request_id, kp, ki, kd, res))
        elif t == "ROACH_PID_GAINS_GET":
            kp, ki, kd = self.gains()
            self.send(self.enc.pid_gains(m.request_id, kp, ki, kd, mav.ROACH_RESULT_CURRENT))
        # HEARTBEAT from the base: nothing to do (the firmware's watchdog is on commands)

    def gains(self) -> tuple[float, float, float]:
        c = self.sim.firmware.config
        return c.kp_duty_per_rps, c.ki_duty_per_rev, c.kd_duty_per_rps2

    # ------------------------------------------------------------------ state
    def faults(self, tel: dict | None = None) -> int:
        fw = self.sim.firmware
        bits = int(fw.faults) if tel is None else int(tel.get("faults", 0))
        if fw.watchdog_tripped:
            bits |= FAULT_WATCHDOG
        if self.link.corrupt_frames > self.rx_corrupt_reported:
            bits |= FAULT_RX_CORRUPT
        return bits

    def check_watchdog(self, now: float) -> None:
        """The firmware's watchdog runs on sim time inside ``advance``; here we only tell
        the base station when it trips (a real firmware sends the same status text)."""
        tripped = bool(self.sim.firmware.watchdog_tripped)
        if tripped and not self.watchdog_tripped and self.last_cmd_t is not None:
            silent_s = now - self.last_cmd_t
            self.send(self.enc.status_text(mav.ROACH_SEVERITY_WARNING, self.faults(),
                                           f"watchdog: no command for {silent_s:.2f}s, motors stopped"))
            log(f"watchdog tripped {silent_s:.3f} s after the last command")
        self.watchdog_tripped = tripped

    def send_telemetry(self) -> None:
        tel = self.sim.telemetry()
        faults = self.faults(tel)
        tel = {**tel, "faults": faults}
        self.telemetry_sent += 1
        if self.nonfinite_telemetry_every and self.telemetry_sent % self.nonfinite_telemetry_every == 0:
            # a sensor glitch as a broken board would send it: a valid frame with NaN in it
            tel = {**tel, "gyro_rps": [math.nan] * 3, "crank_vel_rps": [math.nan, tel["crank_vel_rps"][1]]}
        try:
            frame = self.enc.telemetry(tel, last_cmd_seq=self.last_cmd_seq,
                                       rx_good=self.link.frames_received, rx_corrupt=self.link.corrupt_frames)
        except EncodeError as e:
            log(f"telemetry not encodable: {e}")
            return
        self.rx_corrupt_reported = self.link.corrupt_frames
        self.send(frame)

    def send_pose(self) -> None:
        # mocap is its own system: it keeps streaming through a radio outage
        if self.pose_server is None or self._after_first_cmd(self.pose_silence_after_s):
            return
        pose = self.sim.mocap_pose()
        if pose is not None:
            t_s, pos, quat = pose
            self.pose_server.send(t_s, pos, quat)

    # ------------------------------------------------------------------ loop
    def run(self) -> None:
        """Serve until stopped (SIGTERM, or the parent gone: bus/lifetime.py). Telemetry, pose
        and heartbeat are :class:`~hilstack.bus.cycle.Rate` deadlines (late ones skip the
        boundaries they passed, counted in :meth:`summary`)."""
        t0 = time.monotonic()
        pacer = RealtimePacer(self.sim.sim_time_s, FW_DT_S, MAX_CATCHUP_S, self.rtf, now_s=t0)
        self.tel_rate = tel = Rate(1.0 / self.p.telemetry_hz, t0)
        self.pose_rate = pose = Rate(self.pose_period_s, t0)
        hb = Rate(1.0, t0)
        while self.running:
            now = time.monotonic()
            wait = min(tel.left_s(now), pose.left_s(now), FW_DT_S)
            msgs = self.link.receive(timeout_s=wait)
            if not self.silent:  # radio loss is both ways: the robot hears nothing either
                for m in msgs:
                    self.handle(m, time.monotonic())
            now = time.monotonic()
            self.check_watchdog(now)
            # real time: bring sim time up to the wall clock in whole firmware ticks
            n = pacer.due(now, self.sim.sim_time_s)
            self.realtime_slip_s = pacer.slip_s
            if self.fixture is not None:
                self.fixture.poll()
            if n > 0:
                self.sim.advance(n * FW_DT_S)
            now = time.monotonic()
            if tel.due(now):
                self.send_telemetry()
            if pose.due(now):
                self.send_pose()
            if hb.due(now):
                self.send(self.enc.heartbeat(robot=True, faults=self.faults()))

    def summary(self) -> dict[str, Any]:
        return {
            "frames_out": self.frames_out,
            "injected_corrupt": self.injected_corrupt,
            "injected_garbage": self.injected_garbage,
            "rx_good": self.link.frames_received,
            "rx_corrupt": self.link.corrupt_frames,
            "realtime_slip_s": round(self.realtime_slip_s, 4),
            "sim_time_s": round(self.sim.sim_time_s, 3),
            **(self.tel_rate.counts("telemetry") if self.tel_rate else {}),
            **(self.pose_rate.counts("pose") if self.pose_rate else {}),
            **({"fixture_recoveries": self.fixture.recoveries, "fixture_requests": self.fixture.requests}
               if self.fixture is not None else {}),
        }


def _load_config(arg: str | None) -> dict:
    if not arg:
        return {}
    if arg.lstrip().startswith("{"):
        return json.loads(arg)
    path = Path(arg)
    text = path.read_text()
    if path.suffix in (".yaml", ".yml"):
        import yaml

        data = yaml.safe_load(text) or {}
        return data.get("params", data) if "robot" in data else data
    return json.loads(text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hilstack.sim_backends.velociroach.emulator", description=__doc__.split("\n")[0])
    where = ap.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", help="serial device to serve (e.g. one end of a socat pty pair)")
    where.add_argument("--print-pty", action="store_true", help="create a pty and print its path")
    ap.add_argument("--pose-port", type=int, default=None, help="send the mocap pose to this UDP port (hilstack.drivers.mocap.udp)")
    ap.add_argument("--pose-host", default="127.0.0.1")
    ap.add_argument("--config", help="VelociRoachParams as inline JSON or a JSON/YAML file")
    ap.add_argument("--physics", default=None, help=f"module:Class of the physics (default {DEFAULT_PHYSICS})")
    ap.add_argument("--corrupt-every", type=int, default=None, help="break every N-th frame sent")
    ap.add_argument("--garbage", action="store_true", default=None, help="noise bytes between frames")
    ap.add_argument("--silence-after", type=float, default=None, help="stop transmitting S s after the first command")
    ap.add_argument("--fixture-port", type=int, default=None,
                    help="serve the lab fixture on this UDP port (0: any free port; drivers/fixture.py)")
    args = ap.parse_args(argv)

    params = VelociRoachParams(**_load_config(args.config))
    emu = params.emulator

    def opt(cli: Any, key: str) -> Any:
        return cli if cli is not None else getattr(emu, key)

    physics = load_physics(opt(args.physics, "physics") or DEFAULT_PHYSICS, params)
    physics.configure()
    try:
        physics.reset(0.0, 0.0, 0.0)
    except TypeError:
        physics.reset()

    if args.print_pty:
        master, slave = os.openpty()
        # raw before anyone writes: a cooked pty would echo and translate bytes
        tty.setraw(slave)
        tty.setraw(master)
        path = os.ttyname(slave)
        port: Any = FdPort(master, name=path)
        # keep the slave open so reads on the master do not fail before the driver opens it
        keep_slave = slave
    else:
        path = args.pty
        port = open_serial(path, params.baudrate)
        keep_slave = None
    link = RadioLink(port, role="robot", robot_addr64=params.robot_addr64, name=path)

    pose_server = None
    pose_port = None
    if args.pose_port is not None:
        from hilstack.drivers.mocap.udp import PoseStreamServer

        pose_server = PoseStreamServer(args.pose_host, args.pose_port)
        pose_port = args.pose_port

    fixture = None
    fixture_port = None
    if args.fixture_port is not None:
        sock, fixture_port = service_socket(args.fixture_port)
        fixture = LabFixture(physics, sock)
    if emu.start_upside_down:
        if fixture is None:
            fixture = LabFixture(physics, None)  # its placing code, without a service
        fixture.place(upside_down=True)

    em = Emulator(
        params, link, physics, pose_server,
        corrupt_every=int(opt(args.corrupt_every, "corrupt_every") or 0),
        garbage=bool(opt(args.garbage, "garbage")),
        silence_after_s=opt(args.silence_after, "silence_after_s"),
        realtime_factor=emu.realtime_factor,
        pose_hz=emu.pose_hz,
        seed=emu.seed,
        pose_silence_after_s=emu.pose_silence_after_s,
        nonfinite_telemetry_every=emu.nonfinite_telemetry_every,
        fixture=fixture if fixture_port is not None else None,
    )

    def _stop(signum, frame):  # noqa: ARG001
        em.running = False

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    exit_with_parent(lambda: (log("parent process is gone: exiting"), _stop(None, None)))
    print(json.dumps({"pty": path, "pose_port": pose_port, "fixture_port": fixture_port, "pid": os.getpid()}),
          flush=True)
    log(f"serving {path}, pose udp port {pose_port}, telemetry {params.telemetry_hz} Hz, "
        f"watchdog {params.firmware_watchdog_s} s")
    try:
        em.run()
    except Exception as e:  # a LinkError here means the pty is gone: nothing left to serve
        log(f"stopped: {type(e).__name__}: {e}")
    finally:
        log(f"summary {json.dumps(em.summary())}")
        link.close()
        if pose_server is not None:
            pose_server.close()
        if fixture is not None and fixture.sock is not None:
            fixture.sock.close()
        if keep_slave is not None:
            try:
                os.close(keep_slave)
            except OSError:
                pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
