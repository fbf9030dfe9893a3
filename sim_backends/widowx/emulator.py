"""The WidowX bench's Dynamixel bus emulator (sim_backends/dynamixel/emulator.py on this bench).

It owns the device end of a serial link (a pty it creates with ``--print-pty``) and
answers Protocol 2.0 instruction packets for every servo of the simulated bench (the
arm's six IDs and the mechanism's two): PING, READ, WRITE, REBOOT, SYNC_READ,
SYNC_WRITE, each servo with its own control table (:mod:`.firmware`), on the MuJoCo
world (:mod:`.world`) advanced in real time in 1 ms servo ticks.

It must be a separate process: dynamixel-sdk busy-polls the port and starves any thread
of its own process (docs/arms.md).

    python -m hilstack.sim_backends.widowx.emulator --print-pty --config '{"missing_ids": [8]}'

On start it prints one JSON line ``{"pty": ..., "pid": ...}`` on stdout; logs go to
stderr. It stops on SIGTERM, on SIGINT unless a parent started it (bus/lifetime.py: Ctrl-C
in the driver's terminal must not cut the bus before the driver's stop), or when the parent dies.

Fault injection (config keys): ``missing_ids`` (these IDs never answer, as an unplugged
servo), ``hardware_errors`` ({id: bits}: latched at power-on, cleared by a reboot
unless ``persistent_errors``), ``corrupt_every`` (every N-th status packet gets a bad
CRC), ``garbage_every`` (noise bytes before every N-th status packet). ``start_holding``
({joint: rad}) starts the arm torqued in position mode at that pose instead of limp in
its sleep pose.

Effects the MuJoCo model lacks (config ``effects``, on the arm's servos; for calibration,
docs/calibration.md "The robots' own MuJoCo models"): ``joint_friction_nm`` (Coulomb
friction in each gearbox), ``joint_damping_nm_s`` (viscous), ``input_delay_s`` (a goal acts
this long after it was written). ``mjcf``: the bench from an MJCF file (a calibrated one).

Host death (tests): ``state_file`` (a path) gets one JSON line every ``state_every_s``
wall-clock seconds: ``{"t": monotonic [s], "sim_t": [s], "servos": {id: [position
rad, velocity rad/s, Bus Watchdog]}}``, read without sending the servos a packet (a
read over the bus would feed their watchdog). ``linger_s``: when the parent process
dies, go on simulating the servos this long before exiting, as a real bench stays
powered after its host died (default 0: exit at once).
"""

from __future__ import annotations

import sys
from typing import Any

from hilstack.sim_backends.dynamixel.emulator import main as serve
from hilstack.sim_backends.widowx.world import ArmWorld


def make_world(cfg: dict[str, Any]) -> ArmWorld:
    return ArmWorld(cfg.get("arm_ids"), cfg.get("mech_ids"), start_holding=cfg.get("start_holding"),
                    effects=cfg.get("effects"), mjcf=cfg.get("mjcf"))


def main(argv: list[str] | None = None) -> int:
    return serve(argv, make_world, "python -m hilstack.sim_backends.widowx.emulator")


if __name__ == "__main__":
    sys.exit(main())
