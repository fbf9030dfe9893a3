"""Measured episodes for calibration: loading any lab's logs through a column map.

An *episode* is one contiguous recording of a single-axis drive: time ``t_s``, command ``u``
(e.g. volts or duty), position ``x`` and, when logged, velocity ``v``, battery voltage
``vbat_v`` and a payload indicator ``payload``. Files are CSV or Parquet, one file per
episode or several episodes in one file told apart by an ``episode`` column.

MCAP recordings of a rig (``bus/recording.py``) are read through
:func:`hilstack.learning.recordings.episodes_from_mcap` with ``normalize=False``, so commands stay in
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

import itertools
import math
from collections.abc import Callable
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
class Recording:
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

    def transitions(self, state_names: tuple[str, ...] | list[str] | None = None,
                    action_names: tuple[str, ...] | list[str] | None = None):
        """The multi-channel part as a :class:`hilstack.learning.datasets.Episode`, the one
        episode type of learning: ``N`` states and the ``N − 1`` actions between them
        (``actions[k]``, held from t_k to t_{k+1}, leads from ``states[k]`` to ``states[k+1]``;
        the repeated last row is dropped). ``state_names``/``action_names``: the channels to
        keep, in that order (default all)."""
        from hilstack.learning.datasets import Episode as Transitions

        if self.states is None or self.actions is None:
            raise DataError(f"{self.name}: no state/action channels (an .mcap recording or a mapped table has them)")
        si = [self.state_names.index(n) for n in state_names] if state_names is not None else slice(None)
        ai = [self.action_names.index(n) for n in action_names] if action_names is not None else slice(None)
        return Transitions(self.states[:, si], self.actions[:-1, ai], times=self.t_s, name=self.name,
                           meta={**self.meta, "state_names": list(state_names or self.state_names),
                                 "action_names": list(action_names or self.action_names)})

    @property
    def period_s(self) -> float:
        """Sample period [s]: the median time step (robust to a few jittered stamps)."""
        return float(np.median(np.diff(self.t_s)))

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    def slice(self, start: int, stop: int, name: str) -> Recording:
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
                if k.strip() in mapping:
                    raise DataError(f"column map gives key {k.strip()!r} twice ({mapping[k.strip()]!r} and "
                                    f"{v.strip()!r}); give each key once")
                mapping[k.strip()] = v.strip()
    unknown = sorted(set(mapping) - set(COLUMN_KEYS))
    if unknown:
        known = ", ".join(f"{k} ({d})" for k, d in COLUMN_KEYS.items())
        raise DataError(f"unknown column map key(s) {unknown}; known keys: {known}")
    missing = [k for k in required if k not in mapping]
    if missing:
        raise DataError(f"column map lacks required key(s) {missing} (need t=..., u=..., x=...)")
    # One column feeding two keys (e.g. t=time,u=time) is always a typo: the fit would be degenerate.
    seen: dict[str, str] = {}
    for k, col in mapping.items():
        if col in seen:
            raise DataError(f"column map names column {col!r} twice (keys {seen[col]!r} and {k!r}); "
                            "each key needs its own column")
        seen[col] = k
    return mapping


# ----------------------------------------------------------------------------- loading


def _read_table(path: Path):
    """The file as a DataFrame; an unreadable file (empty, binary, not Parquet) is a one-line DataError."""
    import pandas as pd

    kind = path.suffix.lower()
    if kind not in (".csv", ".parquet", ".pq"):
        raise DataError(f"unsupported file type {path.suffix!r} for {path} (use .csv, .parquet or .mcap)")
    if path.stat().st_size == 0:
        raise DataError(f"{path} is empty (0 bytes)")
    try:
        df = pd.read_csv(path) if kind == ".csv" else pd.read_parquet(path)
    except UnicodeDecodeError as e:
        raise DataError(f"{path} is not a text CSV file (byte {e.start} is not UTF-8 text); is it binary?") from e
    except (pd.errors.EmptyDataError, pd.errors.ParserError) as e:
        raise DataError(f"{path} is not a readable CSV table: {str(e).splitlines()[0]}") from e
    except (OSError, ValueError) as e:  # pyarrow.ArrowInvalid is a ValueError
        raise DataError(f"{path} is not a readable {'CSV' if kind == '.csv' else 'Parquet'} file: "
                        f"{str(e).splitlines()[0]}") from e
    if len(df) == 0:
        raise DataError(f"{path} has a header but no data rows (columns {list(df.columns)})")
    return df


def _column(df, key: str, col: str, path: Path) -> np.ndarray:
    """One mapped column as floats; NaN/inf are kept (the caller splits around them).

    A cell that is not a number (text such as ``"1,5"`` or ``"n/a "``) is a DataError naming the
    file, the data row and the column: it is a format problem the user must fix, not missing data.
    """
    import pandas as pd

    if col not in df.columns:
        raise DataError(
            f"column {col!r} (map key {key!r}) not found in {path}; available columns: {list(df.columns)}"
        )
    raw = df[col]
    num = pd.to_numeric(raw, errors="coerce")
    text = num.isna().to_numpy() & raw.notna().to_numpy()
    if text.any():
        i = int(np.flatnonzero(text)[0])
        row = df.index[i]
        where = f"data row {row} (line {row + 2} of the file)" if path.suffix.lower() == ".csv" else f"data row {row}"
        raise DataError(f"non-numeric value {raw.iloc[i]!r} in {path}, column {col!r}, {where} "
                        f"({int(text.sum())} such cell(s) in this column); fix the file (decimal point, no units "
                        "or text in numeric columns)")
    return np.asarray(num.to_numpy(), dtype=float)


#: Fewest samples an episode (or a piece of one between NaN rows) must have to be used.
MIN_SAMPLES = 20
#: Largest magnitude a logged value may have; beyond it (e.g. 1e300, a corrupt cell) the row is treated
#: like a NaN row: dropped, and the episode split there. Squares and sums of such values overflow.
MAX_ABS_VALUE = 1e12
#: A time step longer than this many median periods is a gap (logging paused, clock jumped): the
#: recording is split there into separate episodes, never bridged or resampled across.
GAP_PERIODS = 5.0


def _episodes_from_table(df, mapping: dict[str, str], path: Path, warn: Callable[[str], None]) -> list[Recording]:
    ep_col = mapping.get("episode", "episode" if "episode" in df.columns else None)
    if ep_col is not None and ep_col not in df.columns:
        raise DataError(f"episode column {ep_col!r} not found in {path}; available: {list(df.columns)}")
    groups = [(None, df)] if ep_col is None else list(df.groupby(ep_col, sort=True))
    out = []
    for ep_id, g in groups:
        keys = [k for k in ("t", "u", "x", "v", "vbat", "m") if k in mapping]
        arrays = {k: _column(g, k, mapping[k], path) for k in keys}
        name = path.name if ep_id is None else f"{path.name}#episode={ep_id}"
        bad = np.zeros(len(g), bool)
        for k in keys:
            with np.errstate(invalid="ignore"):
                bad |= ~(np.abs(arrays[k]) <= MAX_ABS_VALUE)  # NaN, inf, and values beyond the bound
        if bad.any():
            # Drop the bad rows and keep every clean stretch as its own episode: no data is lost and
            # no stretch is bridged across a gap the model would have to integrate through.
            first = int(np.flatnonzero(bad)[0])
            key = next(k for k in keys if not abs(arrays[k][first]) <= MAX_ABS_VALUE)
            col = mapping[key]
            d = np.diff(np.concatenate([[0], (~bad).astype(int), [0]]))
            pieces = list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist(), strict=True))
            warn(f"{path}: {int(bad.sum())} row(s) with NaN/inf or |value| > {MAX_ABS_VALUE:g} dropped in {name} "
                 f"(first: data row {g.index[first]}, column {col!r}, value {arrays[key][first]:g}); the rest is "
                 f"kept as {len(pieces)} contiguous piece(s)")
            for a, b in pieces:
                out.extend(_make_episode(f"{name}[rows {g.index[a]}-{g.index[b - 1]}]",
                                         {k: v[a:b] for k, v in arrays.items()}, path, warn))
            continue
        out.extend(_make_episode(name, arrays, path, warn))
    return out


def _make_episode(name: str, arrays: dict[str, np.ndarray], path: Path | str,
                  warn: Callable[[str], None]) -> list[Recording]:
    """The episode(s) of one clean stretch of rows: split at time gaps, resampled when jittery.

    A step longer than :data:`GAP_PERIODS` median periods splits the stretch into separate
    episodes (with a warning): bridging it would make the models integrate through time that was
    not recorded, and resampling across it would allocate memory for the gap (a 1e6 s clock jump
    at 100 Hz is 1e8 samples). After the split every step is at most GAP_PERIODS periods, so a
    resampled episode has at most GAP_PERIODS times as many samples as it had rows.
    """
    t = arrays["t"]
    if t.size < MIN_SAMPLES:
        warn(f"{name}: skipped, only {t.size} samples (need at least {MIN_SAMPLES} per episode)")
        return []
    dt = np.diff(t)
    if np.any(dt <= 0):
        i = int(np.flatnonzero(dt <= 0)[0])
        raise DataError(f"{path}: time column is not strictly increasing at data row {i + 1} ({name})")
    med = float(np.median(dt))
    gaps = np.flatnonzero(dt > GAP_PERIODS * med)
    if gaps.size:
        cuts = [0, *(gaps + 1).tolist(), t.size]
        warn(f"{name}: {gaps.size} time gap(s) longer than {GAP_PERIODS:g} median periods ({med:.4g} s) split it "
             f"into {len(cuts) - 1} episodes (largest gap {float(dt.max()):.4g} s after data row {int(gaps[0])})")
        out: list[Recording] = []
        for j, (a, b) in enumerate(itertools.pairwise(cuts)):
            out.extend(_make_episode(f"{name}[part{j}]", {k: v[a:b] for k, v in arrays.items()}, path, warn))
        return out
    if np.max(np.abs(dt - med)) > 0.25 * med:
        # The models are discrete-time with one period; resample a jittery log onto a uniform grid.
        n = int(round((t[-1] - t[0]) / med)) + 1
        tu = t[0] + med * np.arange(n)
        arrays = {k: (tu if k == "t" else np.interp(tu, t, a)) for k, a in arrays.items()}
    if float(np.ptp(arrays["x"])) <= 1e-12 * max(1.0, float(np.max(np.abs(arrays["x"])))):
        warn(f"{name}: skipped, position is constant ({float(arrays['x'][0]):.6g}) over all {t.size} samples")
        return []
    return [Recording(
        name=name,
        t_s=arrays["t"],
        u=arrays["u"],
        x=arrays["x"],
        v_meas=arrays.get("v"),
        vbat_v=arrays.get("vbat"),
        payload=arrays.get("m"),
        meta={"source": str(path)},
    )]


def _warn_default(msg: str) -> None:
    import warnings

    warnings.warn(msg, stacklevel=3)


def load_episodes(path: str | Path, column_map: str | dict | Path | None = None,
                  robot: str | None = None, normalize_actions: bool = False,
                  warn: Callable[[str], None] | None = None) -> list[Recording]:
    """Load episodes from a .csv/.parquet file, a directory of those, or an .mcap recording.

    Args:
        path: file or directory.
        column_map: see :func:`parse_column_map`. For MCAP it is optional: keys name state or
            action channels of the recording (``u=leg_vel_l,x=x``); by default u is the first
            action channel, x the channel named ``x`` (else the first state channel), and vbat
            the state channel ``vbat`` when there is one.
        robot: MCAP only: which robot's states, when the recording holds several.
        normalize_actions: MCAP only: actions in [-1, 1] of the robot's spec (what a learned
            checkpoint trained by ``hilstack.learning.mbrl`` sees) instead of robot units.
        warn: called with one line per recoverable problem (rows with NaN dropped and the
            episode split there, too-short episodes skipped); default :func:`warnings.warn`.

    Raises:
        DataError: missing file/column, non-numeric cells, bad time stamps, a map naming a
            column twice, no usable episode (the message names file, column and row).
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
    warn = warn or _warn_default
    episodes: list[Recording] = []
    for f in files:
        episodes.extend(_episodes_from_table(_read_table(f), mapping, f, warn))
    if not episodes:
        raise DataError(f"{p}: no usable episode (each needs at least {MIN_SAMPLES} clean samples with moving "
                        "position)")
    u_all = np.concatenate([e.u for e in episodes])
    if float(np.ptp(u_all)) == 0.0:
        raise DataError(f"{p}: the command column {mapping['u']!r} is constant ({float(u_all[0]):.6g}) in every "
                        "row: the actuator gain cannot be told apart from a constant force; record with a "
                        "varying command")
    return episodes


