"""Motion capture pose sources: a small protocol, a UDP pose stream, an OptiTrack NatNet client."""

from hilstack.drivers.mocap.base import PoseSample, PoseSource

__all__ = ["PoseSample", "PoseSource"]
