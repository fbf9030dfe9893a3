"""Two UVC cameras through OpenCV (``cv2.VideoCapture``), paired by timestamp.

Each camera has a grabber thread that reads frames as they come and stamps them on the
local monotonic clock at arrival (UVC frames carry no usable shared clock); it keeps a
short history. :func:`pair_frames` picks the newest left frame and the right frame closest
to it in time, and refuses pairs more than ``max_skew_s`` apart (counted: ``skewed``).
A device that does not open, or a stream that stops, is a one-line :class:`LinkError`.

A device may be an index (``0``), a path (``/dev/video2``), or anything
``cv2.VideoCapture`` opens (a video file, a GStreamer pipeline); files are read at their
own frame rate, which is how the tests run this exact code without cameras.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass

import cv2
import numpy as np

from hilstack.bus.cycle import CycleTimer
from hilstack.drivers.base import LinkError


@dataclass(frozen=True)
class Frame:
    t_s: float  # arrival time, local monotonic clock [s]
    seq: int
    image: np.ndarray  # (H, W, 3) uint8 RGB


def pair_frames(left: list[Frame], right: list[Frame], max_skew_s: float) -> tuple[Frame, Frame] | None:
    """The newest left frame with the right frame nearest in time, if within ``max_skew_s``."""
    if not left or not right:
        return None
    a = left[-1]
    b = min(right, key=lambda f: abs(f.t_s - a.t_s))
    return (a, b) if abs(a.t_s - b.t_s) <= max_skew_s else None


def _device(dev: int | str) -> int | str:
    return int(dev) if isinstance(dev, str) and dev.isdigit() else dev


class Grabber:
    """One camera: opens it, then reads on a thread, keeping the last ``history`` frames."""

    def __init__(self, name: str, device: int | str, width_px: int, height_px: int, fps: float, history: int = 4):
        self.name, self.device = name, device
        self.width_px, self.height_px = width_px, height_px
        cap = cv2.VideoCapture(_device(device))
        if not cap.isOpened():
            cap.release()
            raise LinkError(f"camera {name}: cannot open device {device!r} (not connected, busy, or no permission)")
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, width_px)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height_px)
        cap.set(cv2.CAP_PROP_FPS, fps)
        self._cap = cap
        # a file plays at its own rate (a live camera paces itself)
        self._file_period_s = 1.0 / (cap.get(cv2.CAP_PROP_FPS) or fps) if isinstance(_device(device), str) and \
            not str(device).startswith("/dev/") else 0.0
        self._frames: collections.deque[Frame] = collections.deque(maxlen=history)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.received = 0
        self.bad_frames = 0
        self.error: str | None = None
        self._pace: CycleTimer | None = None
        self._thread = threading.Thread(target=self._run, name=f"uvc-{name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        seq = 0
        # a file is paced by the one scheduler (bus/cycle.py): after a stall the frames it
        # missed are skipped and counted (``missed_frames``), never read in a burst
        pace = CycleTimer(self._file_period_s, sleep=self._stop.wait) if self._file_period_s else None
        self._pace = pace
        if pace is not None:
            pace.start()
        while not self._stop.is_set():
            ok, bgr = self._cap.read()
            now = time.monotonic()
            if not ok:
                self.error = f"camera {self.name}: stream from {self.device!r} ended"
                return
            seq += 1
            if bgr is None or bgr.ndim != 3 or bgr.shape[:2] != (self.height_px, self.width_px):
                self.bad_frames += 1  # a camera that ignored the size request: counted, not used
                continue
            f = Frame(now, seq, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
            with self._lock:
                self._frames.append(f)
                self.received += 1
            if pace is not None:
                pace.wait()

    @property
    def missed_frames(self) -> int:
        """File playback: frame periods skipped after a stall (a live camera paces itself: 0)."""
        return 0 if self._pace is None else self._pace.missed

    def frames(self) -> list[Frame]:
        with self._lock:
            return list(self._frames)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._cap.release()


class StereoUvc:
    """Two grabbers and the pairing rule; counts pairs, repeats and skewed pairs."""

    def __init__(self, left: int | str, right: int | str, width_px: int, height_px: int, fps: float,
                 max_skew_s: float):
        self.max_skew_s = max_skew_s
        self.left = Grabber("left", left, width_px, height_px, fps)
        try:
            self.right = Grabber("right", right, width_px, height_px, fps)
        except LinkError:
            self.left.close()
            raise
        #: left frames that found no right frame within max_skew_s
        self.skewed = 0
        self._refused: int | None = None
        self._last: tuple[int, int] | None = None

    def latest_pair(self) -> tuple[Frame, Frame] | None:
        """A new pair since the last call, or None (nothing new, or too far apart)."""
        for g in (self.left, self.right):
            if g.error:
                raise LinkError(g.error)
        lf, rf = self.left.frames(), self.right.frames()
        p = pair_frames(lf, rf, self.max_skew_s)
        if p is None:
            if lf and rf and lf[-1].seq != self._refused:
                self._refused = lf[-1].seq  # each left frame without a partner counts once
                self.skewed += 1
            return None
        key = (p[0].seq, p[1].seq)
        if key == self._last:
            return None
        self._last = key
        return p

    def close(self) -> None:
        self.left.close()
        self.right.close()
