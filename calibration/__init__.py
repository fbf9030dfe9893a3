"""hilstack calibration: residual → effect → augmented model → before/after report.

Entry points: :func:`run_calibration` (the whole pipeline, also ``hil calibrate``),
:func:`load_episodes` (CSV/Parquet/MCAP with a column map) and :func:`load_model`
(the augmented model saved as ``model.json``). See docs/calibration.md.
"""

from hilstack.calibration.data import DataError, Recording, load_episodes
from hilstack.calibration.models import ModelNotAvailable, UnknownModel, get_model, load_model
from hilstack.calibration.report import run_calibration

__all__ = [
    "DataError",
    "Recording",
    "ModelNotAvailable",
    "UnknownModel",
    "get_model",
    "load_episodes",
    "load_model",
    "run_calibration",
]
