"""Motion capture behind the driver contract: a sensor (no action channels).

State: x, y, z [m], qw, qx, qy, qz (body → world), in the mocap world frame (z up).
``params.source`` picks the stream: ``natnet`` (OptiTrack Motive, the real lab setup)
or ``udp`` (hilstack's pose stream, served by the VelociRoACH emulator). ``read()`` returns
the newest pose without blocking, stamped with its arrival time on the local monotonic
clock (the mocap system's own stamp is in ``extras["source_t_s"]``). The pose is the
driver's one input (:class:`hilstack.drivers.base.Freshness`, deadline ``stale_after_s``): ``ok`` is
False and ``flags["stale_pose"]`` True until a pose arrived and while the newest usable one
is older than the deadline; a pose with NaN/inf is not used (the last finite one is kept)
and the next read reports ``flags["nonfinite_input"]``. A finite pose outside the configured
volume (``volume_min_m`` .. ``volume_max_m``, a box around the arena) or whose quaternion's
norm is not 1 within ``quat_norm_tol`` (a zero quaternion, garbage) is not used either:
counted (``pose_invalid_samples``, why in ``pose_last_invalid``) and flagged
``invalid_input``. ``health().extra["pose_age_s"]`` is the age of the newest usable pose;
none for ``link_timeout_periods`` periods (the mocap system frozen, dead or unreachable)
takes the error path (``LinkError``, UNCONFIGURED).
``write()`` accepts only the empty action.
"""

from __future__ import annotations

import time
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from hilstack.configs.schema import Params, PeriodS, Periods, StaleS, finite
from hilstack.drivers.base import Driver, Flag, Freshness, Health, Inputs, Observation, RobotSpec, Space
from hilstack.drivers.mocap.base import PoseSource

#: a coordinate of the tracked volume [m]: finite and within 100 m of the origin
VolumeCoord = Annotated[float, Field(ge=-100.0, le=100.0)]


class MocapParams(Params):
    source: Literal["natnet", "udp"] = "udp"
    rigid_body_id: int = Field(1, ge=0)
    period_s: PeriodS = Field(0.01, description="how often consumers should read (100 Hz)")
    stale_after_s: StaleS = Field(0.1, description="a pose older than this is not ok")
    link_timeout_periods: Periods = Field(
        100, description="no usable pose for this many periods (the mocap system frozen, dead or "
                         "unreachable, or the body lost): the error path (LinkError, UNCONFIGURED)")
    volume_min_m: tuple[VolumeCoord, VolumeCoord, VolumeCoord] = Field(
        (-10.0, -10.0, -1.0), description="the tracked volume's lower corner [m, world frame]; a pose outside is "
                                          "rejected (invalid_input)")
    volume_max_m: tuple[VolumeCoord, VolumeCoord, VolumeCoord] = Field(
        (10.0, 10.0, 5.0), description="the tracked volume's upper corner [m, world frame]")
    quat_norm_tol: finite(gt=0, le=0.1, source=(
        "≤ 0.1: a unit quaternion off by more is not a rotation a tracker sends (a broken or zero packet)")) = Field(
        0.01, description="a quaternion whose norm differs from 1 by more than this is rejected")
    # udp
    host: str = "127.0.0.1"
    port: int = Field(0, ge=0, le=65535, description="UDP port to listen on (0: ephemeral)")
    # natnet
    server_ip: str = "127.0.0.1"
    local_ip: str = "127.0.0.1"
    multicast: bool = True
    up_axis: Literal["y", "z"] = "y"

    @model_validator(mode="after")
    def _bounds(self) -> MocapParams:
        if not all(lo < hi for lo, hi in zip(self.volume_min_m, self.volume_max_m, strict=True)):
            raise ValueError(f"volume_min_m {list(self.volume_min_m)} must be below volume_max_m "
                             f"{list(self.volume_max_m)} on every axis")
        if not self.link_timeout_periods * self.period_s > self.stale_after_s:
            raise ValueError(f"link_timeout_periods: {self.link_timeout_periods} periods of {self.period_s:g} s must "
                             f"exceed stale_after_s ({self.stale_after_s:g} s)")
        return self


def pose_problem(p: MocapParams, position_m: np.ndarray, quaternion_wxyz: np.ndarray) -> str | None:
    """Why a finite pose cannot be used (None: usable): outside the volume, or a quaternion
    that is not a rotation (its norm off 1 by more than ``quat_norm_tol``)."""
    lo, hi = np.asarray(p.volume_min_m), np.asarray(p.volume_max_m)
    pos = np.asarray(position_m, dtype=np.float64)
    if np.any(pos < lo) or np.any(pos > hi):
        return f"position {pos.tolist()} m outside the volume {lo.tolist()} .. {hi.tolist()}"
    norm = float(np.linalg.norm(quaternion_wxyz))
    if abs(norm - 1.0) > p.quat_norm_tol:
        return f"quaternion {np.asarray(quaternion_wxyz).tolist()} has norm {norm:.3g}, not 1 ± {p.quat_norm_tol:g}"
    return None


