"""The mathematics of GMM occupancy mapping (O'Meadhra, Tabib, Michael, RA-L 2019).

numpy + numba only: no I/O, no network, no threads of its own beyond numba's kernels.
"""

from gmm_core.grid import Grid
from gmm_core.mixture import Mixture
from gmm_core.pose import Pose
from gmm_core.scan import FitConfig, ScanModel, fit_scan

__all__ = ["FitConfig", "Grid", "Mixture", "Pose", "ScanModel", "fit_scan"]
