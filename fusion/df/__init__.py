"""Bearings-only emitter localisation (documents 000–003, docs/algorithms.md).

Modules: :mod:`.models` (geometry, edge conversions), :mod:`.filters` (EKFT/EKFS/SKF,
cross-fed MEKF), :mod:`.imm`, :mod:`.init` (robust choice of the initial ``ipu`` pair
under jamming), :mod:`.triangulation` (ipu, Torrieri, Stansfield,
pairwise average, perpendicular LS, leave-one-out), :mod:`.smoothing` (KF/MKF bearing
smoothers), :mod:`.noise`, :mod:`.crb`, :mod:`.methods` (the streaming Methods and
:data:`DF_METHODS`).
"""

from .methods import DF_METHODS, DFConfig, DFMethod, centre_fix, make, make_station_smoother

__all__ = ["DF_METHODS", "DFConfig", "DFMethod", "centre_fix", "make", "make_station_smoother"]
