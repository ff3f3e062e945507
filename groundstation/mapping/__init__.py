"""Mapping engine: GP implicit surfaces from touch observations.

``GPIS`` is the homoscedastic Gaussian-likelihood model; ``RobustGPIS`` the Student-t model fitted
by variational EM (ALGORITHM.md). Both follow the scikit-learn estimator API.
"""

from groundstation.mapping.gpis import GPIS
from groundstation.mapping.robust import RobustGPIS

__all__ = ["GPIS", "RobustGPIS"]
