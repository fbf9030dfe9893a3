"""Settings every robot on a Dynamixel bus shares: the bus (port, baud rate, watchdog, link
timeout), the bus emulator's fault injection, and the check of the Bus Watchdog against the
control period. A robot's params subclass :class:`BusParams` (drivers/widowx/config.py,
drivers/pan_unit/config.py)."""

from __future__ import annotations

from pydantic import Field, ValidationInfo, model_validator

from hilstack.configs.schema import EmulatorParams, EmulatorS, Params, StaleS, bounded_int, finite

#: the bus emulator's pacing (not a safety value)
RealtimeFactor = finite(gt=0, le=100.0, source="emulator pacing: up to 100× the wall clock (not a safety value)")


class DynamixelEmulatorParams(EmulatorParams):
    """``params.emulator``: the bus emulator's faults (sim_backends/dynamixel/emulator.py;
    docs/arms.md). Robots of one bus share one emulator: the first to open the bus starts it."""

    missing_ids: list[int] = Field(default_factory=list, description="servo IDs that never answer")
    hardware_errors: dict[int, int] = Field(default_factory=dict, description="ID → Hardware Error Status bits "
                                            "latched at power-on (0 input voltage, 2 overheating, 3 encoder, "
                                            "4 electrical shock, 5 overload)")
    persistent_errors: bool = Field(False, description="the hardware errors survive reboots")
    corrupt_every: int = Field(0, ge=0, description="every N-th status packet has a bad CRC (0: never)")
    garbage_every: int = Field(0, ge=0, description="noise bytes before every N-th status packet (0: never)")
    start_holding: dict[str, float] | None = Field(None, description="start torqued in position mode at these "
                                                   "joint angles [rad] (default: limp in the sleep pose)")
    realtime_factor: RealtimeFactor = Field(1.0, description="sim seconds per wall-clock second")
    state_file: str | None = Field(None, description="tests: append the servos' state (position, velocity, "
                                   "Bus Watchdog) as JSON lines to this file, without bus traffic")
    state_every_s: EmulatorS = Field(0.02, description="period of the state_file lines [s]")
    linger_s: EmulatorS = Field(0.0, description="tests of host death: keep simulating the servos "
                                "this long after the driver's process died [s]")
    effects: dict[str, float] = Field(default_factory=dict, description="WidowX bench, for calibration: what the "
                                      "arm's servos have that the MuJoCo model lacks (joint_friction_nm, "
                                      "joint_damping_nm_s, input_delay_s; checked by sim_backends/dynamixel/firmware.py)")
    mjcf: str | None = Field(None, description="WidowX bench: built from this MJCF file (e.g. a calibrated one)")


class BusParams(Params):
    """A Dynamixel bus the robots on it share (units in names): every Dynamixel robot's params."""

    port: str | None = Field(None, description="real: the USB-serial adapter, e.g. /dev/ttyUSB0")
    baudrate: int = Field(1_000_000, gt=0, description="servo Baud Rate register (3 = 1 Mbps)")
    #: robots built with the same bus name share one port/emulator/sim world in a process
    bus_name: str = "widowx"
    latency_timer_ms: int = Field(1, ge=1, le=16, description="USB-serial latency timer (docs/arms.md)")
    telemetry_stale_s: StaleS = Field(0.25, description="a reading older than this is not ok")
    link_timeout_periods: bounded_int(ge=2, le=100, source=(
        "≥ 2 periods: one missed status packet is noise on a loaded bus; ≤ 100 periods (5 s at 20 Hz), and the "
        "count times period_s ≤ 10 s (FailAfterS): the servos' own Bus Watchdog stops them after 0.2 s, the "
        "host must not command a silent bus for long")) = Field(10, description="no status from every servo for this many "
                                          "control periods: the device is gone (frozen, unpowered, unplugged): "
                                          "error path")
    bus_watchdog_s: finite(ge=0.04, le=2.54, source=(
        "the X-series Bus Watchdog register (98): 1..127 units of 20 ms, 0.02..2.54 s; ≥ 2 control periods "
        "so a live host never trips it")) = Field(
        0.2, description="the servos' Bus Watchdog: with no instruction packet for this long they stop by "
                         "themselves (host died); rounded up to 20 ms, at least 2 control periods")
    stop_confirm_timeout_s: finite(gt=0, le=1.0, source=(
        "≤ 1 s: half of `hil estop`'s default wait for the acknowledgements (2 s), which carry the confirmation; "
        "the stop's hold is written before it, so it only bounds how long the read-back is retried")) = Field(
        0.5, description="a stop's read-back (stop_confirmed) is retried, one read at most 0.8 control period each, "
                         "until every servo reports the hold or this much time passed in all")
    reboot_on_hardware_error: bool = Field(False, description="reboot a servo with a latched hardware error "
                                           "at configure (after the operator checked why)")
    emulator: DynamixelEmulatorParams = Field(default_factory=DynamixelEmulatorParams,
                                              description="emulator settings and fault injection")
    sim: dict = Field(default_factory=dict, description="sim world settings")

    @model_validator(mode="after")
    def _stale_before_error(self):
        """A silent bus reads stale (ok False) before it takes the error path."""
        period = getattr(self, "period_s", None)
        if period is not None and not self.telemetry_stale_s < self.link_timeout_periods * period:
            raise ValueError(f"telemetry_stale_s {self.telemetry_stale_s:g} s must be shorter than the error "
                             f"deadline link_timeout_periods x period_s = {self.link_timeout_periods * period:g} s")
        return self


def check_watchdog(period_s: float, info: ValidationInfo) -> float:
    """``period_s`` (declared after ``bus_watchdog_s``) against the watchdog."""
    wd = info.data.get("bus_watchdog_s")
    if wd is not None and wd < 2 * period_s:
        raise ValueError(f"bus_watchdog_s {wd:g} must be at least 2 control periods (2 x period_s = "
                         f"{2 * period_s:g} s): shorter stops the servos between commands")
    return period_s
