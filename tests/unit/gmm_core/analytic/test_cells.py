"""gmm_core.analytic.cells: occupancy (Eq. 11) and evidence at given cells, and the checks of
dimensions and cell sizes."""

import numpy as np
import pytest

from gmm_core import Grid, Mixture, Pose, ScanModel
from gmm_core.analytic.cells import occupancy_at_cells, scan_evidence
from gmm_core.analytic.evidence_2d import analytic_map_2d
from support.evidence import two_scans_2d


def test_occupancy_at_cells_is_eq11_of_the_evidence_and_the_prior_where_unseen():
    models = two_scans_2d()[:1]
    cells = np.array([[2.0, -0.3], [2.0, 0.4], [1.0, 0.0], [2.5, 0.0], [-5.0, 5.0]])
    hits, misses = scan_evidence(models, cells, 0.05)
    p = occupancy_at_cells(models, cells, 0.05, prior=0.2)
    np.testing.assert_allclose(p, (hits + 0.2) / (hits + misses + 0.4), rtol=1e-6)
    assert p[0] > 0.8 and p[1] > 0.8  # on the wall
    assert p[2] < 0.15  # in the free space in front of it (about 1.5 misses against N_p = 0.2)
    assert p[3] == p[4] == 0.5  # behind the wall, and far away: never observed
    assert occupancy_at_cells([], cells, 0.05).tolist() == [0.5] * 5


def test_3d_scan_evidence_and_dimension_checks():
    flat = Mixture(np.ones(1), np.array([[2.0, 0.0, 0.0]]), np.diag([1e-4, 0.04, 0.04])[None], 50)
    scan = ScanModel(flat, Mixture.empty(3), np.zeros(3), 10.0)
    cells = np.array([[2.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    hits, misses = scan_evidence([(scan, Pose.identity(3))], cells, 0.1)
    # 50 points over a 20 cm x 20 cm patch: about 2 in the 10 cm cube at its centre.
    assert hits[0] > 1.5 and hits[1] == 0 and misses[1] > 1.5 and hits[2] == misses[2] == 0
    with pytest.raises(ValueError, match="2D"):
        analytic_map_2d([(scan, Pose.identity(3))], Grid(np.zeros(3), 0.1, (2, 2, 2)))
    with pytest.raises(ValueError, match="2D points"):
        scan_evidence([(scan, Pose.identity(3))], np.zeros((1, 2)), 0.1)
    with pytest.raises(ValueError, match="cell_size"):
        scan_evidence([(scan, Pose.identity(3))], cells, 0.0)
