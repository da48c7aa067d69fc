"""mtbudget: uncertainty budgets for machine-tool volumetric verification with a laser tracker.

Internal unit system of every hot-path array: mm, rad, K, s (see :mod:`mtbudget.units`).
``ureg``, ``Q_`` and ``hookimpl`` are imported on first use, so ``mtbudget --help`` starts fast.
"""

__version__ = "0.3.0"

__all__ = ["ureg", "Q_", "hookimpl", "__version__"]


def __getattr__(name):
    if name in ("ureg", "Q_"):
        from . import units

        return getattr(units, name)
    if name == "hookimpl":
        from .hookspecs import hookimpl

        return hookimpl
    raise AttributeError(f"module 'mtbudget' has no attribute {name!r}")
