"""Image residuals in reference pixels (``FitOptions.reference_px_per_m``): the same person seen
by a camera of twice the resolution costs the same, so the priors weigh the same against the
images on any camera.

The person is the template with a different thigh / shank split, drawn as exact silhouettes by
the fit's own rasteriser in posture 3 (whose knee is marked) through two cameras that differ
only in resolution: the second has twice the focal length and twice the image size.
"""

import dataclasses

import pytest
import torch

from torchfit.body.postures import POSTURES, pose_nominal
from torchfit.camera import camera_centre, project_points, stack_cameras
from torchfit.errors import ConfigError
from torchfit.fit import FitOptions, person_data_from_masks
from torchfit.fit.bends import BendFit, BendOptions
from torchfit.fit.options import pixels_per_metre
from torchfit.viz.preview import nominal_view
from torchfit.viz.raster import render_silhouette

SPLIT = {"thigh": 0.93, "calf": 1.05}


def _camera(factor: float):
    return nominal_view(
        distance=3.2, height=1.0, azimuth_deg=20.0, focal=450.0 * factor,
        image_size=(int(360 * factor), int(288 * factor)),
    )  # fmt: skip


def _fit(model, factor: float, reference: float | None) -> BendFit:
    """Posture 3 of the template with another leg split, seen by :func:`_camera` (factor)."""
    camera = _camera(factor)
    scales = torch.ones(1, model.num_segments, 3, dtype=model.dtype)
    for name, value in SPLIT.items():
        for side in "lr":
            scales[0, model.template.segments.index(f"{side}_{name}"), 2] = value
    posture = next(p for p in POSTURES if p.index == 3)
    _, out = pose_nominal(model, scales, posture, camera_centre(camera.R, camera.t))
    px = project_points(out.vertices, camera.to(dtype=out.vertices.dtype))[0].numpy()
    mask = torch.from_numpy(render_silhouette(px, model.faces.numpy(), camera.image_size) > 127)
    person = person_data_from_masks(mask[None, None], stack_cameras([camera]))
    person.silhouettes = {0: mask[None]}
    options = FitOptions(poses=(3,), reference_px_per_m=reference)
    return BendFit(model, person, options, bends=BendOptions(weight=1.0))


def test_pixels_per_metre_is_the_focal_length_over_the_distance_to_the_person():
    # the camera stands 1 m high, 3.2 m from the mark: 3.2 m from the point 1 m above it
    for factor in (1.0, 2.0):
        torch.testing.assert_close(
            pixels_per_metre(stack_cameras([_camera(factor)])),
            torch.tensor([factor * 450.0 / 3.2], dtype=torch.float64),
        )


def _image_rows(fit: BendFit) -> torch.Tensor:
    layout = fit.residual_layout
    rows = [torch.arange(layout.size)[layout.e_p(3)], torch.tensor([layout.e_m(3)])]
    return torch.cat([*rows, torch.arange(layout.size)[layout.marks]])


def test_the_image_terms_are_scaled_to_reference_pixels_and_the_rest_is_not(model):
    plain = _fit(model, 1.0, None)
    ppm = float(pixels_per_metre(plain.camera)[0])
    scaled = _fit(model, 1.0, 2.0 * ppm)  # a reference of twice this camera's resolution
    torch.testing.assert_close(scaled.image_scale, torch.tensor([2.0], dtype=torch.float64))
    x = plain.initial_params() + 0.01  # off the template: the marks and barriers are set
    sel = plain.select(x)
    free = torch.arange(plain.num_params)
    jac_p, r_p = plain.jacobian_and_residual(x, free, sel)
    jac_s, r_s = scaled.jacobian_and_residual(x, free, scaled.select(x))
    image = _image_rows(plain)
    assert float(r_p[0, image].abs().sum()) > 0
    torch.testing.assert_close(r_s[0, image], 2.0 * r_p[0, image])
    torch.testing.assert_close(jac_s[0, image], 2.0 * jac_p[0, image])
    rest = torch.ones(r_p.shape[1], dtype=torch.bool)
    rest[image] = False
    torch.testing.assert_close(r_s[0, rest], r_p[0, rest])
    torch.testing.assert_close(jac_s[0, rest], jac_p[0, rest])
    # the robust loss's unit is a reference pixel: the same entries as before
    torch.testing.assert_close(scaled.loss_units(), plain.loss_units())


def test_twice_the_resolution_costs_the_same_in_reference_pixels(model):
    def image_cost(fit):
        x = fit.initial_params()  # the template's split: its contour is off the person's
        r = fit.residual(x, fit.select(x))[0, _image_rows(fit)]
        return float((r * r).sum())

    reference = float(pixels_per_metre(_camera(1.0).to(dtype=torch.float64))[0])
    low, high = image_cost(_fit(model, 1.0, reference)), image_cost(_fit(model, 2.0, reference))
    assert low > 1.0
    assert high == pytest.approx(low, rel=0.15)
    # in the image's own pixels, the sharper camera's contour errors count four times
    assert image_cost(_fit(model, 2.0, None)) == pytest.approx(4 * low, rel=0.15)


def test_a_bad_reference_is_named():
    for bad in (0.0, -3.0, float("inf")):
        with pytest.raises(ConfigError, match="reference_px_per_m"):
            FitOptions(reference_px_per_m=bad)


def test_the_pixel_noise_ratio_lies_between_reference_and_image_pixels():
    """``pixel_noise_ratio`` ρ: the factor is 1 at the reference camera, reference pixels at
    ρ = 0, the image's own pixels as ρ grows, and between the two otherwise."""
    from torchfit.fit.options import image_scale

    low, high = stack_cameras([_camera(1.0)]), stack_cameras([_camera(2.0)])
    cameras = dataclasses.replace(
        high,
        K=torch.cat([low.K, high.K]),
        dist=torch.cat([low.dist, high.dist]),
        R=torch.cat([low.R, high.R]),
        t=torch.cat([low.t, high.t]),
    )  # two resolutions in one batch: only their K and pose are read here
    ppm = pixels_per_metre(cameras)
    reference = image_scale(cameras, float(ppm[0]))
    torch.testing.assert_close(reference, torch.tensor([1.0, 0.5], dtype=torch.float64))
    torch.testing.assert_close(image_scale(cameras, float(ppm[0]), 0.0), reference)
    torch.testing.assert_close(
        image_scale(cameras, float(ppm[0]), 1e6), torch.ones(2, dtype=torch.float64)
    )
    blend = image_scale(cameras, float(ppm[0]), 1.0)
    torch.testing.assert_close(blend, torch.tensor([1.0, (2 / 5) ** 0.5], dtype=torch.float64))
    assert 0.5 < float(blend[1]) < 1.0
    for bad in (-1.0, float("nan")):
        with pytest.raises(ConfigError, match="pixel_noise_ratio"):
            FitOptions(pixel_noise_ratio=bad)
