"""Episodes and transition datasets for learning dynamics models.

An :class:`Episode` is one uninterrupted rollout: ``T+1`` states and the ``T`` actions
applied between them (``actions[t]`` is applied at ``states[t]`` and leads to
``states[t+1]``). A :class:`TransitionDataset` flattens a list of episodes into
transitions ``(s_t, a_t, Δs_t = s_{t+1} - s_t)`` while remembering which episode each
transition came from, so that train/validation splits are made by whole episode (transitions
of one episode are strongly correlated; splitting inside an episode leaks).

Tabular logs (CSV/Parquet) are read with a column map::

    eps = load_episodes("log.csv", state=["x", "y", ...], action=["u_left", "u_right"],
                        episode="run_id", time="t_s")

Row ``t`` of an episode holds ``s_t`` and the action ``a_t`` applied after observing it;
the action of an episode's last row is unused (there is no next state).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = [
    "Episode",
    "NormStats",
    "TransitionDataset",
    "Transitions",
    "episodes_from_table",
    "load_episodes",
    "split_episodes",
]


@dataclass
class Episode:
    """One rollout.

    Attributes:
        states: ``[T+1, S]`` float array, in the units of ``meta["state_units"]`` if given.
        actions: ``[T, A]`` float array; ``actions[t]`` is applied at ``states[t]``.
        times: ``[T+1]`` timestamps in seconds (``None`` if unknown).
        name: free-form identifier (file name, run id).
        meta: anything else (robot, rig, state/action names and units, ...).
    """

    states: np.ndarray
    actions: np.ndarray
    times: np.ndarray | None = None
    name: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.states = np.asarray(self.states, dtype=np.float32)
        self.actions = np.asarray(self.actions, dtype=np.float32)
        if self.states.ndim != 2 or self.actions.ndim != 2:
            raise ValueError(
                f"episode {self.name!r}: states must be [T+1,S] and actions [T,A], got "
                f"{self.states.shape} and {self.actions.shape}"
            )
        if self.states.shape[0] != self.actions.shape[0] + 1:
            raise ValueError(
                f"episode {self.name!r}: need T+1 states for T actions, got {self.states.shape[0]} "
                f"states and {self.actions.shape[0]} actions"
            )
        if self.times is not None:
            self.times = np.asarray(self.times, dtype=np.float64)
            if self.times.shape != (self.states.shape[0],):
                raise ValueError(
                    f"episode {self.name!r}: times must be [T+1]={self.states.shape[0]}, got {self.times.shape}"
                )

    def __len__(self) -> int:
        """Number of transitions T."""
        return self.actions.shape[0]

    @property
    def state_dim(self) -> int:
        return self.states.shape[1]

    @property
    def action_dim(self) -> int:
        return self.actions.shape[1]

    def transitions(self) -> Transitions:
        """This episode's ``T`` transitions (:class:`Transitions`)."""
        return Transitions.from_episodes([self])


