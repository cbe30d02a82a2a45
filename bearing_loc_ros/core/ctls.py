"""Deprecated alias of :mod:`bearing_loc_ros.core.constrained_tls` (kept for one release).

Import ``constrained_tls``, ``ctls_cost``, ``ctls_derivatives`` and ``ctls_covariance`` from
``bearing_loc_ros.core.constrained_tls`` instead.
"""

import warnings

from .constrained_tls import (constrained_tls, ctls_cost, ctls_covariance,  # noqa: F401
                              ctls_derivatives, WEIGHTINGS)

warnings.warn('bearing_loc_ros.core.ctls is deprecated: use bearing_loc_ros.core.constrained_tls',
              DeprecationWarning, stacklevel=2)
