"""Shadow Hand firmware emulator: a process that behaves like the hand on its CAN bus.

It runs the motor-board firmware (:mod:`.firmware`: 20 joint position loops at 1 kHz,
watchdog, e-stop) on the MuJoCo hand (:mod:`.backend`) in real time and speaks the
hand's CAN database (``drivers/shadow_hand/shadow_hand.dbc``) over one of:

* ``--transport slcan``: it plays a USB-CAN adapter in SLCAN (Lawicel) mode on a pty it
  creates (``--print-pty``) or on ``--pty PATH``. The host's python-can ``slcan``
  interface opens it like a real adapter (``C``, ``S8``, ``O``, each answered ``\\r``;
  ``tIIILDD..`` frames answered ``z``) and receives the hand's frames as ``tIIILDD..\\r``.
* ``--transport udp_multicast``: python-can's UDP multicast bus (``--channel`` an IPv4
  group, ``--udp-port``). The bus echoes every frame to every member, so the emulator
  keeps only host frames (``protocol.HOST_IDS``).

With ``--ball-ports P0,P1`` it also stands in for the ball tracker: each ball's
position streams to its UDP port in the ``hilstack.drivers.mocap.udp`` format at the telemetry rate.
With ``--fixture-port`` (``params.emulator.lab_fixture``) it serves the lab fixture
(drivers/fixture.py, op ``place``): the lab's hands, which put the balls back at rest in the
palm (:meth:`ShadowHandSim.place_balls`); its port is in the ready line (``fixture_port``).
With the reset station in the scene (``params.sim.reset_station``) and
``params.emulator.arm_port``, it also runs the reset arm's controller on that UDP port
(sim_backends/reset_arm/server.py), in the same world as the hand.

On start it prints one JSON line on stdout (``{"transport", "channel", "port", "pid"}``)
and then logs to stderr. It stops on SIGTERM/SIGINT or when the process that started it dies
(bus/lifetime.py).

Fault injection (flags or the config's ``emulator`` section), counted from the first
target frame: ``corrupt_every`` N (every N-th telemetry frame is broken: alternately a
malformed SLCAN line, or on UDP a frame one byte short, and a frame with a wrong length),
``drop_every`` N (every N-th telemetry frame is not sent), ``bus_off_after_s`` /
``bus_off_s`` (the CAN controller goes bus-off: nothing in or out for that long, then it
recovers and reports FAULT_BUS_OFF once), ``motor_fault_after_s`` / ``motor_fault_joint``
(that actuated joint's motor goes limp and its fault bit is set).
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import sys
import time
import tty
from typing import Any

from hilstack.bus.cycle import Rate
from hilstack.bus.lifetime import exit_with_parent
from hilstack.drivers.fixture import FixtureService, service_socket
from hilstack.drivers.shadow_hand.config import ShadowHandParams
from hilstack.drivers.shadow_hand.protocol import (
    HOST_IDS,
    ID_ESTOP,
    ID_HOST_HEARTBEAT,
    ID_TARGET,
    ProtocolError,
    decode,
    decode_targets,
    encode_telemetry,
)
from hilstack.sim_backends.base import RealtimePacer
from hilstack.sim_backends.shadow_hand.backend import ShadowHandSim

FW_DT_S = 0.001
MAX_CATCHUP_S = 0.05  # never integrate more per loop: if the CPU falls behind, time slips


def log(msg: str) -> None:
    print(f"[shadow-hand-emulator {os.getpid()}] {msg}", file=sys.stderr, flush=True)


class SlcanDevice:
    """The adapter side of SLCAN on a raw pty master: parses the host's ASCII commands,
    answers them, and writes the hand's frames as ``tIIILDD..\\r`` while the channel is open."""

    def __init__(self, fd: int):
        self.fd = fd
        self.buf = bytearray()
        self.open = False
        self.bad_lines = 0
        self.tx_overflows = 0

    def fileno(self) -> int:
        return self.fd

    def _reply(self, b: bytes) -> None:
        try:
            os.write(self.fd, b)
        except BlockingIOError:
            # the host is not reading (a starved process): like an adapter's full USB
            # buffer, the frame is lost; the host sees it as a dropped frame
            self.tx_overflows += 1
        except OSError:
            pass  # EIO: the host closed the port; nothing to deliver to

    def recv(self) -> list[tuple[int, bytes]]:
        try:
            chunk = os.read(self.fd, 4096)
        except (BlockingIOError, InterruptedError):
            return []
        except OSError:
            return []  # EIO: nobody has the slave open (yet/any more)
        self.buf.extend(chunk)
        frames = []
        while b"\r" in self.buf:
            line, _, rest = self.buf.partition(b"\r")
            self.buf = bytearray(rest)
            f = self._command(line.decode("ascii", errors="replace"))
            if f is not None:
                frames.append(f)
        return frames

    def _command(self, line: str) -> tuple[int, bytes] | None:
        if not line:
            return None
        c = line[0]
        if c in "SsC":
            if c == "C":
                self.open = False
            self._reply(b"\r")
        elif c in "OL":
            self.open = True
            self._reply(b"\r")
        elif c == "V":
            self._reply(b"V1013\r")
        elif c == "F":
            self._reply(b"F00\r")
        elif c == "t":
            try:
                mid = int(line[1:4], 16)
                n = int(line[4])
                data = bytes.fromhex(line[5:5 + 2 * n])
                if len(data) != n or len(line) != 5 + 2 * n or mid > 0x7FF or n > 8:
                    raise ValueError("length or id out of range")
            except (ValueError, IndexError):  # short, non-hex or inconsistent line
                self.bad_lines += 1
                self._reply(b"\a")
                return None
            self._reply(b"z\r")
            return (mid, data) if self.open else None
        else:
            self._reply(b"\a")  # the adapter's error answer
        return None

    def send(self, mid: int, data: bytes) -> None:
        if self.open:
            self._reply(f"t{mid:03X}{len(data)}{data.hex().upper()}\r".encode())

    def send_raw(self, line: bytes) -> None:
        if self.open:
            self._reply(line)

    def close(self) -> None:
        pass


