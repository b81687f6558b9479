"""PNG pictures of occupancy: Eq. 12 classes (free white, occupied black, unknown grey) and probabilities."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from gmm_core.occupancy import DEFAULT_VARIANCE, FREE, OCCUPIED, UNKNOWN, classify
from services.render import CLASS_GREY, occupancy_png, probability_png

WHITE, BLACK, GREY = CLASS_GREY[FREE], CLASS_GREY[OCCUPIED], CLASS_GREY[UNKNOWN]


def pixels(png: bytes) -> np.ndarray:
    image = Image.open(io.BytesIO(png))
    assert image.format == "PNG" and image.mode == "L"
    return np.asarray(image)


def test_class_colours():
    assert (WHITE, BLACK, GREY) == (255, 0, 128)
    assert pixels(probability_png(np.full((1, 1), 0.5, np.float32)))[0, 0] == GREY  # p = 0.5 looks the same in both


def test_2d_classes_at_the_default_variance_north_up():
    # sigma^2 = 0.21: thresholds (1 -+ sqrt(0.16)) / 2 = 0.3, 0.7.
    assert DEFAULT_VARIANCE == 0.21
    prob = np.array(
        [
            [0.0, 0.29, 0.31, 0.5],  # iy = 0, the southernmost row: the image's last
            [0.69, 0.71, 1.0, 0.51],
        ],
        dtype=np.float32,
    )
    image = pixels(occupancy_png(prob))
    assert image.shape == (2, 4)
    assert image.tolist() == [[GREY, BLACK, BLACK, GREY], [WHITE, WHITE, GREY, GREY]]


@pytest.mark.parametrize(
    "variance, expected",
    [
        (0.25, [WHITE, WHITE, GREY, BLACK, BLACK, BLACK]),  # the band closes: p = 0.5 alone stays unknown
        (0.09, [WHITE, GREY, GREY, GREY, BLACK, BLACK]),  # thresholds 0.1 and 0.9
        (0.0, [WHITE, GREY, GREY, GREY, GREY, BLACK]),  # only certainty is classified
    ],
)
def test_variance_moves_the_thresholds(variance, expected):
    prob = np.array([[0.0, 0.11, 0.5, 0.51, 0.91, 1.0]], dtype=np.float32)
    assert pixels(occupancy_png(prob, variance))[0].tolist() == expected


@pytest.mark.parametrize("variance", [-0.01, 0.2501, float("nan"), float("inf")])
def test_variance_outside_0_to_quarter_is_refused(variance):
    with pytest.raises(ValueError, match="variance"):
        occupancy_png(np.full((2, 2), 0.5, np.float32), variance)


def test_3d_columns_are_classified_voxel_by_voxel_then_projected():
    # [iz, iy, ix] with ix = columns: occupied+free, free+nothing seen, free+dead band, dead band, nothing seen,
    # occupied+dead band; one row (iy = 0).
    columns = np.array([[0.99, 0.01], [0.01, 0.5], [0.01, 0.3], [0.3, 0.7], [0.5, 0.5], [0.6, 0.97]], np.float32)
    prob = columns.T[:, None, :]
    assert prob.shape == (2, 1, 6)
    assert pixels(occupancy_png(prob))[0].tolist() == [BLACK, WHITE, WHITE, GREY, GREY, BLACK]


def reference_class_grey(prob: np.ndarray, variance: float) -> np.ndarray:
    """Column by column and voxel by voxel, as the rule is stated."""
    if prob.ndim == 2:
        prob = prob[None]
    out = np.empty(prob.shape[1:], np.uint8)
    for iy in range(prob.shape[1]):
        for ix in range(prob.shape[2]):
            column = [int(classify(np.array([p]), variance)[0]) for p in prob[:, iy, ix]]
            label = OCCUPIED if OCCUPIED in column else FREE if FREE in column else UNKNOWN
            out[iy, ix] = CLASS_GREY[label]
    return out[::-1]


@pytest.mark.parametrize("shape", [(9, 13), (5, 9, 13)])
@pytest.mark.parametrize("window", [False, True])  # a server's tile: a window of its layer's array
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_classes_match_the_plain_rule_on_random_maps(shape, window, dtype):
    rng = np.random.default_rng(7)
    prob = rng.uniform(0, 1, shape).astype(dtype)
    prob[rng.uniform(size=shape) < 0.3] = 0.5
    prob[rng.uniform(size=shape) < 0.1] = 0.7  # on the default's threshold: compared in double precision
    if window:
        prob = prob[..., 1:-2, 3:]
    for variance in (0.0, 0.03, DEFAULT_VARIANCE, 0.2, 0.25):
        assert np.array_equal(pixels(occupancy_png(prob, variance)), reference_class_grey(prob, variance))


def test_probability_picture_is_one_minus_p():
    prob = np.array([[0.0, 0.25, 0.5], [0.75, 1.0, 1.5]], dtype=np.float32)  # 1.5: clipped
    assert pixels(probability_png(prob)).tolist() == [[64, 0, 0], [255, 191, 128]]
    # 3D: a column shows its most occupied voxel when one is above 0.5, else its freest.
    columns = np.array([[0.9, 0.1], [0.25, 0.4], [0.5, 0.5]], np.float32)
    assert pixels(probability_png(columns.T[:, None, :]))[0].tolist() == [26, 191, 128]
