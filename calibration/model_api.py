"""The calibration model's contract: what every nominal model has, and what it may declare beyond it.

:func:`hilstack.calibration.selection.select_effects` and
:func:`hilstack.calibration.report.run_calibration` talk to a nominal model through :class:`Model`
alone (fit with and without a candidate effect, held-out and out-of-bag losses, scores, the
effect catalogue and its look-alikes, and four behaviour flags whose defaults are on
:class:`NominalModel`). What a model offers beyond that it **declares** by subclassing one of the
optional capabilities below; the callers ask with ``isinstance`` (never by probing attributes):

* :class:`LoadsEpisodes`: ``load_episodes(path, column_map, robot=...)`` (the model knows its
  channels: a checkpoint's state and action names) instead of the generic column-map loader.
* :class:`BatchLosses`: ``episode_losses(pairs, horizon, nm)`` and ``oob_losses(pairs, nm)``, the
  held-out and out-of-bag losses of many (episode, fitted) pairs in one batch (the axis model
  replays them vectorised) instead of one call per pair.
* :class:`OwnDetectionLimits`, :class:`ResidualRows`, :class:`OwnPlots`: the detection limits,
  the black-box check's rows and the report's figures of a model that is not the axis model
  (without them the axis model's own, which read its regression design, are used).
* :class:`ExportsSimParams` (``export``: the calibrated sim's parameters, "closing the loop") and
  :class:`ExportsAugmented` (``export_augmented``: the retrained network beside the report).
* :class:`CountsRollouts` (``n_rollouts``: simulator replays so far, in the report) and
  :class:`DescribesVelocity` (``velocity_source``: where the report says the velocities came from).

Every capability's members are abstract: a model class that declares one and lacks a member
cannot be built (``TypeError: Can't instantiate abstract class X with abstract method plots``),
so a misspelt or forgotten method fails at construction instead of silently taking the
generic branch. The protocols are also runtime-checkable, as those of
:mod:`hilstack.control.policy_api` are: a class that has the members without declaring them
is treated as having the capability (the models in the repository all declare).

A fitted model (:class:`FittedModel`) may declare :class:`PhaseAlong` (``primary_along``: a
position-periodic load measured along a reference fit's phase, so a bootstrap replicate cannot
flip its sign by moving to the other representation of the same load).

Why protocols and not a capabilities dataclass: the optional parts here are methods, and the
declaration that names a method is the method's own protocol, so it is checked at
construction by Python's abstract-class machinery and read by ``isinstance``; a table of
booleans beside them would say the same thing a second time and could disagree with it. The
four switches that are not methods (``segmentable``, ``pair_tests``, ``reports_bounds``,
``shift_interval_to_refined``) are plain class attributes with defaults on
:class:`NominalModel`, part of :class:`Model`, and read without a default.
"""

from __future__ import annotations

from abc import abstractmethod
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

if TYPE_CHECKING:
    from pathlib import Path

    import numpy as np

    from hilstack.calibration.axis import Scores
    from hilstack.calibration.data import Recording
    from hilstack.calibration.effects import EffectSpec


@runtime_checkable
class PreparedEpisode(Protocol):
    """What every model's prepared episode (``Model.prepare``'s items) has: the recording it came
    from (whose ``meta`` says whether it is a segment of a longer one, ``segment_of``, and
    whether it is locked for the test set, ``locked_test``) and its sample period [s]."""

    ep: Recording
    period_s: float


@runtime_checkable
class FittedModel(Protocol):
    """A nominal model with fitted parameters and a set of effects."""

    effects: list[str]

    def primary(self, name: str) -> float:
        """Value of effect ``name``'s primary parameter (catalogue units)."""
        ...

    def effect_params(self, name: str) -> dict[str, float]: ...

    def to_dict(self) -> dict: ...


@runtime_checkable
class Model(Protocol):
    """A nominal model family: prepares data, fits parameters together with effects.

    ``fit(episodes, effects, weights=None, refine=True, start=None, search=None)``: weights
    are per-episode (bootstrap counts); ``start`` a fitted model whose values are kept for
    effects not in ``search`` (None: search all). ``norms`` returns the normalizers that
    ``episode_loss`` (the selection loss of one held-out episode) and ``oob_loss`` (a cheap
    loss for the bootstrap's out-of-bag check) use; ``score`` returns per-channel squared
    errors (:class:`hilstack.calibration.axis.Scores`) and ``channel_sd`` their report normalizers.

    The flags (defaults on :class:`NominalModel`): ``segmentable``, long recordings may be cut
    into contiguous segments (windows start from measured states); ``pair_tests``, fits are
    cheap enough to test the best candidates in each other's presence and to search over sets;
    ``reports_bounds``, a fit has ``at_bound`` (hyper-parameters stuck at the edge of their
    search range, whose candidate is then rejected); ``shift_interval_to_refined``, bootstrap
    fits are coarse (a cached grid) and the accepted effect's interval is centred on the
    refined pool fit.
    """

    name: str
    catalogue: dict[str, EffectSpec]
    look_alikes: dict
    segmentable: bool
    pair_tests: bool
    reports_bounds: bool
    shift_interval_to_refined: bool

    def prepare(self, episodes: list[Recording]) -> list[PreparedEpisode]: ...

    def fit(self, episodes: list, effects: list[str], **kw) -> FittedModel: ...

    def candidate_effects(self, episodes: list, accepted: tuple[str, ...] = ()
                          ) -> tuple[list[str], dict[str, str]]: ...

    def norms(self, pool: list) -> Any: ...

    def episode_loss(self, prep: Any, fitted: FittedModel, horizon: int, nm: Any) -> float: ...

    def oob_loss(self, prep: Any, fitted: FittedModel, nm: Any) -> float: ...

    def score(self, prep: Any, fitted: FittedModel, horizon: int) -> Scores: ...

    def channel_sd(self, preps: list) -> dict[str, dict[str, float]]: ...


