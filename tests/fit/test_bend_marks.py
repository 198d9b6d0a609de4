"""The bent-joint marks (torchfit.fit.bends): the knee of posture 3 placed by its limbs.

The person is the template itself with a different thigh / shank split, drawn as exact
silhouettes by the fit's own rasteriser in the six nominal postures, so the true knee is
known: the mark must find it, its Jacobian rows must match central differences, and the fit
must move the knee towards it where the contour terms alone keep the template's split.
"""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from central_differences import perturbed_start, residual_differences

from torchfit.body.measure import measure_model
from torchfit.body.postures import POSTURES, pose_nominal
from torchfit.camera import camera_centre, project_points, stack_cameras
from torchfit.config import load_config, replace_keys
from torchfit.errors import ConfigError
from torchfit.fit import FitOptions, person_data_from_masks
from torchfit.fit.bends import SHOWN_BY, BendFit, BendOptions
from torchfit.pipeline.prepare import person_data
from torchfit.pipeline.run import build_problem
from torchfit.pipeline.stages import run_stages
from torchfit.viz.preview import nominal_view
from torchfit.viz.raster import render_silhouette

BENCHMARK = Path(__file__).resolve().parents[2] / "configs" / "benchmark.yaml"
SPLIT = {"thigh": 0.93, "calf": 1.05}  # thigh 7 % shorter, shank 5 % longer than the template


def _scales(model, split: dict[str, float]) -> torch.Tensor:
    scales = torch.ones(1, model.num_segments, 3, dtype=model.dtype)
    for name, value in split.items():
        for side in "lr":
            scales[0, model.template.segments.index(f"{side}_{name}"), 2] = value
    return scales


@pytest.fixture(scope="module")
def scene(model):
    """(camera, (6, H, W) exact silhouettes, posture 3's true joint pixels, true measures)."""
    camera = nominal_view(azimuth_deg=20.0)
    scales = _scales(model, SPLIT)
    w, h = camera.image_size
    masks, knee = [], None
    for posture in POSTURES:
        _, out = pose_nominal(model, scales, posture, camera_centre(camera.R, camera.t))
        cam = camera.to(dtype=out.vertices.dtype)
        px = project_points(out.vertices, cam)[0].numpy()
        masks.append(torch.from_numpy(render_silhouette(px, model.faces.numpy(), (w, h)) > 127))
        if posture.index == 3:
            joints = model.joint_positions(out)
            knee = project_points(joints["l_knee"][:, None], cam)[0, 0]
    truth = {k: float(v[0]) for k, v in measure_model(model, scales).items()}
    return camera, torch.stack(masks), knee, truth


def _side_knee_fit(model, scene, weight=1.0):
    camera, masks, _, _ = scene
    person = person_data_from_masks(masks[None, [2]], stack_cameras([camera]))
    person.silhouettes = {0: masks[None, 2]}
    return BendFit(model, person, FitOptions(poses=(3,)), bends=BendOptions(weight=weight))


def test_the_mark_is_the_persons_knee(model, scene):
    fit = _side_knee_fit(model, scene)
    x = fit.initial_params()  # the template's split: its knee is elsewhere
    sel = fit.select(x)
    target = sel[3].marks[0, 0]
    assert float(target[2]) == 1.0  # found
    model_knee = fit.joint_pixels(x, 3, torch.tensor([0]))[0, 0, 1]
    true_knee = scene[2].to(target)
    assert float((model_knee - true_knee).norm()) > 3.0  # the start is off ...
    assert float((target[:2] - true_knee).norm()) < 1.0  # ... the mark is on the person's knee
    # e_J is weight * (model knee - mark), in the layout's columns
    r = fit.residual(x, sel)[0, fit.residual_layout.marks]
    torch.testing.assert_close(r, model_knee - target[:2])


