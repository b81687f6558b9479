"""`gmmap export --from MAP.npz` on maps written by `gmmap replay` from the real data, and its refusals."""

import numpy as np
import pytest
import yaml
from PIL import Image
from plyfile import PlyData

from gmm_core import Grid
from gmm_core.occupancy import FREE, OCCUPIED, classify
from services.cli import main
from services.export.octomap_tree import lattice_offset
from support.octomap_trees import class_log_odds, nodes_log_odds

octomap = pytest.importorskip("octomap", reason="octomap-python is in the [bench] and [dev] extras")


@pytest.fixture(scope="module")
def intel_npz(data_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("intel") / "intel.npz"
    log = data_dir / "carmen" / "intel-corrected.log.gz"
    assert main(["replay", str(log), "--method", "raw", "--resolution", "0.2", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def kurt3d_npz(data_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("kurt3d") / "kurt3d.npz"
    assert (
        main(["replay", str(data_dir / "3d" / "kurt3d"), "--method", "raw", "--resolution", "0.5", "--out", str(out)])
        == 0
    )
    return out


def saved(npz):
    data = np.load(npz)
    return Grid(data["origin"], float(data["resolution"]), data["prob"].shape[::-1]), data["prob"]


def test_pgm_from_an_npz(intel_npz, tmp_path, capsys):
    grid, prob = saved(intel_npz)
    assert main(["export", "--from", str(intel_npz), "--format", "pgm", "--out", str(tmp_path / "intel")]) == 0
    assert "wrote" in capsys.readouterr().out
    meta = yaml.safe_load((tmp_path / "intel.yaml").read_text())
    assert meta["origin"] == [*grid.origin.tolist(), 0.0] and meta["resolution"] == 0.2
    pixels = np.asarray(Image.open(tmp_path / meta["image"]))[::-1]
    classes = classify(prob, 0.21)
    assert (classes == OCCUPIED).sum() > 500 and (classes == FREE).sum() > 5000
    np.testing.assert_array_equal(pixels == 0, classes == OCCUPIED)
    np.testing.assert_array_equal(pixels == 254, classes == FREE)


def test_bbox_crops_whole_cells_without_resampling(intel_npz, tmp_path):
    grid, prob = saved(intel_npz)
    out = tmp_path / "part"
    assert main(["export", "--from", str(intel_npz), "--format", "ply", "--bbox=-5,-5,5,3", "--out", str(out)]) == 0
    first = np.floor((np.array([-5, -5]) - grid.origin) / 0.2).astype(int)
    stop = np.ceil((np.array([5, 3]) - grid.origin) / 0.2).astype(int)
    part = prob[first[1] : stop[1], first[0] : stop[0]]
    vertex = PlyData.read(tmp_path / "part.ply")["vertex"]
    assert vertex.count == (classify(part, 0.21) == OCCUPIED).sum() > 20
    assert vertex["x"].min() > -5.2 and vertex["x"].max() < 5.2 and vertex["y"].max() < 3.2


def test_bt_from_a_3d_npz(kurt3d_npz, tmp_path, capsys):
    grid, prob = saved(kurt3d_npz)
    out = tmp_path / "kurt3d.bt"
    assert main(["export", "--from", str(kurt3d_npz), "--format", "bt", "--resolution", "0.5", "--out", str(out)]) == 0
    assert "onto OctoMap's voxels" in capsys.readouterr().out  # replay's extent is not on OctoMap's lattice
    tree = octomap.OcTree(str(out).encode())
    assert tree.getResolution() == 0.5
    classes = classify(prob, 0.21).ravel()
    assert (classes == OCCUPIED).sum() > 50 and (classes == FREE).sum() > 500
    voxels = grid.cell_centers() - lattice_offset(grid)  # each cell's voxel
    np.testing.assert_allclose(nodes_log_odds(tree, voxels), class_log_odds(tree, classes, OCCUPIED, FREE), rtol=1e-6)


@pytest.mark.parametrize(
    "arguments, words",
    [
        (["--format", "bt"], "format: bt: OctoMap trees are 3D and this map is 2D"),
        (["--format", "ot"], "format: ot: OctoMap trees are 3D and this map is 2D"),
        (["--format", "pgm", "--resolution", "0.1"], "resolution: the npz holds a 0.2 m grid and --from does not"),
        (["--format", "pgm", "--bbox=0,0,1"], "bbox: this map is 2D: give 4 numbers"),
        (["--format", "pgm", "--bbox=0,0,0,1,1,1"], "bbox: this map is 2D"),
        (["--format", "pgm", "--bbox=1,0,0,1"], "bbox: every max must exceed its min"),
        (["--format", "pgm", "--bbox=500,500,600,600"], "bbox: outside the map"),
        (["--format", "pgm", "--variance", "0.3"], "reconstruction.variance"),
    ],
)
def test_bad_input_is_refused_and_writes_nothing(intel_npz, tmp_path, capsys, arguments, words):
    out = tmp_path / "refused"
    assert main(["export", "--from", str(intel_npz), *arguments, "--out", str(out)]) == 2
    assert words in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_bad_sources_are_refused(tmp_path, capsys):
    np.savez(tmp_path / "other.npz", prob=np.zeros((2, 2), np.float32))
    (tmp_path / "text.npz").write_text("not a zip")
    np.save(tmp_path / "array.npy", np.zeros((2, 2), np.float32))
    for source, words in (
        ("other.npz", "lacks origin, resolution"),
        ("text.npz", "is not an npz file"),
        ("array.npy", "is not an npz file (one array"),
    ):
        assert main(["export", "--from", str(tmp_path / source), "--format", "pgm", "--out", str(tmp_path / "x")]) == 2
        assert words in capsys.readouterr().err
    assert main(["export", "--url", "ftp://host:1", "--format", "pgm", "--out", str(tmp_path / "x")]) == 2
    assert "--url: must be http://HOST:PORT" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        main(["export", "--from", "a.npz", "--format", "pgm", "--bbox=a,b,c,d", "--out", "x"])
    assert exit_.value.code == 2 and "comma-separated numbers" in capsys.readouterr().err