@dataclass(frozen=True)
class Transitions:
    """``N`` transitions ``(s, a, s')``: ``actions[i]`` applied at ``states[i]`` led to
    ``next_states[i]``, one control period later. The one transition record of learning and
    calibration (issue 23): a trainer, a grounding step or a fit takes this, not three
    parallel arrays. ``from_episodes`` stacks episodes; episode boundaries are not kept
    (:class:`TransitionDataset` keeps them, for splits by episode).

    Attributes: ``states [N, S]``, ``actions [N, A]``, ``next_states [N, S]``, float32 (the
    episodes' dtype) or float64 as given; ``state_names`` / ``action_names`` when known.
    """

    states: np.ndarray
    actions: np.ndarray
    next_states: np.ndarray
    state_names: tuple[str, ...] | None = None
    action_names: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        s, a, n = (np.asarray(v) for v in (self.states, self.actions, self.next_states))
        s, a, n = (v if v.dtype in (np.float32, np.float64) else v.astype(np.float64) for v in (s, a, n))
        if s.ndim != 2 or a.ndim != 2 or n.shape != s.shape or len(a) != len(s):
            raise ValueError(f"transitions: states {s.shape}, actions {a.shape} and next_states {n.shape} must be "
                             "[N, S], [N, A] and [N, S]")
        for label, names, dim in (("state_names", self.state_names, s.shape[1]),
                                  ("action_names", self.action_names, a.shape[1])):
            if names is not None and len(names) != dim:
                raise ValueError(f"transitions: {label} has {len(names)} entries, the data {dim} channels")
        object.__setattr__(self, "states", s)
        object.__setattr__(self, "actions", a)
        object.__setattr__(self, "next_states", n)
        for attr in ("state_names", "action_names"):
            if getattr(self, attr) is not None:
                object.__setattr__(self, attr, tuple(getattr(self, attr)))

    @classmethod
    def from_episodes(cls, episodes: Sequence[Episode]) -> Transitions:
        """Every ``(s_t, a_t, s_{t+1})`` of the episodes, stacked in order (names from the first
        episode's ``meta``)."""
        episodes = list(episodes)
        if not episodes:
            raise ValueError("transitions: no episodes")
        meta = episodes[0].meta
        return cls(np.concatenate([e.states[:-1] for e in episodes]),
                   np.concatenate([e.actions for e in episodes]),
                   np.concatenate([e.states[1:] for e in episodes]),
                   _opt_tuple(meta.get("state_names")), _opt_tuple(meta.get("action_names")))

    def __len__(self) -> int:
        return self.states.shape[0]

    @property
    def deltas(self) -> np.ndarray:
        """``s' − s`` ``[N, S]`` (what the dynamics models predict)."""
        return self.next_states - self.states

    def subset(self, idx: np.ndarray | slice) -> Transitions:
        """The transitions at ``idx`` (an index array, a mask or a slice)."""
        return Transitions(self.states[idx], self.actions[idx], self.next_states[idx], self.state_names,
                           self.action_names)

    def finite(self) -> Transitions:
        """These transitions, after checking that no value is NaN or inf (a one-line error)."""
        for label, v in (("states", self.states), ("actions", self.actions), ("next_states", self.next_states)):
            if not np.isfinite(v).all():
                rows = np.flatnonzero(~np.isfinite(v).all(axis=1))
                raise ValueError(f"transitions: NaN or inf in {label} (row {rows[0]} and {len(rows) - 1} more)")
        return self

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(states, actions, next_states)``, for code that takes them apart."""
        return self.states, self.actions, self.next_states


def split_episodes(episodes: Sequence[Episode], val_fraction: float, rng: np.random.Generator | int,
                   assigned: dict[str, bool] | None = None) -> tuple[list[Episode], list[Episode]]:
    """(train, validation): whole episodes, never transitions of one episode on both sides.

    ``round(val_fraction · n)`` of the ``n`` episodes drawn by ``rng.permutation(n)`` are held
    out, at least one and at most ``n − 1`` when ``val_fraction > 0`` and ``n ≥ 2`` (none when
    ``n < 2``). ``rng``: a Generator, or an int seed (``default_rng([seed, 11])``).

    ``assigned`` (episode name → True for validation), updated in place: only episodes whose
    names it does not hold yet are drawn, so an episode keeps its side for good when the list
    grows between iterations (MBRL); names must then be unique.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    if isinstance(rng, (int, np.integer)):
        rng = np.random.default_rng([int(rng), 11])
    if assigned is None:
        new = list(range(len(episodes)))
    else:
        new = [i for i, e in enumerate(episodes) if e.name not in assigned]
        names = [episodes[i].name for i in new]
        if len(set(names)) != len(names):
            raise ValueError("episode names must be unique to keep the validation split fixed")
    n = len(new)
    k = min(max(int(round(val_fraction * n)), 1 if val_fraction > 0 else 0), n - 1) if n >= 2 else 0
    held = set(rng.permutation(n)[:k].tolist())
    side = {i: j in held for j, i in enumerate(new)}
    if assigned is not None:
        assigned.update({episodes[i].name: v for i, v in side.items()})
        side = {i: assigned[e.name] for i, e in enumerate(episodes)}
    return [e for i, e in enumerate(episodes) if not side[i]], [e for i, e in enumerate(episodes) if side[i]]


@dataclass
class NormStats:
    """Per-channel mean and standard deviation (float32 arrays).

    ``input_*`` cover the model input ``[s, a]`` (``S+A`` channels), ``delta_*`` the target
    ``Δs`` and ``state_*`` the raw states (used to normalize multi-step errors). Standard
    deviations below ``1e-6`` (constant channels) are replaced by 1 so normalization never
    divides by zero.
    """

    input_mean: np.ndarray
    input_std: np.ndarray
    delta_mean: np.ndarray
    delta_std: np.ndarray
    state_mean: np.ndarray
    state_std: np.ndarray

    @staticmethod
    def _safe_std(x: np.ndarray) -> np.ndarray:
        std = x.std(axis=0).astype(np.float32)
        return np.where(std < 1e-6, np.float32(1.0), std)


