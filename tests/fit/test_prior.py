"""The population prior (ANSUR II) and the known height in the fit.

Checks: the shipped prior loads and its residuals are ``weight * L^-1 (log s - mu)`` computed
from the file directly; the Jacobian of the added entries matches central differences; a known
height pulls the fitted height to it; the prior does not override the images on a subject
whose thigh is at the population's 1st or 99th percentile given the rest of the body.
"""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from central_differences import perturbed_start, residual_differences
from template_subjects import make_template_subject, segment_subjects

from torchfit.body.measure import measure_model
from torchfit.camera import stack_cameras
from torchfit.errors import ConfigError
from torchfit.fit import StageOptions, person_data_from_masks, solve_stage
from torchfit.fit.prior import (
    PRIOR_DIR,
    KnownFacts,
    PriorFit,
    PriorOptions,
    load_prior,
    neutral_height,
)
from torchfit.io.dataset import load_subject
from torchfit.solver import LMOptions

REPO_ROOT = Path(__file__).resolve().parents[2]
#: the prior as the benchmark configuration sets it (its weight chosen on the development set)
BENCHMARK = yaml.safe_load((REPO_ROOT / "configs" / "benchmark.yaml").read_text())["fit"]["prior"]
WEIGHT = float(BENCHMARK["weight"])
ENTRIES = tuple(BENCHMARK.get("entries") or ()) or None


def _problem(model, subjects, facts=None, weight=WEIGHT, tolerance=0.005, entries=None):
    person = person_data_from_masks(
        segment_subjects(subjects), stack_cameras([s.camera for s in subjects])
    )
    options = PriorOptions(weight=weight, height_tolerance_m=tolerance, entries=entries)
    return PriorFit(model, person, prior=load_prior("ansur2"), prior_options=options, facts=facts)


@pytest.fixture(scope="module")
def plain(tmp_path_factory, model):
    root = tmp_path_factory.mktemp("prior_plain")
    truth = make_template_subject(root / "s", model, scale=1.03, seed=5)
    return load_subject(root / "s"), truth


def test_prior_file_residuals_are_the_whitened_log_scales(model, plain):
    doc = json.loads((PRIOR_DIR / "ansur2.json").read_text())
    facts = [KnownFacts(sex="female")]
    fit = _problem(model, [plain[0]], facts, weight=0.7)
    assert fit.prior.entries == tuple(doc["entries"])  # mpeg4_full has every entry
    g = torch.Generator().manual_seed(1)
    x = fit.initial_params()
    x[:, fit.layout.scales] += 0.05 * torch.randn(1, fit.layout.num_scale_params, generator=g)
    ours = fit.prior_residual(x, torch.tensor([0]))[0].numpy()
    comp = doc["components"]["female"]
    chol = np.array(comp["cholesky"])
    template_height = float(
        measure_model(model, torch.ones(1, model.num_segments, 3))["height_m"][0]
    )
    offsets = (doc.get("calibration") or {}).get("offsets", {})
    shift = np.array([offsets.get(e, 0.0) for e in doc["entries"]])
    mu = np.array(comp["mean"]) + shift - math.log(template_height)
    cols = [fit.layout.scale_column(*e.split(":")) for e in doc["entries"]]
    log_s = np.log(x[0, cols].numpy())
    direct = 0.7 * np.linalg.solve(chol, log_s - mu)
    np.testing.assert_allclose(ours, direct, rtol=1e-6, atol=1e-8)
    # and the residual row carries them where the layout says
    r = fit.residual(x)
    np.testing.assert_allclose(r[0, fit.residual_layout.prior].numpy(), direct, rtol=1e-6)


def test_unknown_prior_is_named():
    with pytest.raises(ConfigError, match="unknown prior 'nope'"):
        load_prior("nope")
    with pytest.raises(ConfigError, match="weight"):
        PriorOptions(weight=-1)


def test_added_rows_of_the_jacobian_match_central_differences(model, plain):
    fit = _problem(model, [plain[0]], [KnownFacts(height_m=1.70, sex="male")], weight=1.3)
    x = perturbed_start(fit, 0.02, 0)
    sel = fit.select(x)
    free = torch.arange(fit.layout.num_scale_params)
    jac = fit.jacobian(x, free, sel)
    rl = fit.residual_layout
    rows = list(range(rl.prior.start, rl.facts.stop))
    diffs = residual_differences(fit, x, sel, rows, free)
    for k, p in enumerate(free.tolist()):
        fd = diffs[..., k]
        torch.testing.assert_close(
            jac[:, rows, p], fd, atol=1e-4 * max(float(fd.abs().max()), 1.0), rtol=0
        )
    assert float(jac[0, rl.facts.start].abs().sum()) > 0
    # the Jacobian pass's residual, e_S and e_H included, is residual()'s bit for bit
    jac2, r = fit.jacobian_and_residual(x, free, sel)
    assert torch.equal(r, fit.residual(x, sel)) and torch.equal(jac2, jac)