#: The first 8 bytes of every MCAP file.
MCAP_MAGIC = b"\x89MCAP0\r\n"


def _load_mcap(path: Path, mapping: dict[str, str], robot: str | None = None,
               normalize_actions: bool = False) -> list[Recording]:
    """Episodes of one robot from an MCAP recording (hilstack.learning.recordings.episodes_from_mcap).

    Actions stay in robot units (``normalize=False``): the nominal models replay them as
    commands, and a sim backend is commanded in robot units, not in [-1, 1]. A learned
    checkpoint sees what it was trained on (``normalize_actions=True``: hilstack.learning.mbrl's default).
    """
    from hilstack.learning.recordings import episodes_from_mcap

    with open(path, "rb") as f:
        magic = f.read(8)
    if magic != MCAP_MAGIC:
        raise DataError(f"{path} is not an MCAP file (its first bytes are not the MCAP magic {MCAP_MAGIC!r})")
    try:
        # the device's own sample clock where the robot reports one (a Dynamixel's Realtime Tick):
        # the host's stamps carry the link's latency and jitter
        raw = episodes_from_mcap(path, robot=robot, normalize=normalize_actions, clock="device")
    except ValueError as e:
        if "robots []" in str(e):
            raise DataError(f"{path}: no robot state messages in the recording (not a hilstack rig recording, or "
                            "truncated)") from e
        raise DataError(str(e)) from e
    except Exception as e:  # a corrupt MCAP body: the reader's own exception types vary
        raise DataError(f"{path}: unreadable MCAP recording: {type(e).__name__}: {str(e).splitlines()[0]}") from e
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
        out.append(Recording(
            name=le.name,
            t_s=t,
            u=channel("u", anames[0]),
            x=channel("x", "x" if "x" in snames else snames[0]),
            v_meas=channel("v", None),
            vbat_v=channel("vbat", "vbat" if "vbat" in snames else None),
            payload=channel("m", None),
            meta={"source": str(path), "robot": le.meta.get("robot"), "episode": le.meta.get("episode"),
                  "actions_normalized": normalize_actions, "clock": le.meta.get("clock", "host")},
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


def resample(e: Recording, period_s: float) -> Recording:
    """``e`` on a uniform grid of ``period_s`` [s] (coarser than its own).

    The command is a zero-order hold, so the new command of interval k is its exact average over
    [t_k, t_k + period_s) (from the integral of the ZOH signal); position, velocity, battery and
    payload are interpolated linearly.
    """
    if e.states is not None:
        raise DataError(f"{e.name}: a full-state recording cannot be resampled; record all episodes at one rate")
    t = e.t_s
    tu = t[0] + period_s * np.arange(int(np.floor((t[-1] - t[0]) / period_s + 1e-9)) + 1)
    integral = np.concatenate([[0.0], np.cumsum(e.u[:-1] * np.diff(t))])
    t_end = np.minimum(tu + period_s, t[-1])
    span = np.maximum(t_end - tu, 1e-12)
    u = (np.interp(t_end, t, integral) - np.interp(tu, t, integral)) / span
    u[span <= 1e-12] = e.u[-1]

    def interp(a):
        return None if a is None else np.interp(tu, t, a)

    return replace(e, t_s=tu, u=u, x=np.interp(tu, t, e.x), v_meas=interp(e.v_meas), vbat_v=interp(e.vbat_v),
                   payload=interp(e.payload), meta={**e.meta, "resampled_from_period_s": e.period_s})


def harmonize_rates(episodes: list[Recording], warn: Callable[[str], None] | None = None,
                    rtol: float = 0.01) -> list[Recording]:
    """One sample period for all episodes: the models are discrete-time with a single period.

    Episodes whose period differs by more than ``rtol`` are resampled to the slowest period
    (never upsampled: that would invent data), with a warning naming the rates found.
    """
    periods = np.array([e.period_s for e in episodes])
    if periods.max() <= (1 + rtol) * periods.min():
        return episodes
    slow = float(periods.max())
    rates = sorted({round(1.0 / p_, 3) for p_ in periods})
    fast = next(e for e in episodes if e.period_s < slow / (1 + rtol))
    (warn or _warn_default)(
        f"episodes are sampled at different rates ({', '.join(f'{r:g}' for r in rates)} Hz, e.g. {fast.name} at "
        f"{1 / fast.period_s:.4g} Hz): all were resampled to the slowest, {1 / slow:.4g} Hz (commands averaged over "
        "each period, positions interpolated); to avoid this, calibrate each rate separately")
    return [e if e.period_s >= slow / (1 + rtol) else resample(e, slow) for e in episodes]


@dataclass(frozen=True)
class SegmentPlan:
    """How recordings were cut into units for cross-validation (see :func:`segment_episodes`).

    Attributes:
        segmented: whether any recording was cut.
        horizon_steps: open-loop horizon [samples] the units were sized for (may be shorter than
            asked when the data are short).
        n_units: number of units (segments and whole episodes).
        n_test: units locked for the final test (the final block of each recording).
        note: what was done, for the report.
    """

    segmented: bool
    horizon_steps: int
    n_units: int
    n_test: int
    note: str | None = None


#: Fewest units (episodes or segments) calibration runs on; fewer cannot give a paired test any power.
MIN_UNITS = 8
#: Shortest open-loop horizon [samples] the segmentation may shrink to for a short recording.
MIN_HORIZON_STEPS = 10
#: Fewest scored samples in a segment of a long recording.
MIN_SEGMENT_SAMPLES = 40


def segment_episodes(episodes: list[Recording], min_episodes: int, horizon_steps: int, margin: int,
                     test_fraction: float = 0.2) -> tuple[list[Recording], SegmentPlan]:
    """Cut long recordings into contiguous segments so there are >= ``min_episodes`` units.

    Blocked time-series folds: every recording is cut into contiguous segments in time order and
    the last ``test_fraction`` of each cut recording (its final segments) is marked
    ``meta["locked_test"]``: the locked test set is the final block of the recording, never
    interleaved with training data. A segment holds ``margin`` samples at both ends (filter
    edges, delay history) as unscored context beyond 1.2 horizons of scored samples, so the
    segments tile the recording without losing rows. When the data are too short for ``min_episodes``
    such segments, the horizon is shortened (down to :data:`MIN_HORIZON_STEPS`), then the
    number of units is lowered (down to :data:`MIN_UNITS`); shorter data is a DataError that
    says how much is needed.
    """
    if len(episodes) >= min_episodes:
        return episodes, SegmentPlan(False, horizon_steps, len(episodes), 0)
    total = sum(e.n for e in episodes) - 2 * margin * len(episodes)
    h = horizon_steps

    def core(h_):  # scored samples per segment: 1.2 horizons, and enough rows to fit and score
        return max(int(math.ceil(1.2 * h_)), MIN_SEGMENT_SAMPLES)

    n_units = min_episodes
    if total < n_units * core(h):
        h = max(MIN_HORIZON_STEPS, int(total / n_units / 1.2))
        while n_units > MIN_UNITS and total < n_units * core(h):
            n_units -= 1
    if total < MIN_UNITS * core(h):
        period = episodes[0].period_s
        need = MIN_UNITS * core(MIN_HORIZON_STEPS) + 2 * margin
        raise DataError(f"data too short to calibrate: {total + 2 * margin * len(episodes)} samples "
                        f"({(total + 2 * margin * len(episodes)) * period:.3g} s) in {len(episodes)} episode(s); need "
                        f"at least {need} samples ({need * period:.3g} s) in one recording at this rate, for "
                        f"{MIN_UNITS} segments; record longer or more episodes")
    out: list[Recording] = []
    n_test = 0
    per = max(core(h), total // n_units)
    for e in episodes:
        k = (e.n - 2 * margin) // per
        if k < 2:  # too short to cut: used whole, as a training unit
            out.append(e)
            continue
        # Segment i scores rows edges[i]..edges[i+1]; it also carries ``margin`` samples of context on
        # each side (delay history, filter edges), which are never scored in that segment.
        edges = np.linspace(margin, e.n - margin, k + 1).astype(int)
        k_test = max(1, int(round(test_fraction * k)))
        for i in range(k):
            seg = e.slice(edges[i] - margin, edges[i + 1] + margin, f"{e.name}[seg{i}]")
            seg.meta["locked_test"] = i >= k - k_test
            n_test += i >= k - k_test
            out.append(seg)
    segmented = len(out) > len(episodes)
    note = None
    if segmented:
        note = (f"{len(episodes)} recording(s) cut into {len(out)} contiguous segments in time order; the final "
                f"{n_test} segment(s) (the last ~{test_fraction:.0%} of each recording) are the locked test set, the "
                "others form blocked folds; neighbouring segments are correlated, so p-values are somewhat optimistic")
        if h < horizon_steps:
            note += f"; the recording is short, so the open-loop horizon was shortened to {h} samples"
    return out, SegmentPlan(segmented, h, len(out), n_test, note)


def summarize(episodes: list[Recording]) -> dict:
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
    "Recording",
    "default_sg_window",
    "load_episodes",
    "parse_column_map",
    "SegmentPlan",
    "harmonize_rates",
    "resample",
    "segment_episodes",
    "sg_velocity",
    "sg_velocity_kernel",
    "summarize",
]