class UdpDevice:
    """python-can's udp_multicast bus; drops the frames it hears from itself."""

    def __init__(self, group: str, port: int):
        import can

        self.bus = can.Bus(interface="udp_multicast", channel=group, port=port, fd=False)
        self.open = True

    def fileno(self) -> int:
        return self.bus._multicast._socket.fileno()

    def recv(self) -> list[tuple[int, bytes]]:
        out = []
        while True:
            msg = self.bus.recv(timeout=0.0)
            if msg is None:
                return out
            if msg.arbitration_id in HOST_IDS:
                out.append((msg.arbitration_id, bytes(msg.data)))

    def send(self, mid: int, data: bytes) -> None:
        import can

        self.bus.send(can.Message(arbitration_id=mid, data=data, is_extended_id=False))

    def close(self) -> None:
        self.bus.shutdown()


class Emulator:
    def __init__(self, params: ShadowHandParams, device: Any, physics: ShadowHandSim, *, transport: str,
                 ball_servers: list | None = None, arm_server: Any = None, fixture: LabFixture | None = None):
        self.p = params
        #: the lab's hands (the lab fixture's ``place``), when served
        self.fixture = fixture
        self.ball_servers = ball_servers or []
        #: the reset arm's controller (sim_backends/reset_arm/server.py), with a reset station
        self.arm = arm_server
        self.dev = device
        self.sim = physics
        self.transport = transport
        e = params.emulator
        self.corrupt_every = e.corrupt_every
        self.drop_every = e.drop_every
        self.bus_off_after_s = e.bus_off_after_s
        self.bus_off_s = e.bus_off_s
        self.motor_fault_after_s = e.motor_fault_after_s
        self.motor_fault_joint = e.motor_fault_joint
        self.running = True
        self.tel_rate: Rate | None = None
        self.first_cmd_t: float | None = None
        self.cycle = 0
        self.rx_error_count = 0
        self.tel_frames = 0
        self.injected_corrupt = 0
        self.injected_drop = 0
        self.bus_off_events = 0
        self.realtime_slip_s = 0.0

    # ------------------------------------------------------------------ faults
    def _since_first_cmd(self, now: float) -> float | None:
        return None if self.first_cmd_t is None else now - self.first_cmd_t

    def bus_off(self, now: float) -> bool:
        t = self._since_first_cmd(now)
        if t is None or self.bus_off_after_s is None:
            return False
        return float(self.bus_off_after_s) <= t < float(self.bus_off_after_s) + self.bus_off_s

    # ------------------------------------------------------------------ rx
    def handle(self, mid: int, data: bytes, now: float) -> None:
        fw = self.sim.firmware
        t_sim = self.sim.sim_time_s
        try:
            if mid in ID_TARGET:
                first, vals = decode_targets(mid, data)
                if self.first_cmd_t is None:
                    self.first_cmd_t = now
                if not fw.set_targets(first, vals, t_sim) and not fw.estop:
                    self.rx_error_count += 1
            elif mid == ID_HOST_HEARTBEAT:
                decode(mid, data)
                fw.heartbeat(t_sim)
            elif mid == ID_ESTOP:
                _, v = decode(mid, data)
                fw.set_estop(v["engage"] >= 1)
                log(f"e-stop {'engaged' if v['engage'] >= 1 else 'released'}")
        except ProtocolError as e:
            # the firmware never trusts the wire: a bad frame is refused and reported
            fw.rx_error = True
            self.rx_error_count += 1
            log(f"refused frame: {e}")

    # ------------------------------------------------------------------ tx
    def send_telemetry(self) -> None:
        q, qd, eff = self.sim.joint_state()
        fw = self.sim.firmware
        frames = encode_telemetry(q, qd, eff, mode=fw.mode, faults=fw.faults, motor_fault_mask=fw.motor_fault_mask,
                                  cycle=self.cycle, rx_error_count=self.rx_error_count, t_fw_ms=fw.t_fw_ms)
        self.cycle = (self.cycle + 1) % 256
        fw.bus_off_event = False  # reported once
        fw.rx_error = False
        for mid, data in frames:
            self.tel_frames += 1
            armed = self.first_cmd_t is not None
            if armed and self.drop_every and self.tel_frames % self.drop_every == 0:
                self.injected_drop += 1
                continue
            if armed and self.corrupt_every and self.tel_frames % self.corrupt_every == 0:
                self.injected_corrupt += 1
                self._send_corrupt(mid, data)
                continue
            self.dev.send(mid, data)

    def send_balls(self) -> None:
        """The ball tracker's stand-in: each ball's position [m, world] on its own stream."""
        if not self.ball_servers:
            return
        balls = self.sim.balls_m()
        for srv, pos in zip(self.ball_servers, balls, strict=True):
            srv.send(self.sim.sim_time_s, pos, (1.0, 0.0, 0.0, 0.0))

    def _send_corrupt(self, mid: int, data: bytes) -> None:
        if self.transport == "slcan" and self.injected_corrupt % 2:
            # a line the adapter garbled: non-hex data digits
            self.dev.send_raw(f"t{mid:03X}{len(data)}{'ZZ' * len(data)}\r".encode())
        else:
            self.dev.send(mid, data[:-1])  # one byte short of what the DBC says

    # ------------------------------------------------------------------ loop
    def run(self) -> None:
        """Serve until stopped (SIGTERM, or the parent gone: bus/lifetime.py). Telemetry is a
        :class:`~hilstack.bus.cycle.Rate` deadline (a late one skips the boundaries it passed,
        counted in :meth:`summary`)."""
        t0 = time.monotonic()
        pacer = RealtimePacer(self.sim.sim_time_s, FW_DT_S, MAX_CATCHUP_S, now_s=t0)
        self.tel_rate = tel = Rate(1.0 / self.p.telemetry_hz, t0)
        was_off = False
        fw = self.sim.firmware
        while self.running:
            now = time.monotonic()
            r, _, _ = select.select([self.dev], [], [], min(tel.left_s(now), FW_DT_S))
            frames = self.dev.recv() if r else []
            now = time.monotonic()
            off = self.bus_off(now)
            if off and not was_off:
                self.bus_off_events += 1
                log("bus-off: CAN controller off the bus")
            if was_off and not off:
                fw.bus_off_event = True
                log("bus-off recovery: back on the bus")
            was_off = off
            if not off:
                for mid, data in frames:
                    self.handle(mid, data, now)
            t = self._since_first_cmd(now)
            if (self.motor_fault_after_s is not None and t is not None and t >= float(self.motor_fault_after_s)
                    and not fw.motor_fault_mask >> self.motor_fault_joint & 1):
                fw.inject_motor_fault(self.motor_fault_joint)
                log(f"motor fault injected on actuated joint {self.motor_fault_joint}")
            if self.arm is not None:
                self.arm.poll(now)
            if self.fixture is not None:
                self.fixture.poll()
            n = pacer.due(now, self.sim.sim_time_s)
            self.realtime_slip_s = pacer.slip_s
            if n > 0:
                self.sim.advance(n * FW_DT_S)
            now = time.monotonic()
            if tel.due(now):
                if not off:
                    self.send_telemetry()
                self.send_balls()  # the camera tracker is its own system: bus-off does not stop it
                if self.arm is not None:
                    self.arm.send_state()  # the arm has its own controller and link

    def summary(self) -> dict[str, Any]:
        return {"telemetry_frames": self.tel_frames, "tx_overflows": getattr(self.dev, "tx_overflows", 0), "injected_corrupt": self.injected_corrupt,
                "injected_drop": self.injected_drop, "bus_off_events": self.bus_off_events,
                "rx_error_count": self.rx_error_count, "realtime_slip_s": round(self.realtime_slip_s, 4),
                "sim_time_s": round(self.sim.sim_time_s, 3),
                **(self.tel_rate.counts("telemetry") if self.tel_rate else {})}