def test_known_height_pulls_the_fitted_height(model, plain):
    subject, truth = plain
    given = truth["height_m"] * 0.97  # 5 cm off what the images show
    stage, options = StageOptions(name="all"), LMOptions(max_iter=25)
    heights = []
    for facts in ([KnownFacts()], [KnownFacts(height_m=given)]):
        fit = _problem(model, [subject], facts, weight=0.0, tolerance=0.001)
        x, _ = solve_stage(fit, fit.initial_params(), stage, options)
        heights.append(float(neutral_height(model, fit.layout, x)[0]))
    free, known = heights
    # the images alone give the height (one pixel is about 5 mm at 360x288)
    assert abs(free / truth["height_m"] - 1) < 0.02
    assert abs(known - given) < 0.2 * abs(free - given), (free, known, given)


def _percentile_subject(folder, model, entry: str, z: float, prior) -> tuple[dict, float]:
    """The template with one scale entry (``group:axis``) at the prior's z-score ``z`` given the
    other entries (each at the template's own value); returns its truth and the scale the prior
    expects for that entry given the others."""
    k = prior.entries.index(entry)
    cov, mean = prior.covariance["any"].numpy(), prior.mean["any"].numpy()
    ones = torch.ones(1, model.num_segments, 3)
    template_height = float(measure_model(model, ones)["height_m"][0])
    mu = mean - math.log(template_height)
    others = [i for i in range(len(mean)) if i != k]
    gain = np.linalg.solve(cov[np.ix_(others, others)], cov[others, k])
    cond_mean = mu[k] + gain @ (0.0 - mu[others])
    cond_sd = math.sqrt(cov[k, k] - cov[others, k] @ gain)
    group, _, axis = entry.partition(":")
    scales = torch.ones(1, model.num_segments, 3, dtype=model.dtype)
    for s in range(model.num_segments):
        if model.template.scale_groups[int(model.template.segment_group[s])] == group:
            scales[0, s, "xyz".index(axis)] = math.exp(cond_mean + z * cond_sd)
    return make_template_subject(folder, model, seed=7, scales=scales), math.exp(cond_mean)


@pytest.mark.slow
@pytest.mark.parametrize("z", [-2.326, 2.326])  # the 1st and 99th percentiles
def test_prior_does_not_override_clear_image_evidence(tmp_path, model, z):
    """A lower leg at the population's 1st / 99th percentile given the rest of the body (the
    knee height, which the bent-knee postures show): the fit with the prior stays where the
    images alone put it, not where the prior expects it from the rest of the body."""
    prior = load_prior("ansur2")
    if ENTRIES is not None:
        prior = prior.restrict(ENTRIES)
    truth, expected = _percentile_subject(tmp_path / "s", model, "calf:z", z, prior)
    subject = load_subject(tmp_path / "s")
    knee = {}
    for weight in (0.0, WEIGHT):
        fit = _problem(model, [subject], weight=weight, entries=ENTRIES)
        x = fit.initial_params()
        for stage in (
            StageOptions(name="a", scales=("legs", "upper_body"), loss="linear"),
            StageOptions(),
        ):
            x, _ = solve_stage(fit, x, stage, LMOptions(max_iter=30))
        scales = model.expand_scales(fit.layout.group_scales(x))
        knee[weight] = float(measure_model(model, scales)["lower_leg_m"][0])
    # the knee height is the calf plus the ankle height (not scaled here)
    ones = torch.ones(1, model.num_segments, 3)
    ankle = float(measure_model(model, ones)["lower_leg_m"][0]) - _calf_length(model)
    prior_guess = ankle + _calf_length(model) * expected
    true, images, with_prior = truth["lower_leg_m"], knee[0.0], knee[WEIGHT]
    # the images put the knee on the truth's side of what the prior expects ...
    assert (images - prior_guess) * (true - prior_guess) > 0, (images, true, prior_guess)
    # ... and the prior moves it less than a quarter of the way to its expectation (a move
    # away from the expectation, e.g. towards the truth, is not the prior's doing)
    towards = (images - with_prior) * math.copysign(1.0, images - prior_guess)
    assert towards < 0.25 * abs(prior_guess - images), (with_prior, images, true, prior_guess)
    # ... and the two fits agree within a centimetre either way
    assert abs(with_prior - images) < 0.01, (with_prior, images, true)


def _calf_length(model) -> float:
    """The template's knee-to-ankle distance (the calf segment's length), metres."""
    p = model.zeros(1)
    joints = model.joint_positions(model(**p))
    return float((joints["l_knee"] - joints["l_ankle"]).norm())


def test_params_record_the_facts_used(model, plain):
    from torchfit.pipeline.run import facts_record

    facts = [KnownFacts(height_m=1.71, weight_kg=80.0, sex="male")]
    record = facts_record(_problem(model, [plain[0]], facts, weight=0.5), 0)
    assert record["known_facts"] == {"height_m": 1.71, "weight_kg": 80.0, "sex": "male"}
    assert record["facts_used"]["height_m"] == {"value": 1.71, "tolerance_m": 0.005}
    assert record["facts_used"]["sex"] == "prior component 'male'"
    assert "weight_kg" not in record["facts_used"]  # known, recorded, not used by the fit
    assert record["prior"] == {"name": "ansur2", "weight": 0.5, "component": "male"}
    assert record["posture_prior"] is None  # not weighed


