"""The reset arm's controller inside the hand's firmware emulator: the arm in the
emulator's scene, served over the UDP link of drivers/reset_arm/protocol.py.

The emulator (sim_backends/shadow_hand/emulator.py, with ``params.sim.reset_station`` and
``params.emulator.arm_port``) calls :meth:`ArmServer.poll` every loop (newest valid
command applied, bad frames counted and refused) and :meth:`ArmServer.send_state` at its
telemetry rate. Like a real arm controller it holds the measured pose when commands stop
for ``watchdog_s``.
"""

from __future__ import annotations

import socket

import numpy as np

from hilstack.drivers.reset_arm.protocol import QUERY, ProtocolError, decode_command, encode_state
from hilstack.sim_backends.reset_arm.backend import arm_command, arm_hold, arm_state
from hilstack.sim_backends.reset_arm.model import ArmIndex


class ArmServer:
    def __init__(self, scene, port: int, host: str = "127.0.0.1", watchdog_s: float = 0.5):
        self.scene = scene
        self.ix = ArmIndex(scene.model)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, port))
        self.sock.setblocking(False)
        self.watchdog_s = watchdog_s
        self.client: tuple[str, int] | None = None
        self.last_cmd_t: float | None = None
        self.bad_frames = 0
        self.commands = 0
        self.watchdog_holds = 0
        self._seq = 0

    def fileno(self) -> int:
        return self.sock.fileno()

    def poll(self, now_s: float) -> None:
        newest = None
        while True:
            try:
                raw, addr = self.sock.recvfrom(512)
            except BlockingIOError:
                break
            if raw == QUERY:
                self.client = addr
                continue
            try:
                newest = decode_command(raw)[1]
                self.client = addr
            except ProtocolError:
                self.bad_frames += 1
        with self.scene.world_lock:
            if newest is not None:
                arm_command(self.scene, self.ix, newest)
                self.commands += 1
                self.last_cmd_t = now_s
            elif self.last_cmd_t is not None and now_s - self.last_cmd_t > self.watchdog_s:
                arm_hold(self.scene, self.ix)
                self.watchdog_holds += 1
                self.last_cmd_t = None

    def send_state(self) -> None:
        if self.client is None:
            return
        with self.scene.world_lock:
            t, s = arm_state(self.scene, self.ix)
        self._seq += 1
        try:
            self.sock.sendto(encode_state(self._seq, t, np.asarray(s)), self.client)
        except OSError:
            pass  # the host went away; it asks again when it is back

    def close(self) -> None:
        self.sock.close()