def test_mark_rows_of_the_jacobian_match_central_differences(model, scene):
    fit = _side_knee_fit(model, scene, weight=0.7)
    x = perturbed_start(fit, 0.01, 3)
    sel = fit.select(x)
    assert float(sel[3].marks[0, 0, 2]) == 1.0
    free = torch.arange(fit.num_params)
    jac, r = fit.jacobian_and_residual(x, free, sel)
    rows = fit.residual_layout.marks
    fd = residual_differences(fit, x, sel, rows, range(fit.num_params))[0]
    assert float(fd.abs().max()) > 10.0  # the scales and angles do move the knee
    torch.testing.assert_close(jac[0, rows], fd, atol=1e-4 * float(fd.abs().max()), rtol=0)
    assert torch.equal(r, fit.residual(x, sel))
    # the solver's sparsity covers every non-zero column of the rows
    blocks = dict((s.start, cols) for s, cols in fit.jacobian_blocks(free))
    nonzero = set(jac[0, rows].abs().sum(0).nonzero().flatten().tolist())
    assert nonzero <= set(blocks[rows.start].tolist())


def test_the_fit_follows_the_knee_the_limbs_show(model, scene):
    """From the template's start the contour terms alone keep most of the template's split
    (benchmarks/knee_split.py); with the mark the thigh comes markedly closer (15.5 → 9.0
    mm here). The model's knee then sits on the mark; what is left is the hip's height."""
    camera, masks, _, truth = scene
    errors = {}
    for weight in (0.0, 1.0):
        config = replace_keys(load_config(BENCHMARK), {"fit.bends.weight": weight})
        person = person_data(
            config, masks[None], torch.zeros_like(masks[None]), stack_cameras([camera]), model.dtype
        )
        fit = build_problem(model, person, config, [{}])
        assert isinstance(fit, BendFit) == (weight > 0)
        x, _ = run_stages(fit, fit.initial_params(), config, ["body"])
        fitted = measure_model(model, model.expand_scales(fit.layout.group_scales(x)))
        errors[weight] = abs(float(fitted["thigh_m"][0]) - truth["thigh_m"])
    assert errors[1.0] < 0.7 * errors[0.0], errors


def test_shown_measurements_need_a_found_and_fitted_mark(model, scene):
    fit = _side_knee_fit(model, scene)
    near = {"pose3": {"l_knee": {"target_px": [1, 2], "model_px": [1, 3], "offset_px": 1.0}}}
    far = {"pose3": {"l_knee": {"target_px": [1, 2], "model_px": [1, 9], "offset_px": 7.0}}}
    lost = {"pose3": {"l_knee": {"target_px": None, "model_px": [1, 9], "offset_px": None}}}
    assert fit.shown(near) == set(SHOWN_BY["knee"]) == {"thigh_m", "lower_leg_m"}
    assert fit.shown(far) == set() and fit.shown(lost) == set()
    # the record params.json gets
    x = fit.initial_params()
    record = fit.mark_record(x, fit.select(x), 0)
    knee = record["pose3"]["l_knee"]
    assert knee["target_px"] is not None and knee["offset_px"] > 3.0
    json.dumps(record)


def test_bad_mark_options_are_named(model, scene):
    with pytest.raises(ConfigError, match=r"fit.bends.joints: expected 'pose<1-6>:"):
        BendOptions(joints=("pose3:l_hip,l_knee",))
    with pytest.raises(ConfigError, match="fit.bends.weight"):
        BendOptions(weight=-1.0)
    with pytest.raises(ConfigError, match=r"fit.bends.max_width_ratio: expected a number > 1"):
        BendOptions(max_width_ratio=0.8)
    camera, masks, _, _ = scene
    person = person_data_from_masks(masks[None, [2]], stack_cameras([camera]))
    person.silhouettes = {0: masks[None, 2]}
    with pytest.raises(ConfigError, match=r"\['l_kneecap'\] not joints of template"):
        BendFit(
            model,
            person,
            FitOptions(poses=(3,)),
            bends=BendOptions(weight=1.0, joints=("pose3:l_hip,l_kneecap,l_ankle",)),
        )


def test_a_silhouette_without_limbs_leaves_the_mark_unset(model, scene):
    camera, masks, _, _ = scene
    blob = torch.zeros_like(masks[2])
    blob[100:300, 300:340] = True  # a post: no thigh, no shank
    person = person_data_from_masks(blob[None, None], stack_cameras([camera]))
    person.silhouettes = {0: blob[None]}
    fit = BendFit(model, person, FitOptions(poses=(3,)), bends=BendOptions(weight=1.0))
    x = fit.initial_params()
    sel = fit.select(x)
    assert float(sel[3].marks[0, 0, 2]) == 0.0
    assert not np.any(fit.residual(x, sel)[0, fit.residual_layout.marks].numpy())
