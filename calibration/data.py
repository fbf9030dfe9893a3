"""Measured episodes for calibration: loading any lab's logs through a column map.

An *episode* is one contiguous recording of a single-axis drive: time ``t_s``, command ``u``
(e.g. volts or duty), position ``x`` and, when logged, velocity ``v``, battery voltage
``vbat_v`` and a payload indicator ``payload``. Files are CSV or Parquet, one file per
episode or several episodes in one file told apart by an ``episode`` column.

MCAP recordings of a rig (``bus/recording.py``) are read through
:func:`learning.recordings.episodes_from_mcap` with ``normalize=False``, so commands stay in
robot units (e.g. rev/s of the VelociRoACH cranks: the units the sim backend is commanded
in). Such an episode also keeps the full state and action arrays (``states``, ``actions``)
with their channel names, which multi-channel nominal models (``velociroach``) use; the
single-axis view (``u``, ``x``) is picked by channel name through the column map.

Velocity, when not logged, is derived from position with a Savitzky-Golay derivative
(local quadratic fit, window ``sg_window`` samples, see :func:`sg_velocity`). The exact
linear filter that this derivative applies to the true velocity is known
(:func:`sg_velocity_kernel`); the identification applies the same filter to the command
features so that the smoothing does not masquerade as a delay or a lag.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

#: Keys accepted in a column map, and what they mean.
COLUMN_KEYS: dict[str, str] = {
    "t": "time [s] (required)",
    "u": "actuator command, e.g. volts or duty (required)",
    "x": "position, e.g. m or rad (required)",
    "v": "measured velocity, x-units/s (optional; derived from x when absent)",
    "vbat": "battery/supply voltage [V] (optional; enables battery_sag)",
    "m": "payload indicator or payload mass, per sample (optional; enables payload_mass)",
    "episode": "episode id column (optional; default: a column named 'episode' if present)",
}
REQUIRED_KEYS = ("t", "u", "x")


class DataError(ValueError):
    """A user-facing data problem (missing column, NaN, bad map). Message says where."""


@dataclass(frozen=True)
class Episode:
    """One contiguous single-axis recording, uniformly sampled.

    Attributes:
        name: where it came from (file and episode id / segment).
        t_s: time stamps [s], shape (N,).
        u: command, shape (N,) (units of the log, e.g. V).
        x: measured position, shape (N,) (x-units, e.g. m).
        v_meas: measured velocity [x-units/s] or None when not logged.
        vbat_v: battery voltage [V] or None.
        payload: payload indicator/mass per sample or None.
    """

    name: str
    t_s: np.ndarray
    u: np.ndarray
    x: np.ndarray
    v_meas: np.ndarray | None = None
    vbat_v: np.ndarray | None = None
    payload: np.ndarray | None = None
    meta: dict = field(default_factory=dict)
    #: multi-channel recordings (MCAP): states [N, S] in robot units, and actions [N, A] where
    #: ``actions[k]`` is the command held from t_k to t_{k+1} (the last row repeats the one
    #: before: nothing was recorded after the last state).
    states: np.ndarray | None = None
    actions: np.ndarray | None = None
    state_names: tuple[str, ...] = ()
    action_names: tuple[str, ...] = ()

    @property
    def n(self) -> int:
        return int(self.t_s.shape[0])

    @property
    def period_s(self) -> float:
        """Sample period [s]: the median time step (robust to a few jittered stamps)."""
        return float(np.median(np.diff(self.t_s)))

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    def slice(self, start: int, stop: int, name: str) -> Episode:
        def cut(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[start:stop]

        return replace(
            self,
            name=name,
            t_s=self.t_s[start:stop],
            u=self.u[start:stop],
            x=self.x[start:stop],
            v_meas=cut(self.v_meas),
            vbat_v=cut(self.vbat_v),
            payload=cut(self.payload),
            states=cut(self.states),
            actions=cut(self.actions),
            meta={**self.meta, "segment_of": self.name, "segment_start": start},
        )


# ----------------------------------------------------------------------------- column map


def parse_column_map(spec: str | dict | Path | None, required: tuple[str, ...] = REQUIRED_KEYS) -> dict[str, str]:
    """Parse ``t=time,u=volts,x=position[,v=..,vbat=..,m=..,episode=..]`` or a YAML file/dict.

    Returns a dict from our keys (t, u, x, v, vbat, m, episode) to the file's column names.
    Raises DataError for unknown keys or missing ``required`` keys (none for MCAP: channel
    names come from the recorded spec).
    """
    if spec is None:
        mapping: dict[str, str] = {k: k for k in required}
    elif isinstance(spec, dict):
        mapping = {str(k): str(v) for k, v in spec.items()}
    else:
        text = str(spec)
        p = Path(text)
        if text.endswith((".yaml", ".yml")) or (p.suffix in (".yaml", ".yml")):
            if not p.exists():
                raise DataError(f"column map file not found: {p}")
            import yaml

            loaded = yaml.safe_load(p.read_text()) or {}
            if not isinstance(loaded, dict):
                raise DataError(f"column map file {p} must hold a mapping like 't: time'")
            mapping = {str(k): str(v) for k, v in loaded.items()}
        else:
            mapping = {}
            for part in text.split(","):
                part = part.strip()
                if not part:
                    continue
                if "=" not in part:
                    raise DataError(f"bad column map entry {part!r}: expected key=column, e.g. t=time")
                k, v = part.split("=", 1)
                mapping[k.strip()] = v.strip()
    unknown = sorted(set(mapping) - set(COLUMN_KEYS))
    if unknown:
        known = ", ".join(f"{k} ({d})" for k, d in COLUMN_KEYS.items())
        raise DataError(f"unknown column map key(s) {unknown}; known keys: {known}")
    missing = [k for k in required if k not in mapping]
    if missing:
        raise DataError(f"column map lacks required key(s) {missing} (need t=..., u=..., x=...)")
    return mapping


# ----------------------------------------------------------------------------- loading


def _read_table(path: Path):
    import pandas as pd

    if path.suffix.lower() == ".csv":
        return pd.read_csv(path)
    if path.suffix.lower() in (".parquet", ".pq"):
        return pd.read_parquet(path)
    raise DataError(f"unsupported file type {path.suffix!r} for {path} (use .csv, .parquet or .mcap)")


def _column(df, key: str, col: str, path: Path) -> np.ndarray:
    if col not in df.columns:
        raise DataError(
            f"column {col!r} (map key {key!r}) not found in {path}; available columns: {list(df.columns)}"
        )
    arr = np.asarray(df[col].to_numpy(), dtype=float)
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise DataError(
            f"non-finite value (NaN/inf) in {path}, column {col!r}, at data row {int(bad[0])} "
            f"({bad.size} bad rows in total); clean or drop these rows first"
        )
    return arr


def _episodes_from_table(df, mapping: dict[str, str], path: Path) -> list[Episode]:
    ep_col = mapping.get("episode", "episode" if "episode" in df.columns else None)
    if ep_col is not None and ep_col not in df.columns:
        raise DataError(f"episode column {ep_col!r} not found in {path}; available: {list(df.columns)}")
    groups = [(None, df)] if ep_col is None else list(df.groupby(ep_col, sort=True))
    out = []
    for ep_id, g in groups:
        arrays = {k: _column(g, k, mapping[k], path) for k in ("t", "u", "x", "v", "vbat", "m") if k in mapping}
        name = path.name if ep_id is None else f"{path.name}#episode={ep_id}"
        out.append(_make_episode(name, arrays, path))
    return out


def _make_episode(name: str, arrays: dict[str, np.ndarray], path: Path | str) -> Episode:
    t = arrays["t"]
    if t.size < 20:
        raise DataError(f"{name}: only {t.size} samples; need at least 20 per episode")
    dt = np.diff(t)
    if np.any(dt <= 0):
        i = int(np.flatnonzero(dt <= 0)[0])
        raise DataError(f"{path}: time column is not strictly increasing at data row {i + 1} ({name})")
    med = float(np.median(dt))
    if np.max(np.abs(dt - med)) > 0.25 * med:
        # The models are discrete-time with one period; resample a jittery log onto a uniform grid.
        n = int(round((t[-1] - t[0]) / med)) + 1
        tu = t[0] + med * np.arange(n)
        arrays = {k: (tu if k == "t" else np.interp(tu, t, a)) for k, a in arrays.items()}
    return Episode(
        name=name,
        t_s=arrays["t"],
        u=arrays["u"],
        x=arrays["x"],
        v_meas=arrays.get("v"),
        vbat_v=arrays.get("vbat"),
        payload=arrays.get("m"),
        meta={"source": str(path)},
    )


def load_episodes(path: str | Path, column_map: str | dict | Path | None = None,
                  robot: str | None = None, normalize_actions: bool = False) -> list[Episode]:
    """Load episodes from a .csv/.parquet file, a directory of those, or an .mcap recording.

    Args:
        path: file or directory.
        column_map: see :func:`parse_column_map`. For MCAP it is optional: keys name state or
            action channels of the recording (``u=leg_vel_l,x=x``); by default u is the first
            action channel, x the channel named ``x`` (else the first state channel), and vbat
            the state channel ``vbat`` when there is one.
        robot: MCAP only: which robot's states, when the recording holds several.
        normalize_actions: MCAP only: actions in [-1, 1] of the robot's spec (what a learned
            checkpoint trained by ``learning.mbrl`` sees) instead of robot units.

    Raises:
        DataError: missing file/column, NaNs, bad time stamps (message names file, column, row).
    """
    p = Path(path)
    if not p.exists():
        raise DataError(f"data path not found: {p}")
    if p.is_file() and p.suffix.lower() == ".mcap":
        return _load_mcap(p, parse_column_map(column_map, required=()), robot, normalize_actions)
    mapping = parse_column_map(column_map)
    if p.is_dir():
        files = sorted(f for f in p.iterdir() if f.suffix.lower() in (".csv", ".parquet", ".pq"))
        if not files:
            raise DataError(f"no .csv or .parquet files in directory {p}")
    else:
        files = [p]
    episodes: list[Episode] = []
    for f in files:
        episodes.extend(_episodes_from_table(_read_table(f), mapping, f))
    return episodes


def _load_mcap(path: Path, mapping: dict[str, str], robot: str | None = None,
               normalize_actions: bool = False) -> list[Episode]:
    """Episodes of one robot from an MCAP recording (learning.recordings.episodes_from_mcap).

    Actions stay in robot units (``normalize=False``): the nominal models replay them as
    commands, and a sim backend is commanded in robot units, not in [-1, 1]. A learned
    checkpoint sees what it was trained on (``normalize_actions=True``: learning.mbrl's default).
    """
    from learning.recordings import episodes_from_mcap

    try:
        raw = episodes_from_mcap(path, robot=robot, normalize=normalize_actions)
    except ValueError as e:
        raise DataError(str(e)) from e
    if not raw:
        raise DataError(f"{path}: no episode with at least 2 transitions and recorded actions")
    out = []
    for le in raw:
        snames = tuple(le.meta.get("state_names") or [f"s{i}" for i in range(le.states.shape[1])])
        anames = tuple(le.meta.get("action_names") or [f"a{i}" for i in range(le.actions.shape[1])])
        states = np.asarray(le.states, dtype=float)
        acts = np.asarray(le.actions, dtype=float)
        # actions[k] is held from t_k to t_{k+1}; nothing is known after the last state
        actions = np.concatenate([acts, acts[-1:]], axis=0)
        if le.times is None:
            raise DataError(f"{path}: episode {le.name} has no time stamps")
        t = np.asarray(le.times, dtype=float)

        def channel(key: str, default: str | None, snames=snames, anames=anames, states=states,
                    actions=actions) -> np.ndarray | None:
            name = mapping.get(key, default)
            if name is None:
                return None
            if name in snames:
                return states[:, snames.index(name)]
            if name in anames:
                return actions[:, anames.index(name)]
            raise DataError(f"{path}: channel {name!r} (map key {key!r}) not in the recording; "
                            f"state channels {list(snames)}, action channels {list(anames)}")

        bad = np.argwhere(~np.isfinite(states))
        if bad.size:
            i, j = bad[0]
            raise DataError(f"{path}: non-finite value in episode {le.name}, state channel {snames[j]!r}, "
                            f"step {int(i)}")
        dt = np.diff(t)
        if np.any(dt <= 0):
            raise DataError(f"{path}: time stamps not strictly increasing in episode {le.name} "
                            f"at step {int(np.flatnonzero(dt <= 0)[0]) + 1}")
        out.append(Episode(
            name=le.name,
            t_s=t,
            u=channel("u", anames[0]),
            x=channel("x", "x" if "x" in snames else snames[0]),
            v_meas=channel("v", None),
            vbat_v=channel("vbat", "vbat" if "vbat" in snames else None),
            payload=channel("m", None),
            meta={"source": str(path), "robot": le.meta.get("robot"), "episode": le.meta.get("episode"),
                  "actions_normalized": normalize_actions},
            states=states,
            actions=actions,
            state_names=snames,
            action_names=anames,
        ))
    return out


# ----------------------------------------------------------------------------- velocity


def default_sg_window(period_s: float) -> int:
    """Savitzky-Golay window [samples]: about 30 ms of data, at least 7 samples, odd."""
    w = max(7, int(round(0.03 / period_s)))
    return w + 1 if w % 2 == 0 else w


def sg_velocity(x: np.ndarray, period_s: float, window: int) -> np.ndarray:
    """Velocity [x-units/s] from position by a Savitzky-Golay derivative (quadratic, zero phase)."""
    from scipy.signal import savgol_filter

    return savgol_filter(x, window, 2, deriv=1, delta=period_s, mode="interp")


def sg_velocity_kernel(window: int) -> np.ndarray:
    """The zero-phase kernel L such that ``sg_velocity(x) ≈ L * v`` for the true velocity v.

    The SG derivative is an antisymmetric kernel d on x; summation by parts turns it into a
    symmetric smoother w on position increments, and an increment is the trapezoid mean of two
    velocity samples. L (length window+1... trimmed to ``window``) sums to one.
    """
    from scipy.signal import savgol_coeffs

    d = savgol_coeffs(window, 2, deriv=1, delta=1.0, use="dot")  # weights on x[k+j], j=-m..m
    w = -np.cumsum(d)[:-1]  # weights on x[k+i+1]-x[k+i], i=-m..m-1
    kernel = np.convolve(w, [0.5, 0.5])  # weights on v[k+j], j=-m..m
    return kernel / kernel.sum()


def segment_episodes(episodes: list[Episode], min_episodes: int, min_len: int) -> tuple[list[Episode], bool]:
    """Split long recordings into contiguous segments so there are >= ``min_episodes``.

    Returns (episodes, segmented). Segments are contiguous (no shuffling inside), so held-out
    segments still test extrapolation in time; neighbouring segments are correlated, which
    the report mentions.
    """
    if len(episodes) >= min_episodes:
        return episodes, False
    total = sum(e.n for e in episodes)
    n_target = min_episodes
    seg_len = max(min_len, total // n_target)
    out = []
    for e in episodes:
        k = max(1, e.n // seg_len)
        edges = np.linspace(0, e.n, k + 1).astype(int)
        for i in range(k):
            out.append(e.slice(edges[i], edges[i + 1], f"{e.name}[seg{i}]"))
    return out, len(out) > len(episodes)


def summarize(episodes: list[Episode]) -> dict:
    """Data summary for the report (units are those of the log)."""
    u = np.concatenate([e.u for e in episodes])
    x = np.concatenate([e.x for e in episodes])
    return {
        "n_episodes": len(episodes),
        "n_samples": int(sum(e.n for e in episodes)),
        "period_s": float(np.median([e.period_s for e in episodes])),
        "duration_s": float(sum(e.duration_s for e in episodes)),
        "u_range": [float(u.min()), float(u.max())],
        "x_range": [float(x.min()), float(x.max())],
        "has_velocity": all(e.v_meas is not None for e in episodes),
        "has_vbat": all(e.vbat_v is not None for e in episodes),
        "has_payload": all(e.payload is not None for e in episodes),
        "sources": sorted({str(e.meta.get("source", e.name)) for e in episodes}),
    }


__all__ = [
    "COLUMN_KEYS",
    "DataError",
    "Episode",
    "default_sg_window",
    "load_episodes",
    "parse_column_map",
    "segment_episodes",
    "sg_velocity",
    "sg_velocity_kernel",
    "summarize",
]