def test_shipped_prior_is_what_make_prior_derives(shared_data):
    import importlib.util
    import sys

    sys.path.insert(0, str(REPO_ROOT / "tools"))
    spec = importlib.util.spec_from_file_location(
        "make_prior", REPO_ROOT / "tools" / "make_prior.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    derived = module.derive(shared_data / "ansur2")
    shipped = json.loads((PRIOR_DIR / "ansur2.json").read_text())
    assert derived["entries"] == shipped["entries"]
    assert derived["components"] == shipped["components"]
    assert shipped["components"]["male"]["n"] == 4082
    assert shipped["components"]["female"]["n"] == 1986


def _posture_prior_problem(model, plain, pose_weight, sigma=15.0, joints=None):
    person = person_data_from_masks(segment_subjects([plain[0]]), stack_cameras([plain[0].camera]))
    kw = {} if joints is None else {"pose_joints": joints}
    options = PriorOptions(pose_weight=pose_weight, pose_sigma_deg=sigma, **kw)
    return PriorFit(model, person, prior=None, prior_options=options)


def test_posture_prior_rows_hold_the_free_arm_angles_to_their_nominal(model, plain):
    fit = _posture_prior_problem(model, plain, pose_weight=0.8, sigma=12.0)
    rl, layout = fit.residual_layout, fit.layout
    expected = []  # (column, nominal) of every free shoulder and elbow angle, posture by posture
    for j in fit.poses:
        block = layout.blocks[j]
        for k, name in enumerate(layout.free_joint_names(j)):
            if name.split("_", 1)[1] in PriorOptions().pose_joints:
                dof = block.dofs[k]
                expected.append((block.joints.start + k, float(fit.poser.nominal[j][dof])))
    assert rl.num_pose_prior == len(expected) > 6 * 4  # both sides, every posture
    x = perturbed_start(fit, 0.1, 3)
    got = fit.residual(x)[0, rl.pose_prior]
    direct = torch.tensor(
        [0.8 * (float(x[0, c]) - nom) / math.radians(12.0) for c, nom in expected]
    )
    torch.testing.assert_close(got, direct.to(got))
    # at the template start every held angle is at its nominal: no cost
    assert float(fit.residual(fit.initial_params())[0, rl.pose_prior].abs().max()) == 0.0
    from torchfit.pipeline.run import facts_record

    assert facts_record(fit, 0)["posture_prior"] == {
        "weight": 0.8,
        "sigma_deg": 12.0,
        "joints": list(PriorOptions().pose_joints),
    }
    with pytest.raises(ConfigError, match="pose_joints.*elbow_flex"):
        _posture_prior_problem(model, plain, pose_weight=0.8, joints=("elbow_flex",))
    # a joint without a side goes by its own name
    spine = _posture_prior_problem(model, plain, pose_weight=0.8, joints=("vc4_tilt",))
    assert spine.residual_layout.num_pose_prior == sum(
        "vc4_tilt" in layout.free_joint_names(j) for j in fit.poses
    )
    # one limb's joint alone
    legs = _posture_prior_problem(model, plain, pose_weight=0.8, joints=("knee_flexion",))
    assert legs.residual_layout.num_pose_prior == sum(
        "knee_flexion" in n for j in fit.poses for n in layout.free_joint_names(j)
    )


def test_posture_prior_jacobian_rows_match_central_differences(model, plain):
    fit = _posture_prior_problem(model, plain, pose_weight=1.5)
    x = perturbed_start(fit, 0.05, 4)
    sel = fit.select(x)
    free = fit.stage_indices(["all"], joints=True, root=True)
    jac, r = fit.jacobian_and_residual(x, free, sel)
    assert torch.equal(r, fit.residual(x, sel))
    rows = fit.residual_layout.pose_prior
    diffs = residual_differences(fit, x, sel, rows, free)
    for p in range(free.numel()):
        torch.testing.assert_close(jac[:, rows, p], diffs[..., p], atol=1e-6, rtol=0)
    # the solver's blocks name exactly the columns these rows depend on
    held = [cols for sl, cols in fit.jacobian_blocks(free) if sl == rows]
    assert len(held) == 1
    nonzero = jac[0, rows].abs().sum(0).nonzero().flatten()
    assert sorted(held[0].tolist()) == nonzero.tolist()


def test_no_posture_prior_without_its_weight(model, plain):
    fit = _posture_prior_problem(model, plain, pose_weight=0.0)
    assert fit.residual_layout.num_pose_prior == 0
    assert fit.residual(fit.initial_params()).shape[1] == fit.residual_layout.size
    with pytest.raises(ConfigError, match="pose_weight"):
        PriorOptions(pose_weight=-0.1)
    with pytest.raises(ConfigError, match="pose_sigma_deg"):
        PriorOptions(pose_sigma_deg=0.0)