class LabFixture(FixtureService):
    """The lab-fixture service (drivers/fixture.py) on the hand's MuJoCo world: like a person
    in the lab it puts both balls back at rest in the palm (``place``). Polled from the loop."""

    ops = ("place",)

    def __init__(self, sim: ShadowHandSim, sock: Any):
        super().__init__(sock)
        self.sim = sim
        self.placements = 0

    def act(self, op: str) -> tuple[bool, str]:  # noqa: ARG002 - its one op
        self.sim.place_balls()
        self.placements += 1
        log(f"lab fixture: balls put back in the palm ({self.placements})")
        return True, "balls put back in the palm"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m hilstack.sim_backends.shadow_hand.emulator",
                                 description=__doc__.split("\n")[0])
    ap.add_argument("--transport", choices=("slcan", "udp_multicast"), default="slcan")
    ap.add_argument("--print-pty", action="store_true", help="slcan: create a pty and print its path")
    ap.add_argument("--pty", help="slcan: serve this serial device (e.g. one end of a socat pty pair)")
    ap.add_argument("--channel", default="239.74.163.2", help="udp_multicast: IPv4 multicast group")
    ap.add_argument("--udp-port", type=int, default=43113, help="udp_multicast: UDP port")
    ap.add_argument("--config", help="ShadowHandParams as inline JSON")
    ap.add_argument("--ball-ports", help="P0,P1: stream the two ball positions to these UDP ports (hilstack.drivers.mocap.udp)")
    ap.add_argument("--fixture-port", type=int, default=None,
                    help="serve the lab fixture on this UDP port (0: any free port; drivers/fixture.py)")
    args = ap.parse_args(argv)

    params = ShadowHandParams(**(json.loads(args.config) if args.config else {}))
    physics = ShadowHandSim(params)
    physics.configure()

    keep_slave = None
    if args.transport == "slcan":
        if args.print_pty:
            master, slave = os.openpty()
            tty.setraw(slave)  # raw before anyone writes: a cooked pty echoes and translates
            tty.setraw(master)
            os.set_blocking(master, False)
            channel = os.ttyname(slave)
            keep_slave = slave  # reads on the master fail with EIO while no slave is open
            dev: Any = SlcanDevice(master)
        elif args.pty:
            fd = os.open(args.pty, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            tty.setraw(fd)
            channel = args.pty
            dev = SlcanDevice(fd)
        else:
            ap.error("--transport slcan needs --print-pty or --pty PATH")
        port = None
    else:
        dev = UdpDevice(args.channel, args.udp_port)
        channel, port = args.channel, args.udp_port

    ball_servers = []
    if args.ball_ports:
        from hilstack.drivers.mocap.udp import PoseStreamServer

        for i, ball_port in enumerate(args.ball_ports.split(",")):
            ball_servers.append(PoseStreamServer("127.0.0.1", int(ball_port), body_id=i + 1))
    arm_server = None
    if params.emulator.arm_port:
        from hilstack.sim_backends.reset_arm.server import ArmServer

        if physics.hand.station is None:
            ap.error("emulator.arm_port needs the reset station in the scene (params.sim.reset_station: true)")
        arm_server = ArmServer(physics, params.emulator.arm_port)
    fixture, fixture_port = None, None
    if args.fixture_port is not None:
        sock, fixture_port = service_socket(args.fixture_port)
        fixture = LabFixture(physics, sock)
    em = Emulator(params, dev, physics, transport=args.transport, ball_servers=ball_servers, arm_server=arm_server,
                  fixture=fixture)

    def _stop(signum, frame):  # noqa: ARG001
        em.running = False

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    # also `kill -USR1 PID`: where is it stuck (stderr; bus/lifetime.dump_stacks_on_signal)
    exit_with_parent(lambda: (log("parent process is gone: exiting"), _stop(None, None)))
    print(json.dumps({"transport": args.transport, "channel": channel, "port": port, "pid": os.getpid(),
                      **({"fixture_port": fixture_port} if fixture_port else {})}), flush=True)
    log(f"serving {args.transport} on {channel}{'' if port is None else f':{port}'}")
    try:
        em.run()
    finally:
        log(f"summary {json.dumps(em.summary())}")
        dev.close()
        for srv in ball_servers:
            srv.close()
        if arm_server is not None:
            arm_server.close()
        if fixture is not None:
            fixture.sock.close()
        if keep_slave is not None:
            os.close(keep_slave)
    return 0


if __name__ == "__main__":
    sys.exit(main())
