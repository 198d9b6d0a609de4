"""A posture whose silhouette lost its feet is flagged and, with ``segmentation.floor_retry``,
segmented again (torchfit.pipeline.prepare.reach_floor), on a hand-built scene seen through a
real camera; the judge makes such a subject ``poor_fit`` with that reason."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "image"))
from image_testing import COLOUR_SHADOW, shin_scene  # noqa: E402

from torchfit.camera import Camera, look_at  # noqa: E402
from torchfit.config.schema import SegmentationConfig  # noqa: E402
from torchfit.image import fit_background, segment  # noqa: E402
from torchfit.pipeline.judge import judge  # noqa: E402
from torchfit.pipeline.prepare import floor_reach, reach_floor  # noqa: E402
from torchfit.pipeline.stages import StageRecord  # noqa: E402
from torchfit.status import SubjectStatus  # noqa: E402

H, W = 90, 100


def _camera() -> Camera:
    # 1 m above the floor, looking horizontally at the floor mark from 1.56 m: image row v
    # sees the floor 100 / (v - 20) m from the camera, so the shoes' soles (row 84) stand on
    # the mark and the bottom of the thighs (row 54) sees the floor 1.3 m behind it
    R, t = look_at(torch.tensor([[1.5625, 0.0, 1.0]]), torch.tensor([[0.0, 0.0, 1.0]]))
    K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 100.0, 20.0], [0.0, 0.0, 1.0]])
    return Camera(K=K, dist=torch.zeros(5), R=R[0], t=t[0], image_size=(W, H)).to(
        dtype=torch.float64
    )


def _options(**kw) -> SegmentationConfig:
    # colour alone decides the shadow test (as in test_shadow.py's bridge scene)
    return SegmentationConfig(**COLOUR_SHADOW, **kw)


def _segmented(shin_shade: float):
    """The scene's image, background model, first silhouette and shadow pixels (1, H, W),
    and the true person (H, W)."""
    # test_shadow.py's bridge scene without its cast shadow, moved to the camera's centre
    scene = shin_scene(left=35, shin_shade=shin_shade, cast=False)
    frames, image = scene["frames"], scene["image"]
    person = scene["body"] | scene["shins"] | scene["shoes"]
    options = _options()
    model = fit_background(frames, options)
    first = segment(image, model, options)
    return image, model, first.masks[:, 0], first.shadow[:, 0], person


def test_a_silhouette_cut_off_at_the_knees_is_flagged_and_on_request_segmented_again():
    image, model, masks, shadow, person = _segmented(shin_shade=0.8)
    camera = _camera()
    # the shins passed as shadow and the shoes were dropped: the lowest pixel sees the floor
    # about 1.3 m behind the mark
    (reach,) = floor_reach(masks, camera)
    assert 1.1 < reach < 1.6
    # by default: flagged, the silhouette kept
    got, _, notes, flags = reach_floor(image, model, masks, shadow, camera, _options())
    assert torch.equal(got, masks) and notes == []
    assert len(flags) == 1 and flags[0].startswith("pose1: the silhouette does not reach the floor")
    assert flags[0].endswith("(segmentation.floor_retry: true segments such a posture once more)")
    # with floor_retry: segmented again, kept, no flag
    retry = _options(floor_retry=True)
    got, got_shadow, notes, flags = reach_floor(image, model, masks, shadow, camera, retry)
    assert float((got[0] == person).float().mean()) > 0.98
    assert not bool(got_shadow[0][person].any())
    assert floor_reach(got, camera)[0] < 0.1
    assert flags == [] and len(notes) == 1 and "; segmented again (" in notes[0]
    # nothing to segment again without the background model (own masks, chroma key)
    no_model = reach_floor(image, None, masks, shadow, camera, retry)
    assert no_model[2] == [] and no_model[3][0].startswith("pose1: the silhouette does not reach")
    assert "floor_retry" not in no_model[3][0]  # nothing it could do there
    # not checked at all
    off = _options(floor_reach_m=None, floor_retry=True)
    assert reach_floor(image, model, masks, shadow, camera, off)[2:] == ([], [])


def test_the_judge_puts_a_lost_floor_first():
    records = [StageRecord("all", "XTOL", "converged", 1.0, 10)]
    quality = {"pose1": {"e_P_rms_px": 30.0, "e_M_px": 30.0}}
    flag = "pose1: the silhouette does not reach the floor (...)"
    status, message = judge(records, quality, 15.0, [flag])
    assert status == SubjectStatus.POOR_FIT and message == flag
    assert judge(records, quality, 15.0)[1].startswith("model contour 30.0 px")
    fine = {"pose1": {"e_P_rms_px": 1.0, "e_M_px": 1.0}}
    assert judge(records, fine, 15.0) == (SubjectStatus.OK, "converged")


def test_a_silhouette_standing_on_the_floor_is_left_alone():
    image, model, masks, shadow, _ = _segmented(shin_shade=0.3)
    options = _options()
    assert floor_reach(masks, _camera())[0] < 0.1
    got, _, notes, flags = reach_floor(image, model, masks, shadow, _camera(), options)
    assert notes == [] and flags == [] and torch.equal(got, masks)
    assert floor_reach(torch.zeros(1, H, W, dtype=torch.bool), _camera()) == [float("inf")]
