"""Early stopping on a held-out loss: the one loop every trainer in learning/ uses.

A trainer measures its held-out loss every so often (:func:`due` says when) and passes it
to :meth:`EarlyStopping.update`, which remembers a copy of the weights whenever the loss
improves on the best so far by more than ``min_delta``, and answers True once ``patience``
evaluations in a row brought no improvement. After the loop, :meth:`EarlyStopping.restore`
writes the best evaluation's weights back (in place). ``patience=None`` never stops early
but still keeps and restores the best weights (checkpoint selection).

What is watched is given once, at construction: ``torch.nn.Module`` objects (their
``state_dict``, restored with ``load_state_dict``) and/or mappings of name to tensor (e.g.
``dict(net.named_parameters())`` or GrBAL's ψ), restored in place with ``copy_`` so tensors an
optimizer holds stay the same objects.

Counting: evaluations are numbered from 1; :attr:`best_index` is the number of the best one
(0 before any improvement), so ``history[best_index - 1]`` is its entry when a trainer
appends one history entry per evaluation.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping

import torch

__all__ = ["EarlyStopping", "due"]


def due(step: int, total: int, every: int) -> bool:
    """Whether step ``step`` (0-based) of ``total`` is an evaluation step: every ``every``-th
    step and the last one."""
    return (step + 1) % every == 0 or step == total - 1


class EarlyStopping:
    """Patience, best-state copy and restore for one training run (see the module docstring).

    Args:
        *watched: modules and/or mappings of name → tensor whose values are copied at each
            new best and written back by :meth:`restore`.
        patience: evaluations without a new best after which :meth:`update` returns True
            (None: never).
        min_delta: an evaluation is a new best when ``loss < best - min_delta``.
        keep_initial: copy the weights now, so :meth:`restore` returns to them when no
            evaluation ever improves (e.g. every loss was NaN).
    """

    def __init__(self, *watched: torch.nn.Module | Mapping[str, torch.Tensor], patience: int | None = None,
                 min_delta: float = 0.0, keep_initial: bool = False):
        if not watched:
            raise ValueError("EarlyStopping needs at least one module or tensor mapping to watch")
        if patience is not None and patience < 1:
            raise ValueError(f"patience must be >= 1 or None, got {patience}")
        if not min_delta >= 0.0:
            raise ValueError(f"min_delta must be >= 0, got {min_delta}")
        self.watched = watched
        self.patience = patience
        self.min_delta = float(min_delta)
        self.best = float("inf")
        self.best_index = 0
        self.evaluations = 0
        self._best_state: list | None = self._copy() if keep_initial else None

    def _copy(self) -> list:
        out = []
        for w in self.watched:
            if isinstance(w, torch.nn.Module):
                out.append(copy.deepcopy(w.state_dict()))
            else:
                out.append({k: v.detach().clone() for k, v in w.items()})
        return out

    @property
    def stale(self) -> int:
        """Evaluations since the best one."""
        return self.evaluations - self.best_index

    def update(self, loss: float) -> bool:
        """Record one evaluation's held-out loss; True when training should stop now."""
        self.evaluations += 1
        if loss < self.best - self.min_delta:
            self.best, self.best_index = float(loss), self.evaluations
            self._best_state = self._copy()
            return False
        return self.patience is not None and self.stale >= self.patience

    def restore(self) -> bool:
        """Write the best weights back into the watched objects; False when there is nothing
        to restore (no evaluation improved and ``keep_initial`` was not set)."""
        if self._best_state is None:
            return False
        with torch.no_grad():
            for w, state in zip(self.watched, self._best_state, strict=True):
                if isinstance(w, torch.nn.Module):
                    w.load_state_dict(state)
                else:
                    for k, v in w.items():
                        v.copy_(state[k])
        return True
