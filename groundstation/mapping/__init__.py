"""Mapping engine: GP implicit surfaces from touch observations.

``GPIS`` is the homoscedastic Gaussian-likelihood model; ``RobustGPIS`` the Student-t model fitted
by variational EM (ALGORITHM.md). Both follow the scikit-learn estimator API. Names are imported
lazily so that reading settings (``groundstation.mapping.settings``) stays cheap.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from groundstation.mapping.gpis import GPIS
    from groundstation.mapping.robust import RobustGPIS

_EXPORTS = {
    "GPIS": "groundstation.mapping.gpis",
    "RobustGPIS": "groundstation.mapping.robust",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'groundstation.mapping' has no attribute {name!r}")