def mocap_spec(p: MocapParams) -> RobotSpec:
    chans = [("x", "m"), ("y", "m"), ("z", "m"), ("qw", "1"), ("qx", "1"), ("qy", "1"), ("qz", "1")]
    lo = [-np.inf] * 3 + [-1.0] * 4
    hi = [np.inf] * 3 + [1.0] * 4
    return RobotSpec(
        name="mocap",
        state=Space.build([(n, u, a, b) for (n, u), a, b in zip(chans, lo, hi, strict=True)]),
        action=Space.build([]),
        period_s=p.period_s,
        description=f"rigid body {p.rigid_body_id} from a {p.source} pose stream",
    )


class MocapDriver(Driver):
    params_type = MocapParams

    def __init__(self, params: MocapParams | None = None, backend: str = "real", source: str | None = None):
        super().__init__()
        self.params = params or MocapParams()
        self.backend = backend
        self.source = source
        self.spec = mocap_spec(self.params)
        self.pose_source: PoseSource | None = None
        self._seq = 0
        self.inputs = Inputs(Freshness.fail_after_periods("pose", self.params.stale_after_s, Flag.STALE_POSE,
                                                          self.params.link_timeout_periods, self.params.period_s))
        self._pose = None  # the newest finite sample
        self._seen = None  # the newest sample looked at (finite or not)

    def _on_configure(self) -> None:
        p = self.params
        self.inputs.start(time.monotonic())
        self._pose = self._seen = None
        if p.source == "udp":
            from hilstack.drivers.mocap.udp import UdpPoseClient

            self.pose_source = UdpPoseClient(p.host, p.port, body_id=p.rigid_body_id)
        else:
            from hilstack.drivers.mocap.natnet_client import NatNetPoseSource

            src = NatNetPoseSource(p.server_ip, p.local_ip, p.rigid_body_id, use_multicast=p.multicast,
                                   up_axis=p.up_axis)
            src.connect()
            self.pose_source = src

    def _on_cleanup(self) -> None:
        if self.pose_source is not None:
            self.pose_source.close()
            self.pose_source = None

    @property
    def port(self) -> int | None:
        """The UDP port actually bound (useful with ``port: 0``)."""
        return None if self.pose_source is None else self.pose_source.port

    def _poll(self) -> float:
        """Take the source's newest sample into the freshness record; returns now [s]."""
        s = self.pose_source.latest() if self.pose_source is not None else None
        now = time.monotonic()
        if s is not None and s is not self._seen:
            self._seen = s
            finite = bool(np.all(np.isfinite(s.position_m)) and np.all(np.isfinite(s.quaternion_wxyz)))
            why = pose_problem(self.params, s.position_m, s.quaternion_wxyz) if finite else None
            if why is not None:
                self.inputs["pose"].reject(why)
                return now
            self.inputs["pose"].update(s.received_s if s.received_s is not None else now, finite)
            if finite:
                self._pose = s
        return now

    def _read(self) -> Observation:
        self._seq += 1
        now = self._poll()
        ok, flags = self.inputs.assess(now, report=True)
        s = self._pose
        if s is None:
            return Observation(now, np.array([0, 0, 0, 1, 0, 0, 0], float), self._seq, ok=False, flags=flags)
        state = np.concatenate([s.position_m, s.quaternion_wxyz]).astype(np.float64)
        # t_s on the local monotonic clock (arrival), like every wall-clock backend; the
        # mocap system's own stamp is kept in extras (its clock has an unknown offset)
        t_local = s.received_s if s.received_s is not None else now
        return Observation(t_local, state, self._seq, ok=ok, flags=flags,
                           extras={"age_s": self.inputs["pose"].age_s(now), "frame_id": s.frame_id,
                                   "source_t_s": s.t_s})

    def _refresh_inputs(self) -> None:
        self._poll()

    def _write(self, action: np.ndarray) -> None:
        pass  # a sensor: nothing to command (validation already refused anything non-empty)

    def _stop(self) -> None:
        pass

    def _health(self) -> Health:
        st = self.pose_source.stats() if self.pose_source is not None else {}
        now = self._poll()
        ok, _ = self.inputs.assess(now)
        age = self.inputs["pose"].age_s(now)
        n = max(1, st.get("received", 0) + st.get("dropped", 0))
        return Health(
            ok=ok and self.pose_source is not None,
            link_quality=st.get("received", 0) / n if st else (1.0 if self._pose is not None else 0.0),
            frames_received=st.get("received", 0),
            corrupt_frames=st.get("corrupt", 0),
            dropped_frames=st.get("dropped", 0),
            latency_s=age,
            last_error=self.last_error,
            extra=self.inputs.ages(now),
        )
