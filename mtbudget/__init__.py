"""mtbudget: uncertainty budgets for machine-tool volumetric verification with a laser tracker.

Internal unit system of every hot-path array: mm, rad, K, s (see :mod:`mtbudget.units`).
"""

__version__ = "0.1.0"

from .hookspecs import hookimpl  # noqa: E402
from .units import Q_, ureg  # noqa: E402

__all__ = ["ureg", "Q_", "hookimpl", "__version__"]