class TransitionDataset:
    """Transitions ``(s_t, a_t, Δs_t)`` flattened from a list of episodes.

    Attributes (numpy, float32 unless stated):
        states ``[N, S]``, actions ``[N, A]``, deltas ``[N, S]``,
        episode_index ``[N]`` (int64, index into :attr:`episodes`).
        state_names / action_names / state_units / action_units: lists of str or ``None``.
    """

    def __init__(
        self,
        episodes: Sequence[Episode],
        state_names: Sequence[str] | None = None,
        action_names: Sequence[str] | None = None,
        state_units: Sequence[str] | None = None,
        action_units: Sequence[str] | None = None,
    ) -> None:
        episodes = list(episodes)
        if not episodes:
            raise ValueError("TransitionDataset needs at least one episode")
        s_dim, a_dim = episodes[0].state_dim, episodes[0].action_dim
        for ep in episodes:
            if (ep.state_dim, ep.action_dim) != (s_dim, a_dim):
                raise ValueError(
                    f"episode {ep.name!r} has dims (S={ep.state_dim}, A={ep.action_dim}), "
                    f"expected (S={s_dim}, A={a_dim})"
                )
        meta0 = episodes[0].meta
        self.episodes = episodes
        self.state_names = _opt_list(state_names if state_names is not None else meta0.get("state_names"))
        self.action_names = _opt_list(action_names if action_names is not None else meta0.get("action_names"))
        self.state_units = _opt_list(state_units if state_units is not None else meta0.get("state_units"))
        self.action_units = _opt_list(action_units if action_units is not None else meta0.get("action_units"))
        for label, names, dim in (
            ("state_names", self.state_names, s_dim),
            ("action_names", self.action_names, a_dim),
            ("state_units", self.state_units, s_dim),
            ("action_units", self.action_units, a_dim),
        ):
            if names is not None and len(names) != dim:
                raise ValueError(f"{label} has {len(names)} entries, data has {dim} channels")
        tr = Transitions.from_episodes(episodes)
        self.states = tr.states.astype(np.float32)
        self.actions = tr.actions.astype(np.float32)
        self.deltas = tr.deltas.astype(np.float32)
        self.episode_index = np.concatenate(
            [np.full(len(ep), i, dtype=np.int64) for i, ep in enumerate(episodes)]
        )

    # -- sizes ---------------------------------------------------------------------------
    def __len__(self) -> int:
        return self.states.shape[0]

    @property
    def state_dim(self) -> int:
        return self.states.shape[1]

    @property
    def action_dim(self) -> int:
        return self.actions.shape[1]

    def __repr__(self) -> str:
        return (
            f"TransitionDataset({len(self.episodes)} episodes, {len(self)} transitions, "
            f"S={self.state_dim}, A={self.action_dim})"
        )

    # -- statistics ----------------------------------------------------------------------
    def stats(self) -> NormStats:
        """Mean/std of inputs ``[s, a]``, of targets ``Δs`` and of states, over all transitions."""
        x = np.concatenate([self.states, self.actions], axis=1)
        return NormStats(
            input_mean=x.mean(axis=0).astype(np.float32),
            input_std=NormStats._safe_std(x),
            delta_mean=self.deltas.mean(axis=0).astype(np.float32),
            delta_std=NormStats._safe_std(self.deltas),
            state_mean=self.states.mean(axis=0).astype(np.float32),
            state_std=NormStats._safe_std(self.states),
        )

    # -- splitting and aggregation -------------------------------------------------------
    def _with_episodes(self, episodes: Sequence[Episode]) -> TransitionDataset:
        return TransitionDataset(
            episodes, self.state_names, self.action_names, self.state_units, self.action_units
        )

    def split(self, val_fraction: float = 0.2, seed: int = 0) -> tuple[TransitionDataset, TransitionDataset]:
        """Split by whole episode into ``(train, val)``.

        At least one episode goes to each side (so at least two episodes are needed); the
        number of validation episodes is ``round(val_fraction * n_episodes)`` clipped to
        ``[1, n-1]``. The choice is a seeded random permutation, so it is reproducible.
        """
        n = len(self.episodes)
        if n < 2:
            raise ValueError("splitting by episode needs at least 2 episodes")
        n_val = int(np.clip(round(val_fraction * n), 1, n - 1))
        perm = np.random.default_rng(seed).permutation(n)
        val_ids, train_ids = sorted(perm[:n_val]), sorted(perm[n_val:])
        return (
            self._with_episodes([self.episodes[i] for i in train_ids]),
            self._with_episodes([self.episodes[i] for i in val_ids]),
        )

    def extend(self, episodes: Iterable[Episode]) -> TransitionDataset:
        """A new dataset with ``episodes`` appended (the MBRL loop's data aggregation)."""
        return self._with_episodes(self.episodes + list(episodes))

    @staticmethod
    def concatenate(datasets: Sequence[TransitionDataset]) -> TransitionDataset:
        """Aggregate several datasets (names/units taken from the first)."""
        if not datasets:
            raise ValueError("nothing to concatenate")
        eps = [ep for d in datasets for ep in d.episodes]
        return datasets[0]._with_episodes(eps)

    def __add__(self, other: TransitionDataset) -> TransitionDataset:
        return TransitionDataset.concatenate([self, other])


