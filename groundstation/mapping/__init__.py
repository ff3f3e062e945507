"""Mapping engine: GP implicit surfaces from touch observations.

``GPIS`` is the homoscedastic Gaussian-likelihood model; ``RobustGPIS`` the Student-t model fitted
by variational EM (ALGORITHM.md); ``SparseRobustGPIS`` its inducing-point version (§8); all follow
the scikit-learn estimator API. ``SurfaceModel`` is the mapper's default pipeline: merge redundant
observations, fit exact or sparse by budget (warm-started), evaluate the field in a narrow band,
mesh. Names are imported
lazily so that reading settings (``groundstation.mapping.settings``) stays cheap.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from groundstation.mapping.gpis import GPIS
    from groundstation.mapping.model import SurfaceModel
    from groundstation.mapping.robust import RobustGPIS
    from groundstation.mapping.sparse import SparseRobustGPIS

_EXPORTS = {
    "GPIS": "groundstation.mapping.gpis",
    "RobustGPIS": "groundstation.mapping.robust",
    "SparseRobustGPIS": "groundstation.mapping.sparse",
    "SurfaceModel": "groundstation.mapping.model",
}

__all__ = ["GPIS", "RobustGPIS", "SparseRobustGPIS", "SurfaceModel"]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'groundstation.mapping' has no attribute {name!r}")
