"""The judge and lengths a posture shows end to end (torchfit.pipeline.checks.SHOWN_BY_POSTURE).

A body whose arm span over its height lies below the population's 1st percentile is flagged by
the population range, unless the T-pose (posture 4), which shows the span fingertip to
fingertip, was fitted with its full weight. The flags are read at a parameter vector made by
hand: the template with its arms shortened along their length.
"""

import pytest
import torch

from torchfit.body.measure import measure_model
from torchfit.body.postures import POSTURES, pose_nominal
from torchfit.camera import camera_centre, project_points, stack_cameras
from torchfit.config import load_config
from torchfit.fit import FitOptions, person_data_from_masks
from torchfit.fit.problem import SilhouetteFit
from torchfit.pipeline.checks import SHOWN_BY_POSTURE, population_ranges
from torchfit.pipeline.stages import _final_flags, _template_ratios
from torchfit.viz.preview import nominal_view
from torchfit.viz.raster import render_silhouette


@pytest.fixture(scope="module")
def masks(model):
    """(6, H, W) the template's exact silhouettes in the nominal postures, and the camera."""
    camera = nominal_view(azimuth_deg=0.0)
    w, h = camera.image_size
    scales = torch.ones(1, model.num_segments, 3, dtype=model.dtype)
    out = []
    for posture in POSTURES:
        _, body = pose_nominal(model, scales, posture, camera_centre(camera.R, camera.t))
        px = project_points(body.vertices, camera.to(dtype=body.vertices.dtype))[0].numpy()
        out.append(torch.from_numpy(render_silhouette(px, model.faces.numpy(), (w, h)) > 127))
    return camera, torch.stack(out)


def _short_arms(model, masks, poses, factor=0.925):
    """The fit over ``poses`` and its start with the arms' length scales at ``factor`` (0.925:
    the span over the height between the hard limit and the 1st percentile)."""
    camera, silhouettes = masks
    person = person_data_from_masks(
        silhouettes[None, [p - 1 for p in poses]], stack_cameras([camera])
    )
    fit = SilhouetteFit(model, person, FitOptions(poses=poses))
    x = fit.initial_params().clone()
    for name in ("scale:upperarm:z", "scale:forearm:z", "scale:hand:z"):
        x[:, fit.layout.names.index(name)] = factor
    return fit, x


def test_the_short_arms_are_below_the_population_range(model, masks):
    fit, x = _short_arms(model, masks, (1, 4))
    scales = model.expand_scales(fit.layout.group_scales(x))
    m = {k: float(v[0]) for k, v in measure_model(model, scales).items()}
    low, _ = population_ranges(_template_ratios(fit))["arm_span_m"]
    assert 0.94 < m["arm_span_m"] / m["height_m"] < low


def test_a_full_weight_t_pose_shows_the_arm_span(model, masks):
    assert SHOWN_BY_POSTURE == {"arm_span_m": 4}
    config = load_config(None)
    fit, x = _short_arms(model, masks, (1, 4))
    flags = _final_flags(fit, x, config, [{}])[0]
    assert not any("arm_span" in f for f in flags), flags
    # the T-pose down-weighted as an outlier: the span is judged by the population again
    note = {4: "pose4 down-weighted: contour rms 9.0 px vs median 1.5"}
    flags = _final_flags(fit, x, config, [note])[0]
    assert any(f.startswith("arm_span / height") and "below the 1st percentile" in f for f in flags)


def test_without_the_t_pose_the_arm_span_is_judged(model, masks):
    fit, x = _short_arms(model, masks, (1, 2))
    flags = _final_flags(fit, x, load_config(None), [{}])[0]
    assert any(f.startswith("arm_span / height") for f in flags), flags


def test_the_hard_limits_hold_whatever_the_t_pose_shows(model, masks):
    fit, x = _short_arms(model, masks, (1, 4), factor=0.85)
    flags = _final_flags(fit, x, load_config(None), [{}])[0]
    assert any(f.startswith("arm_span / height") and "widened" in f for f in flags), flags