def _opt_list(x: Sequence[str] | None) -> list[str] | None:
    return None if x is None else [str(v) for v in x]


def _opt_tuple(x: Sequence[str] | None) -> tuple[str, ...] | None:
    return None if x is None else tuple(str(v) for v in x)


# -- tabular loading ------------------------------------------------------------------------
def episodes_from_table(
    table,
    state: Sequence[str],
    action: Sequence[str],
    episode: str | None = None,
    time: str | None = None,
    state_units: Sequence[str] | None = None,
    action_units: Sequence[str] | None = None,
    name: str = "",
) -> list[Episode]:
    """Cut a pandas DataFrame into episodes with a column map.

    Args:
        table: ``pandas.DataFrame``, one row per time step.
        state: column names forming the state vector, in order.
        action: column names forming the action vector, in order.
        episode: column whose value identifies the episode (rows of one episode keep their
            file order; episodes appear in order of first occurrence). ``None``: one episode.
        time: optional timestamp column in seconds.
        name: prefix for episode names.
    """
    missing = [c for c in [*state, *action, *([episode] if episode else []), *([time] if time else [])]
               if c not in table.columns]
    if missing:
        raise KeyError(f"columns {missing} not in table (has {list(table.columns)})")
    groups = [(name or "episode", table)] if episode is None else list(table.groupby(episode, sort=False))
    out = []
    meta = {
        "state_names": list(state),
        "action_names": list(action),
        "state_units": list(state_units) if state_units is not None else None,
        "action_units": list(action_units) if action_units is not None else None,
    }
    for key, g in groups:
        if len(g) < 2:
            continue  # a single row has no transition
        s = g[list(state)].to_numpy(np.float32)
        a = g[list(action)].to_numpy(np.float32)[:-1]
        t = g[time].to_numpy(np.float64) if time else None
        ep_name = f"{name}:{key}" if (name and episode is not None) else str(key)
        out.append(Episode(s, a, t, name=ep_name, meta=dict(meta)))
    return out


def load_episodes(path: str | Path, **column_map) -> list[Episode]:
    """Load episodes from a file, dispatching on its suffix.

    ``.csv`` and ``.parquet``/``.pq`` take the column map of :func:`episodes_from_table`
    (``state=[...], action=[...], episode=col, time=col``). ``.mcap`` recordings are read
    by ``hilstack.learning.recordings.episodes_from_mcap(path, **kwargs)`` (``robot=``,
    ``normalize=``, ...): a recording names its own channels, so no column map applies.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".mcap":
        from hilstack.learning.recordings import episodes_from_mcap  # noqa: PLC0415 - pulls in the bus

        return episodes_from_mcap(path, **column_map)
    import pandas as pd  # noqa: PLC0415 - keep import cost off the planner path

    if suffix == ".csv":
        table = pd.read_csv(path)
    elif suffix in (".parquet", ".pq"):
        table = pd.read_parquet(path)
    else:
        raise ValueError(f"{path}: unknown episode file type {suffix!r} (expected .csv, .parquet, .mcap)")
    if "state" not in column_map or "action" not in column_map:
        raise TypeError(f"{path}: a column map with state=[...] and action=[...] is required")
    return episodes_from_table(table, name=column_map.pop("name", path.stem), **column_map)
