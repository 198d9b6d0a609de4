"""A silhouette cut by the image frame: the frame's pixels are not the person's outline.

A hand or the feet outside the picture leave a straight run of outline pixels along the image
border. They say where the picture ends, not where the person does, so they must neither pull
the model's contour (e_P) nor seed the distance map the model contour is scored on (e_M).
"""

import torch

from torchfit.camera import Camera, project_points
from torchfit.fit import FitOptions, SilhouetteFit, person_data_from_masks
from torchfit.viz.preview import nominal_view
from torchfit.viz.raster import render_silhouette

SIZE = (360, 288)


def test_outline_pixels_on_the_frame_are_invalid_and_seed_no_distance():
    masks = torch.zeros(1, 1, 120, 160, dtype=torch.bool)
    masks[0, 0, 40:61, 0:90] = True  # a bar the left border cuts
    camera = nominal_view(image_size=(160, 120))
    person = person_data_from_masks(masks, camera)
    c, ok = person.contours[0][0], person.valid[0][0]
    on_frame = c[:, 0] == 0
    assert on_frame.any()
    assert not ok[on_frame].any()  # the cut
    assert ok[~on_frame].all()  # the rest of the outline counts
    # the distance map on the cut measures to the bar's own edges, 10 rows up or down at most
    dmap = person.distance_maps[0][0]
    assert float(dmap[50, 0]) > 9.0
    assert float(dmap[40, 0]) == 0.0 or float(dmap[40, 1]) == 0.0  # the top edge is a seed
    # a silhouette inside the picture keeps every outline pixel
    inside = torch.zeros_like(masks)
    inside[0, 0, 40:61, 10:90] = True
    assert person_data_from_masks(inside, camera).valid[0][0].all()


def _shifted_view() -> Camera:
    """The template in the T-pose, its arm on the image's left cut by the frame at the
    forearm."""
    cam = nominal_view(distance=3.5, focal=450.0, image_size=SIZE)
    K = cam.K.clone()
    K[..., 0, 2] -= 160.0
    return Camera(K=K, dist=cam.dist, R=cam.R, t=cam.t, image_size=SIZE)


def test_the_true_pose_fits_a_silhouette_the_frame_cuts(model):
    camera = _shifted_view()
    placeholder = torch.zeros(1, 1, SIZE[1], SIZE[0], dtype=torch.bool)
    placeholder[0, 0, 100:200, 150:200] = True
    options = FitOptions(poses=(4,))
    probe = SilhouetteFit(model, person_data_from_masks(placeholder, camera), options)
    x = probe.initial_params()
    rows = torch.zeros(1, dtype=torch.long)
    world, _ = probe.poser.world(x.to(model.dtype), 4, rows)
    pixels = project_points(world, camera.to(dtype=model.dtype))[0].detach().numpy()
    mask = torch.from_numpy(render_silhouette(pixels, model.faces.numpy(), SIZE) > 0)
    assert mask[:, 0].any() and not mask[:, -1].any()  # the left border cuts an arm

    person = person_data_from_masks(mask[None, None], camera)
    fit = SilhouetteFit(model, person, options)
    r = fit.residual(x, fit.select(x))
    valid = person.valid[0][0]
    n = int(valid.sum())
    distances = r[0, fit.residual_layout.e_p(4)].abs() * n**0.5
    # the person's outline is the model's own (its pixel centres within about a pixel of the
    # model contour); the border run, where the arm goes on beyond the picture, is left out
    assert float(distances.max()) < 1.5  # 16.8 px on the border run
    cut = person.contours[0][0][:, 0] == 0
    assert int(cut.sum()) > 50 and not valid[cut].any()
    # the model's own rendered outline runs along the frame too: no contour sample is chosen
    # for that run, whose distance map (seeded by the person's outline alone) is large there
    assert float(r[0, fit.residual_layout.e_m(4)]) < 1.0  # 1.57 px with the run's samples


def test_a_posture_the_frame_cuts_is_flagged_with_its_borders():
    from torchfit.image.plausibility import cut_borders
    from torchfit.pipeline.prepare import frame_cuts

    masks = torch.zeros(3, 60, 80, dtype=torch.bool)
    masks[0, 10:50, 20:60] = True  # inside the picture
    masks[1, 10:50, 0:80] = True  # arms out on both sides
    masks[2, 30:60, 30:40] = True  # feet below the picture
    assert frame_cuts(masks) == [
        "pose2: the image frame cuts the silhouette (left, right border): its parts beyond the "
        "picture are not measured, check the overlays",
        "pose3: the image frame cuts the silhouette (bottom border): its parts beyond the "
        "picture are not measured, check the overlays",
    ]
    assert cut_borders(masks[:, None]) == [[], ["left", "right"], ["bottom"]]
