"""Per-task replay of whole episodes (MELD keeps one buffer per training task, Table 7.1).

An episode of ``T`` steps holds ``T+1`` images and rewards (``r_t`` observed with ``x_t``, the
reward of the state the image shows) and ``T`` actions (``a_t`` taken after ``x_t``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class ImageEpisode:
    images: np.ndarray    #: [T+1, H, W, 3] uint8
    rewards: np.ndarray   #: [T+1] float32
    actions: np.ndarray   #: [T, A] float32, normalized to [−1, 1]
    task: int
    success: bool = False

    def __post_init__(self) -> None:
        t = len(self.actions)
        if len(self.images) != t + 1 or len(self.rewards) != t + 1:
            raise ValueError(f"episode of {t} actions needs {t + 1} images and rewards, "
                             f"got {len(self.images)} and {len(self.rewards)}")


class TaskReplay:
    """Episodes per task; sequences sampled with tasks drawn uniformly."""

    def __init__(self, capacity_per_task: int = 10_000):
        self.capacity = capacity_per_task
        self.episodes: dict[int, list[ImageEpisode]] = {}

    def add(self, ep: ImageEpisode) -> None:
        buf = self.episodes.setdefault(ep.task, [])
        buf.append(ep)
        if len(buf) > self.capacity:
            buf.pop(0)

    @property
    def n_samples(self) -> int:
        return sum(len(e.actions) for buf in self.episodes.values() for e in buf)

    def sample(self, rng: np.random.Generator, batch: int, length: int, pad_front: int = 0) -> dict[str, np.ndarray]:
        """``batch`` subsequences of ``length`` images (and ``length − 1`` actions). With
        ``pad_front = k``, each episode is seen as if its first image (and reward) were repeated
        ``k`` more times with zero actions before it: windows of a history policy at the start."""
        tasks = [t for t, b in self.episodes.items() if b]
        if not tasks:
            raise ValueError("replay is empty")
        imgs, rews, acts, task_ids = [], [], [], []
        for _ in range(batch):
            task = tasks[rng.integers(len(tasks))]
            ep = self.episodes[task][rng.integers(len(self.episodes[task]))]
            im, rw, ac = ep.images, ep.rewards, ep.actions
            if pad_front:
                im = np.concatenate([np.repeat(im[:1], pad_front, 0), im])
                rw = np.concatenate([np.repeat(rw[:1], pad_front), rw])
                ac = np.concatenate([np.zeros((pad_front, ac.shape[1]), ac.dtype), ac])
            if len(im) < length:
                raise ValueError(f"episodes of {len(im)} images are shorter than sequences of {length}")
            s = rng.integers(len(im) - length + 1)
            imgs.append(im[s:s + length]), rews.append(rw[s:s + length]), acts.append(ac[s:s + length - 1])
            task_ids.append(task)
        return {"images": np.stack(imgs), "rewards": np.stack(rews).astype(np.float32),
                "actions": np.stack(acts).astype(np.float32), "tasks": np.array(task_ids)}