class NominalModel:
    """Base of the repository's nominal models: the defaults of :class:`Model`'s flags."""

    segmentable: ClassVar[bool] = False
    pair_tests: ClassVar[bool] = False
    reports_bounds: ClassVar[bool] = False
    shift_interval_to_refined: ClassVar[bool] = False


#: every member of :class:`Model` (its annotated attributes and its methods)
MODEL_MEMBERS: tuple[str, ...] = tuple(sorted(
    set(Model.__annotations__) | {k for k, v in vars(Model).items() if callable(v) and not k.startswith("_")}))


def missing_members(model: object) -> list[str]:
    """The members of :class:`Model` that ``model`` lacks (empty: it is a model)."""
    return [m for m in MODEL_MEMBERS if not hasattr(model, m)]


def require_model(model: object, name: str) -> Model:
    """``model`` if it has every member of :class:`Model`, else a one-line TypeError naming them."""
    missing = missing_members(model)
    if missing:
        raise TypeError(f"nominal model {name!r} ({type(model).__name__}) lacks {', '.join(missing)} "
                        "of the Model protocol (hilstack.calibration.model_api)")
    return model  # type: ignore[return-value]


# ----------------------------------------------------------------------------- optional capabilities


@runtime_checkable
class LoadsEpisodes(Protocol):
    """The model reads its own data (its channels by name) instead of the column-map loader."""

    @abstractmethod
    def load_episodes(self, path: str | Path, column_map: Any = None, robot: str | None = None
                      ) -> list[Recording]: ...


@runtime_checkable
class BatchLosses(Protocol):
    """Held-out and out-of-bag losses of many (prepared episode, fitted) pairs in one call, equal
    to ``episode_loss`` / ``oob_loss`` of each pair."""

    @abstractmethod
    def episode_losses(self, pairs: list[tuple[Any, FittedModel]], horizon: int, nm: Any) -> list: ...

    @abstractmethod
    def oob_losses(self, pairs: list[tuple[Any, FittedModel]], nm: Any) -> list: ...


@runtime_checkable
class OwnDetectionLimits(Protocol):
    """The report's ``detection_limit`` section (same shape as
    :func:`hilstack.calibration.selection.detection_limits`)."""

    @abstractmethod
    def detection_limits(self, pool: list, fitted: FittedModel, candidates: list[str],
                         skipped: dict[str, str], cfg: Any) -> dict: ...


@runtime_checkable
class ResidualRows(Protocol):
    """The black-box check's rows of one episode: (features [N, d], residual [N]) of ``fitted``."""

    @abstractmethod
    def residual_rows(self, prep: Any, fitted: FittedModel) -> tuple[np.ndarray, np.ndarray]: ...


@runtime_checkable
class OwnPlots(Protocol):
    """The report's figures (``residual_before_after.png``; the candidates' plot is shared)."""

    @abstractmethod
    def plots(self, out: Path, sel: Any, preps: list, pool: list, test: list) -> None: ...


@runtime_checkable
class ExportsSimParams(Protocol):
    """Closing the loop: the calibrated simulator's parameters written beside the report; returns
    the report's ``closing_the_loop`` section."""

    @abstractmethod
    def export(self, out: Path, fitted: FittedModel, report: dict) -> dict: ...


@runtime_checkable
class ExportsAugmented(Protocol):
    """The augmented (retrained) model written beside the report; returns the report's
    ``augmented_model`` section."""

    @abstractmethod
    def export_augmented(self, out: Path, fitted: FittedModel, report: dict, test: list) -> dict: ...


@runtime_checkable
class CountsRollouts(Protocol):
    """Simulator replays run so far (the report's ``sim_rollouts``)."""

    @property
    @abstractmethod
    def n_rollouts(self) -> int: ...


@runtime_checkable
class DescribesVelocity(Protocol):
    """Where the velocities come from, as the report says it (default: from the prepared episode)."""

    @property
    @abstractmethod
    def velocity_source(self) -> str: ...


@runtime_checkable
class PhaseAlong(Protocol):
    """A fitted model whose position-periodic loads have a phase: ``primary_along(name, ref)`` is
    the primary of ``name`` measured along ``ref``'s phase."""

    @abstractmethod
    def primary_along(self, name: str, ref: Any) -> float: ...
