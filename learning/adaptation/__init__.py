"""Online adaptation of learned dynamics (thesis ch. 5-6): GrBAL, ReBAL, MB+DE, MOLe.

The interface (``ModelUpdate``, ``Adapter``, ``load_adapter``) is in :mod:`.base`.
"""

from hilstack.learning.adaptation.base import ADAPTERS, Adapter, ModelUpdate, load_adapter

__all__ = ["ADAPTERS", "Adapter", "ModelUpdate", "load_adapter"]
