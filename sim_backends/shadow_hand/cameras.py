"""The tracker's stereo pair in the MuJoCo hand scene, and a checkerboard for calibrating it.

Geometry (thesis: 280×180 RGB, 12 cm baseline): two parallel cameras fixed to the hand's
mount (the *hand frame*, body ``robot0:hand mount``), ``distance_m`` from the palm centre
along the palm normal, ``baseline_m`` apart along the mount's x, looking at the palm.
Their poses in the hand frame are exact by construction, which is the truth calibration
is checked against (:func:`truth_calibration`).

Rendering goes through :class:`hilstack.sim_backends.rendering.OffscreenRenderer` (shared with the
WidowX cameras; shadows and reflections off).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np
from pydantic import Field

from hilstack.configs.schema import ConfigError, Params, parse_model
from hilstack.drivers.base import Health, Observation
from hilstack.drivers.camera.config import CameraParams, camera_spec
from hilstack.drivers.camera.pipeline import CameraPipeline, FramePair
from hilstack.perception.geometry import (
    StereoCalibration,
    apply,
    cv_from_mujoco_cam,
    homogeneous,
    intrinsics_from_fovy,
    invert,
)
from hilstack.sim_backends.base import LockstepSim
from hilstack.sim_backends.rendering import OffscreenRenderer

LEFT_CAMERA = "stereo_left"
RIGHT_CAMERA = "stereo_right"
#: the hand frame: the hand's mount (fixed to the rig; the wrist moves the palm, not this)
HAND_FRAME_BODY = "robot0:hand mount"
BOARD_BODY = "calib_board"
#: the palm centre at the hold pose, in the hand frame [m] (palm normal = the mount's −y)
PALM_CENTER_IN_HAND_M = (0.0, -0.02, 0.34)


@dataclass(frozen=True)
class StereoMount:
    """Where the stereo pair sits, in the hand frame; units in the names."""

    baseline_m: float = 0.12
    distance_m: float = 0.25
    fovy_deg: float = 45.0
    width_px: int = 280
    height_px: int = 180

    def camera_pos_in_hand(self, right: bool) -> np.ndarray:
        c = np.asarray(PALM_CENTER_IN_HAND_M, dtype=np.float64)
        # image right = mount −x, so the left camera sits at +x
        return c + np.array([(-1.0 if right else 1.0) * self.baseline_m / 2, -self.distance_m, 0.0])

    #: MuJoCo camera axes in the hand frame: x (image right) = −x, y (image up) = −z; looks along +y
    XYAXES = (-1.0, 0.0, 0.0, 0.0, 0.0, -1.0)


@dataclass(frozen=True)
class Checkerboard:
    """A flat board of ``squares`` (columns, rows) black/white squares of ``square_m``;
    OpenCV finds its ``(columns − 1) × (rows − 1)`` inner corners."""

    squares: tuple[int, int] = (8, 5)
    square_m: float = 0.01
    border_m: float = 0.008

    @property
    def inner(self) -> tuple[int, int]:
        return self.squares[0] - 1, self.squares[1] - 1


def add_stereo_cameras(spec: mujoco.MjSpec, mount: StereoMount = StereoMount()) -> None:
    body = spec.body(HAND_FRAME_BODY)
    for name, right in ((LEFT_CAMERA, False), (RIGHT_CAMERA, True)):
        cam = body.add_camera(name=name, pos=mount.camera_pos_in_hand(right), fovy=mount.fovy_deg)
        cam.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
        cam.alt.xyaxes = np.array(StereoMount.XYAXES)
    spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, mount.width_px)
    spec.visual.global_.offheight = max(spec.visual.global_.offheight, mount.height_px)


def add_board(spec: mujoco.MjSpec, board: Checkerboard = Checkerboard()) -> None:
    """A mocap body carrying the board (visual only: no contacts). Its frame is OpenCV's
    board convention: origin at the board centre on the printed face, x along a row, y
    down the columns, z into the board (the printed face looks along −z). Squares are
    geoms (exact geometry, no texture mapping to get wrong); the (0, 0) square is black."""
    b = spec.worldbody.add_body(name=BOARD_BODY, mocap=True, pos=[0, 0, -1])
    cols, rows = board.squares
    s, t, ink = board.square_m, 0.002, 0.0001
    vis = {"contype": 0, "conaffinity": 0}
    b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[cols * s / 2 + board.border_m, rows * s / 2 + board.border_m, t],
               pos=[0, 0, t], rgba=[0.95, 0.95, 0.95, 1], **vis)
    for i in range(cols):
        for j in range(rows):
            if (i + j) % 2 == 0:
                b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[s / 2, s / 2, ink],
                           pos=[(i - cols / 2 + 0.5) * s, (j - rows / 2 + 0.5) * s, -ink],
                           rgba=[0.02, 0.02, 0.02, 1], **vis)


def scene_edit(mount: StereoMount = StereoMount(), board: Checkerboard | None = None):
    """The ``edit`` for :func:`hilstack.sim_backends.shadow_hand.model.build_scene`: cameras (+ board)."""

    def edit(spec: mujoco.MjSpec) -> None:
        add_stereo_cameras(spec, mount)
        if board is not None:
            add_board(spec, board)

    return edit


def world_from_hand(model: mujoco.MjModel, data: mujoco.MjData) -> np.ndarray:
    b = model.body(HAND_FRAME_BODY).id
    return homogeneous(data.xmat[b].reshape(3, 3), data.xpos[b])


def truth_calibration(model: mujoco.MjModel, data: mujoco.MjData, mount: StereoMount = StereoMount(),
                      camera_id: str = "stereo0") -> StereoCalibration:
    """The exact calibration of the rendered pair (after ``mj_forward``)."""
    wl = cv_from_mujoco_cam(data.cam_xpos[model.camera(LEFT_CAMERA).id], data.cam_xmat[model.camera(LEFT_CAMERA).id])
    wr = cv_from_mujoco_cam(data.cam_xpos[model.camera(RIGHT_CAMERA).id],
                            data.cam_xmat[model.camera(RIGHT_CAMERA).id])
    right_from_left = invert(wr) @ wl
    K = intrinsics_from_fovy(mount.fovy_deg, mount.width_px, mount.height_px)
    return StereoCalibration(camera_id=camera_id, width_px=mount.width_px, height_px=mount.height_px,
                             K1=K, dist1=np.zeros(5), K2=K, dist2=np.zeros(5),
                             R=right_from_left[:3, :3], T=right_from_left[:3, 3],
                             hand_from_left=invert(world_from_hand(model, data)) @ wl,
                             report={"source": "MuJoCo camera model (truth)"})


class StereoRenderer:
    """Renders the (left, right) pair from a model built with :func:`scene_edit`."""

    def __init__(self, model: mujoco.MjModel, mount: StereoMount = StereoMount()):
        self.mount = mount
        self._r = OffscreenRenderer(model, mount.height_px, mount.width_px)

    def render(self, data: mujoco.MjData) -> tuple[np.ndarray, np.ndarray]:
        """Two (height, width, 3) uint8 RGB images."""
        return self._r.render(data, LEFT_CAMERA), self._r.render(data, RIGHT_CAMERA)

    def close(self) -> None:
        self._r.close()


class HandCameraScene:
    """The hand scene with the stereo pair (and optionally the board), posed directly
    (no physics): rendered training data, calibration views, scripted Baoding motion.

    Positions are in the hand frame [m] unless a name says world."""

    def __init__(self, palm_tilt_rad: float = 0.15, mount: StereoMount = StereoMount(),
                 board: Checkerboard | None = None):
        from hilstack.sim_backends.shadow_hand.backend import hold_pose_q
        from hilstack.sim_backends.shadow_hand.model import build_scene

        self.mount, self.board = mount, board
        self.hand = build_scene(palm_tilt_rad, edit=scene_edit(mount, board))
        self.model = self.hand.model
        self.data = mujoco.MjData(self.model)
        self.hold_q = hold_pose_q()
        self.set_hand(self.hold_q)
        self.renderer = StereoRenderer(self.model, mount)
        self.world_from_hand = world_from_hand(self.model, self.data)

    def set_hand(self, q_rad: np.ndarray) -> None:
        h = self.hand
        self.data.qpos[h.qpos_adr] = np.clip(q_rad, h.joint_low, h.joint_high)
        mujoco.mj_forward(self.model, self.data)

    def set_balls(self, balls_in_hand_m: np.ndarray) -> None:
        w = self.world_from_hand
        pts = np.asarray(balls_in_hand_m, dtype=np.float64).reshape(2, 3) @ w[:3, :3].T + w[:3, 3]
        for adr, p in zip(self.hand.ball_qpos_adr, pts, strict=True):
            self.data.qpos[adr:adr + 3] = p
            self.data.qpos[adr + 3:adr + 7] = (1.0, 0.0, 0.0, 0.0)
        mujoco.mj_forward(self.model, self.data)

    def set_board(self, hand_from_board: np.ndarray) -> None:
        """Put the board (4×4 pose in the hand frame)."""
        wb = self.world_from_hand @ hand_from_board
        mid = self.model.body(BOARD_BODY).mocapid[0]
        self.data.mocap_pos[mid] = wb[:3, 3]
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, wb[:3, :3].ravel())
        self.data.mocap_quat[mid] = q
        mujoco.mj_forward(self.model, self.data)

    def render(self) -> tuple[np.ndarray, np.ndarray]:
        return self.renderer.render(self.data)

    def truth(self, camera_id: str = "stereo0") -> StereoCalibration:
        return truth_calibration(self.model, self.data, self.mount, camera_id)

    def close(self) -> None:
        self.renderer.close()


def baoding_motion(t_s: np.ndarray, radius_m: float = 0.025, rate_rad_s: float = np.pi / 5,
                   bob_m: float = 0.004) -> np.ndarray:
    """Ball centres (len(t), 2, 3) in the hand frame for a Baoding turn: the task's targets
    (:class:`hilstack.tasks.baoding.BaodingTask` about the palm centre, palm normal
    = the hand frame's −y) bobbing ``bob_m`` along the normal (rolling over the fingers)."""
    from hilstack.tasks.baoding import BaodingTask

    task = BaodingTask(center_m=np.asarray(PALM_CENTER_IN_HAND_M), axis=np.array([0.0, -1.0, 0.0]),
                       radius_m=radius_m, rate_rad_s=rate_rad_s)
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    bob = np.array([0.0, -bob_m, 0.0]) * np.sin(3 * rate_rad_s * t)[:, None, None]  # along the normal
    return np.stack([task.targets(ti) for ti in t]) + bob


class CameraSimParams(Params):
    """``params.sim`` of the camera's sim backend (units in names)."""

    palm_tilt_rad: float = Field(0.15, ge=-0.5, le=0.5, description="as the hand sim's mount tilt")
    motion_radius_m: float = Field(0.025, gt=0, description="scripted Baoding turn: circle radius")
    motion_rate_rad_s: float = Field(float(np.pi / 5), description="scripted Baoding turn: rate (+: ccw)")
    finger_wiggle_rad: float = Field(0.0, ge=0, le=1.0, description="finger motion about the hold pose (occlusions)")


class StereoCameraSim(LockstepSim):
    """The camera robot's sim backend: the stereo pair watching a scripted Baoding turn
    (:func:`baoding_motion`) over the hand at its hold pose, rendered each period.

    The calibration is the exact one of the rendered pair unless ``params.calibration``
    names a file (e.g. one ``hil calibrate camera`` produced from rendered boards).
    ``extras["balls_true_m"]`` holds the truth (hand frame) for evaluation."""
    params_type = CameraParams

    def __init__(self, params: CameraParams | None = None, source: str | None = None):
        super().__init__()
        self.params = p = params or CameraParams()
        self.source = source
        try:
            self.sim = parse_model(CameraSimParams, dict(p.sim), source)
        except ConfigError as e:
            raise ConfigError(source, [(f"params.sim.{f}", m) for f, m in e.problems]) from None
        self.spec = camera_spec(p)
        self.scene: HandCameraScene | None = None
        self.pipeline: CameraPipeline | None = None
        self._t_s = 0.0
        self._seq = 0
        self._rendered_t: float | None = None
        self._truth = np.zeros((2, 3))

    @property
    def sim_time_s(self) -> float:
        return self._t_s

    def _on_configure(self) -> None:
        p = self.params
        mount = StereoMount(width_px=p.width_px, height_px=p.height_px)
        self.scene = HandCameraScene(self.sim.palm_tilt_rad, mount)
        try:
            cal = self.scene.truth() if p.calibration is None else StereoCalibration.load(p.calibration, p.camera_id)
            self.pipeline = CameraPipeline(p, cal)
        except ValueError as e:
            raise ConfigError(self.source, [("params.calibration", str(e))]) from None
        self.reset()

    def _on_cleanup(self) -> None:
        if self.scene is not None:
            self.scene.close()
            self.scene = None

    def reset(self) -> None:
        self._t_s = 0.0
        self._rendered_t = None
        self.pipeline.start(0.0)

    def _advance(self, duration_s: float) -> None:
        self._t_s += duration_s

    def pose_scene(self, t_s: float) -> np.ndarray:
        """Put balls and fingers where the script has them at ``t_s``; returns the truth (2, 3)."""
        s = self.sim
        balls = baoding_motion(np.array([t_s]), s.motion_radius_m, s.motion_rate_rad_s)[0]
        q = self.scene.hold_q.copy()
        if s.finger_wiggle_rad:
            q[2:] += s.finger_wiggle_rad * np.sin(2.0 * t_s + np.arange(q.size - 2))
        self.scene.set_hand(q)
        self.scene.set_balls(balls)
        return balls

    def _read(self) -> Observation:
        self._seq += 1
        if self._rendered_t != self._t_s:  # one render per period, however often read
            self._truth = self.pose_scene(self._t_s)
            left, right = self.scene.render()
            self.pipeline.feed(FramePair(left, right, self._t_s, self._t_s))
            self._rendered_t = self._t_s
        obs = self.pipeline.observation(self._t_s, self._seq)
        obs.extras["balls_true_m"] = self._truth.copy()
        return obs

    def _write(self, action: np.ndarray) -> None:
        pass

    def _stop(self) -> None:
        pass

    def _health(self) -> Health:
        return Health(ok=self.scene is not None, last_error=self.last_error,
                      extra={"sim_time_s": self._t_s, "backend": "sim",
                             **({} if self.pipeline is None else self.pipeline.ages(self._t_s))})


class TrackerOptions(Params):
    """``params.sim.tracker`` of the hand sim: feed ``extras["balls_m"]`` from the camera
    tracker (rendered stereo pair) instead of the simulator's truth."""

    kind: Literal["color", "learned"] = "learned"
    weights: str | None = Field(None, description="learned: weights file (default: the shipped ones)")
    min_confidence: float = Field(0.5, ge=0, le=1)
    stale_after_s: float = Field(0.15, gt=0, description="balls not confidently seen for longer are stale")
    encoding: Literal["jpeg", "png"] = "jpeg"


class HandTracker:
    """The stereo pair and a tracker inside the hand sim (cameras added to its scene with
    :func:`scene_edit`): each :meth:`observe` renders the pair at the sim's state and
    tracks it. Ball positions come back in the world frame, as the hand reports them."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, opts: TrackerOptions, period_s: float):
        self.opts = opts
        self.renderer = StereoRenderer(model)
        # no error deadline here: the hand sim owns its balls' freshness (a lost ball is not a dead
        # device), and nothing asks this pipeline's inputs whether they expired
        cp = CameraParams(tracker=opts.kind, weights=opts.weights, min_confidence=opts.min_confidence,
                          stale_after_s=opts.stale_after_s, encoding=opts.encoding, period_s=period_s)
        self.pipeline = CameraPipeline(cp, truth_calibration(model, data))
        self.world_from_hand = world_from_hand(model, data)
        self._rendered_t = None

    def start(self, t_s: float) -> None:
        self.pipeline.start(t_s)
        self._rendered_t = None

    def observe(self, data: mujoco.MjData, t_s: float, seq: int) -> Observation:
        """The camera's observation at ``t_s`` (state: balls in the hand frame + confidence);
        one render per sim instant, however often the hand is read."""
        if self._rendered_t != t_s:
            left, right = self.renderer.render(data)
            self.pipeline.feed(FramePair(left, right, t_s, t_s))
            self._rendered_t = t_s
        return self.pipeline.observation(t_s, seq)

    def balls_world(self, cam_obs: Observation) -> np.ndarray:
        return apply(self.world_from_hand, cam_obs.state[:6].reshape(2, 3))

    def close(self) -> None:
        self.renderer.close()
