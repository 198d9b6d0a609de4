"""PersonData's contour normals: aligned with the contour pixels, kept by subset and to."""

from __future__ import annotations

import torch

from torchfit.camera import Camera
from torchfit.fit.person import person_data_from_masks
from torchfit.image.contours import contour_normals, trace_outer_contour


def _camera(b: int) -> Camera:
    k = torch.tensor([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]], dtype=torch.float64)
    return Camera(
        K=k.expand(b, 3, 3),
        dist=torch.zeros(b, 5, dtype=torch.float64),
        R=torch.eye(3, dtype=torch.float64).expand(b, 3, 3),
        t=torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64).expand(b, 3),
        image_size=(64, 48),
    )


def test_normals_follow_the_contour_pixels_and_the_subset():
    masks = torch.zeros(2, 1, 48, 64, dtype=torch.bool)
    masks[0, 0, 10:30, 5:45] = True
    masks[1, 0, 5:15, 20:30] = True
    person = person_data_from_masks(masks, _camera(2), stride=2, normals=True)
    assert person_data_from_masks(masks, _camera(2), stride=2).normals is None
    (normals,), (contours,) = person.normals, person.contours
    assert normals.shape == contours.shape and normals.dtype == torch.float32
    for i in range(2):
        expected = contour_normals(trace_outer_contour(masks[i, 0]))[::2]
        assert torch.equal(normals[i, : len(expected)], expected)
        assert normals[i, len(expected) :].abs().sum() == 0  # padding
        # each normal belongs to its pixel: it points away from the rectangle's centre
        n = len(expected)
        centre = contours[i, :n].mean(0).float()
        assert ((contours[i, :n].float() - centre) * normals[i, :n]).sum(1).min() > 0
    sub = person.subset([1])
    assert torch.equal(sub.normals[0][0], normals[1])
    assert sub.to("cpu").normals[0].data_ptr() == sub.normals[0].data_ptr()
