"""mtbudget: uncertainty budgets for machine-tool volumetric verification with a laser tracker.

Internal unit system of every hot-path array: mm, rad, K, s (see :mod:`mtbudget.units`).
"""

__version__ = "0.1.0"

from .units import ureg, Q_  # noqa: E402

__all__ = ["ureg", "Q_", "__version__"]
