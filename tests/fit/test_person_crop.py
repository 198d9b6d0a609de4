"""person_data_from_masks(crop_margin_px=...): each distance map, on its own silhouette's box,
is that of the whole image inside the box and keeps growing outside it; a row's map does not
depend on the other rows."""

import pytest
import torch

from torchfit.fit.person import person_data_from_masks
from torchfit.viz.preview import nominal_view


def _blobs() -> torch.Tensor:
    masks = torch.zeros(2, 1, 120, 160, dtype=torch.bool)
    masks[0, 0, 30:90, 60:80] = True  # a bar
    masks[0, 0, 40:50, 40:100] = True  # and arms
    masks[1, 0, 50:100, 70:110] = True  # another row, another place
    return masks


@pytest.mark.parametrize("method", ["chamfer", "euclidean"])
def test_cropped_maps_equal_the_whole_image_inside_the_box(method):
    masks = _blobs()
    camera = nominal_view(image_size=(160, 120))[[0, 0]]
    whole = person_data_from_masks(masks, camera, method=method).distance_maps[0]
    margin = 8
    crop = person_data_from_masks(masks, camera, method=method, crop_margin_px=margin)
    cropped = crop.distance_maps[0]
    boxes = [(30, 89, 40, 99), (50, 99, 70, 109)]  # each row's silhouette
    for i, (y0, y1, x0, x1) in enumerate(boxes):
        y0, y1, x0, x1 = y0 - margin, y1 + margin, x0 - margin, x1 + margin
        box = (slice(y0, y1 + 1), slice(x0, x1 + 1))
        torch.testing.assert_close(cropped[i][box], whole[i][box])
        outside = torch.ones(120, 160, dtype=torch.bool)
        outside[box] = False
        assert (cropped[i, outside] - whole[i, outside]).abs().max() > 0  # not the same map
        # away from the box the bound keeps growing: the corner is the farthest pixel
        assert cropped[i, 0, 0] > cropped[i, y0, x0]
        assert cropped[i, 0, 0] >= 0.8 * whole[i, 0, 0]


def test_a_rows_cropped_map_does_not_depend_on_the_others():
    """The same silhouette alone, beside another one far away, and twice: the same map."""
    masks = _blobs()
    camera = nominal_view(image_size=(160, 120))
    alone = person_data_from_masks(masks[:1], camera, crop_margin_px=8).distance_maps[0]
    for others in (masks, masks[[0, 0, 1]]):
        cams = camera[[0] * others.shape[0]]
        got = person_data_from_masks(others, cams, crop_margin_px=8).distance_maps[0]
        assert torch.equal(got[0], alone[0])


def test_an_empty_frame_gives_the_whole_image_map():
    masks = torch.zeros(1, 1, 60, 80, dtype=torch.bool)
    camera = nominal_view(image_size=(80, 60))
    a = person_data_from_masks(masks, camera).distance_maps[0]
    b = person_data_from_masks(masks, camera, crop_margin_px=4).distance_maps[0]
    torch.testing.assert_close(a, b)


@pytest.mark.parametrize("method", ["chamfer", "euclidean"])
def test_the_maps_are_those_of_each_silhouettes_outer_contour_bitwise(method):
    """D_P is seeded by the outlines the contours were traced from: it is
    mask_to_distance_map's map of the silhouette, bit for bit (a second region, here a speck
    apart from the body, is no seed: only the region holding the first pixel is traced)."""
    from torchfit.image.distance import mask_to_distance_map

    masks = _blobs()
    masks[0, 0, 5:8, 140:150] = True  # a speck before the body in raster order
    camera = nominal_view(image_size=(160, 120))[[0, 0]]
    got = person_data_from_masks(masks, camera, method=method).distance_maps[0]
    want = torch.nan_to_num(mask_to_distance_map(masks, method)[:, 0], posinf=280.0)
    assert torch.equal(got, want)
