"""A subject's fit does not depend on the batch it is fitted in.

Alone, first in one batch and second in another (each batch with its own padding of the
person contours and model contour samples), the same subject must get the same parameters and
measurements, bit for bit: the solver steps each problem on its own rows and forms every sum
over a problem's residuals from its own entries, and the fit's residual and Jacobian sums do
not see the padding.
"""

import pytest
import torch
from template_subjects import make_template_subject

from torchfit.body import BodyModel
from torchfit.body.measure import measure_model
from torchfit.camera import stack_cameras
from torchfit.fit import (
    FitOptions,
    SilhouetteFit,
    StageOptions,
    person_data_from_masks,
    solve_stage,
)
from torchfit.fit.bends import BendFit, BendOptions
from torchfit.fit.prior import PriorFit, PriorOptions, load_prior
from torchfit.fit.stages import SOLVER_DTYPE
from torchfit.image import SegmentationOptions, fit_background, segment
from torchfit.io.dataset import load_subject
from torchfit.io.images import load_frames
from torchfit.solver import LMOptions

# two postures and a few iterations of both stages keep it quick
POSES = (1, 3)
STAGES = (
    StageOptions(name="legs_upper_body", scales=("legs", "upper_body"), max_iter=2),
    StageOptions(name="all", scales=("all",), max_iter=2),
)


@pytest.fixture(scope="module")
def masks(tmp_path_factory, model):
    """Silhouettes (J, H, W) of the fitted postures and camera of three template subjects of
    different sizes."""
    root = tmp_path_factory.mktemp("batch_subjects")
    cfg = SegmentationOptions(gamma=0.05)
    out = {}
    for name, scale, seed in (("a", 0.96, 11), ("b", 1.05, 12), ("c", 0.9, 13)):
        make_template_subject(root / name, model, scale=scale, seed=seed)
        subject = load_subject(root / name)
        background, _ = load_frames(subject.background)
        images, _ = load_frames(subject.poses)
        seg = segment(images, fit_background(background, cfg), cfg)
        out[name] = (seg.masks[[j - 1 for j in POSES], 0], subject.camera)
    return out


def _fit(model, masks, names):
    person = person_data_from_masks(
        torch.stack([masks[n][0] for n in names]), stack_cameras([masks[n][1] for n in names])
    )
    fit = SilhouetteFit(model, person, FitOptions(poses=POSES))
    x = fit.initial_params()
    for stage in STAGES:
        x, _ = solve_stage(fit, x, stage, LMOptions(max_iter=stage.max_iter, min_diag=1.0))
    scales = model.expand_scales(fit.layout.group_scales(x))
    return x, measure_model(model, scales)


def test_a_subject_alone_equals_it_first_and_second_in_other_batches(model, masks):
    alone_x, alone_m = _fit(model, masks, ["a"])
    for names in (["a", "b"], ["c", "a"]):
        x, measures = _fit(model, masks, names)
        i = names.index("a")
        torch.testing.assert_close(x[i : i + 1], alone_x, rtol=0, atol=0)
        for key, value in alone_m.items():
            assert abs(float(measures[key][i]) - float(value[0])) <= 1e-9, key


def test_float32_fit_is_batch_invariant_with_a_float64_solver(masks):
    """A float32 fit (residuals and Jacobian in float32, the solver's state in float64) gives
    a subject the same parameters alone as in a batch, and its solver result is float64."""
    model32 = BodyModel("mpeg4_full", dtype=torch.float32)
    stage = STAGES[0]

    def one_stage(names):
        person = person_data_from_masks(
            torch.stack([masks[n][0] for n in names]),
            stack_cameras([masks[n][1] for n in names]),
            dtype=torch.float32,
        )
        fit = SilhouetteFit(model32, person, FitOptions(poses=POSES))
        options = LMOptions(max_iter=stage.max_iter, min_diag=1.0)
        return solve_stage(fit, fit.initial_params(), stage, options)

    alone_x, alone = one_stage(["a"])
    assert alone_x.dtype == torch.float32
    assert alone.x.dtype == alone.cost.dtype == SOLVER_DTYPE == torch.float64
    assert int(alone.n_iter[0]) == stage.max_iter
    for names in (["a", "b"], ["c", "a"]):
        x, result = one_stage(names)
        i = names.index("a")
        torch.testing.assert_close(x[i : i + 1], alone_x, rtol=0, atol=0)
        torch.testing.assert_close(result.x[i : i + 1], alone.x, rtol=0, atol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_prior_residual_of_a_subject_does_not_depend_on_its_batch(masks, dtype):
    """The prior's whitened residuals of a subject, alone and in a batch of four, are the same
    bits (a batched matrix product rounds one row differently from several)."""
    model = BodyModel("mpeg4_full", dtype=dtype)
    person = person_data_from_masks(
        torch.stack([masks[n][0] for n in "abca"]),
        stack_cameras([masks[n][1] for n in "abca"]),
        dtype=dtype,
    )
    fit = PriorFit(
        model,
        person,
        FitOptions(poses=POSES),
        prior=load_prior("ansur2"),
        prior_options=PriorOptions(weight=0.3),
    )
    g = torch.Generator().manual_seed(0)
    start = fit.initial_params()
    rows = torch.arange(4)
    for _ in range(5):
        x = start * (1 + 0.2 * torch.rand(start.shape, generator=g, dtype=torch.float64).to(dtype))
        batch = fit.prior_residual(x, rows)
        for i in range(4):
            alone = fit.prior_residual(x[i : i + 1], rows[i : i + 1])
            torch.testing.assert_close(alone, batch[i : i + 1], rtol=0, atol=0)


def _person(masks, names, dtype):
    """The person data of the subjects ``names``, in that order."""
    return person_data_from_masks(
        torch.stack([masks[n][0] for n in names]),
        stack_cameras([masks[n][1] for n in names]),
        dtype=dtype,
    )


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_prior_fit_is_batch_invariant(masks, dtype):
    """With the population prior (its whitening product per subject) a subject gets the same
    parameters alone as in a batch, in either dtype."""
    model = BodyModel("mpeg4_full", dtype=dtype)
    prior, weight = load_prior("ansur2"), PriorOptions(weight=0.3)
    stage = STAGES[1]

    def one_stage(names):
        person = _person(masks, names, dtype)
        fit = PriorFit(model, person, FitOptions(poses=POSES), prior=prior, prior_options=weight)
        options = LMOptions(max_iter=stage.max_iter, min_diag=1.0)
        return solve_stage(fit, fit.initial_params(), stage, options)[0]

    alone = one_stage(["a"])
    for names in (["a", "b"], ["c", "a"]):
        i = names.index("a")
        torch.testing.assert_close(one_stage(names)[i : i + 1], alone, rtol=0, atol=0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_bend_mark_fit_is_batch_invariant(masks, dtype):
    """With the knee's mark (its target per subject, its Jacobian by forward mode over the
    batch folded with the tangents) a subject gets the same parameters alone as in a batch."""
    model = BodyModel("mpeg4_full", dtype=dtype)
    stage = STAGES[1]

    def one_stage(names):
        person = _person(masks, names, dtype)
        person.silhouettes = {POSES.index(3): torch.stack([masks[n][0][1] for n in names])}
        fit = BendFit(model, person, FitOptions(poses=POSES), bends=BendOptions(weight=1.0))
        options = LMOptions(max_iter=stage.max_iter, min_diag=1.0)
        x = solve_stage(fit, fit.initial_params(), stage, options)[0]
        marks = fit.select(x)[3].marks
        return x, marks

    alone, alone_marks = one_stage(["a"])
    assert float(alone_marks[0, 0, 2]) == 1.0  # the knee is marked
    for names in (["a", "b"], ["c", "a"]):
        i = names.index("a")
        x, marks = one_stage(names)
        torch.testing.assert_close(x[i : i + 1], alone, rtol=0, atol=0)
        torch.testing.assert_close(marks[i : i + 1], alone_marks, rtol=0, atol=0)
