"""Tests of torchfit.camera.

The reference pixels in ``tests/data/camera_reference.npz`` were computed once with
``cv2.projectPoints`` by ``tools/make_camera_reference.py``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchfit.camera import (
    Camera,
    camera_centre,
    look_at,
    project_points,
    stack_cameras,
    world_to_camera,
)
from torchfit.errors import CameraError, ShapeError
from torchfit.io.camera import (
    camera_from_dict,
    camera_to_dict,
    load_camera,
    load_stereo_cameras,
    save_camera,
    save_stereo_cameras,
)

REFERENCE = Path(__file__).resolve().parent / "data" / "camera_reference.npz"


def _reference_camera() -> tuple[Camera, torch.Tensor, torch.Tensor]:
    ref = np.load(REFERENCE)
    cam = Camera(
        K=torch.from_numpy(ref["K"]),
        dist=torch.from_numpy(ref["dist"]),
        R=torch.from_numpy(ref["R"]),
        t=torch.from_numpy(ref["t"]),
        image_size=(720, 576),
    )
    return cam, torch.from_numpy(ref["points"]), torch.from_numpy(ref["pixels"])


def _simple_camera(dtype=torch.float64) -> Camera:
    R, t = look_at(torch.tensor([[3.0, -1.0, 1.3]]), torch.tensor([[0.0, 0.0, 1.0]]))
    return Camera(
        K=torch.tensor([[900.0, 0.0, 359.5], [0.0, 910.0, 287.5], [0.0, 0.0, 1.0]]),
        dist=torch.tensor([0.1, -0.05, 0.002, -0.001, 0.01]),
        R=R[0],
        t=t[0],
        image_size=(720, 576),
    ).to(dtype=dtype)


def test_project_points_matches_opencv_reference():
    cam, points, pixels = _reference_camera()
    out, depth = project_points(points, cam, return_depth=True)
    torch.testing.assert_close(out, pixels, rtol=0, atol=1e-7)
    assert bool((depth > 0).all())


def test_project_points_broadcasts_one_camera():
    cam, points, pixels = _reference_camera()
    one = cam[2]
    out = project_points(points[2:3].expand(4, -1, -1), one)
    torch.testing.assert_close(out, pixels[2:3].expand(4, -1, -1), rtol=0, atol=1e-7)


def test_project_points_float32():
    cam, points, pixels = _reference_camera()
    out = project_points(points.float(), cam.to(dtype=torch.float32))
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.double(), pixels, rtol=0, atol=2e-3)


def test_gradcheck_points_and_camera():
    cam = _simple_camera()
    points = (torch.rand(1, 7, 3, dtype=torch.float64) - 0.5) + torch.tensor([0.0, 0.0, 1.0])
    K = cam.K.clone().requires_grad_(True)
    dist = cam.dist.clone().requires_grad_(True)
    t = cam.t.clone().requires_grad_(True)
    points.requires_grad_(True)

    def f(p, K, dist, t):
        c = Camera(K=K, dist=dist, R=cam.R, t=t, image_size=cam.image_size)
        return project_points(p, c)

    assert torch.autograd.gradcheck(f, (points, K, dist, t))


def test_look_at_facing_and_centre():
    centre = torch.tensor([[3.0, 2.0, 1.4], [-2.0, 3.5, 1.2]], dtype=torch.float64)
    target = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.2]], dtype=torch.float64)
    R, t = look_at(centre, target)
    eye = torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(2, dtype=torch.float64))
    torch.testing.assert_close(camera_centre(R, t), centre)
    cam = Camera(
        K=torch.tensor([[800.0, 0, 360], [0, 800.0, 288], [0, 0, 1]], dtype=torch.float64).expand(
            2, 3, 3
        ),
        dist=torch.zeros(2, 5, dtype=torch.float64),
        R=R,
        t=t,
        image_size=(720, 576),
    )
    # the target projects to the principal point; a point above it projects higher (v smaller)
    pts = torch.stack([target, target + torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64)], 1)
    px = project_points(pts, cam)
    torch.testing.assert_close(px[:, 0], torch.tensor([[360.0, 288.0]] * 2, dtype=torch.float64))
    assert bool((px[:, 1, 1] < px[:, 0, 1]).all())
    torch.testing.assert_close(cam.centre, centre)


def test_look_at_errors():
    with pytest.raises(CameraError, match="coincide"):
        look_at(torch.ones(1, 3), torch.ones(1, 3))
    with pytest.raises(CameraError, match="parallel"):
        look_at(torch.tensor([[0.0, 0.0, 3.0]]), torch.zeros(1, 3))


def test_world_to_camera_and_shapes():
    cam = _simple_camera()
    pts = torch.randn(2, 5, 3, dtype=torch.float64)
    cam_pts = world_to_camera(pts, cam)
    expected = torch.einsum("ij,bnj->bni", cam.R[0], pts) + cam.t[0]
    torch.testing.assert_close(cam_pts, expected)
    with pytest.raises(ShapeError, match=r"points: expected shape \(B, N, 3\), got \(5, 3\)"):
        project_points(pts[0], cam)
    with pytest.raises(ShapeError, match="differ from the camera's torch.float64"):
        project_points(pts.float(), cam)
    with pytest.raises(ShapeError, match="batch size 3"):
        project_points(pts, stack_cameras([cam, cam, cam]))
    with pytest.raises(ShapeError, match=r"dist: expected shape \(1, 5\), got \(1, 4\)"):
        Camera(K=cam.K, dist=torch.zeros(1, 4), R=cam.R, t=cam.t, image_size=(720, 576))


def test_to_and_indexing():
    cam = stack_cameras([_simple_camera(), _simple_camera()])
    assert cam.batch_size == 2
    c32 = cam.to(dtype=torch.float32)
    assert c32.K.dtype == c32.R.dtype == c32.t.dtype == c32.dist.dtype == torch.float32
    assert cam[1].batch_size == 1 and cam[-1].batch_size == 1
    assert cam[0].expand(3).batch_size == 3


def test_yaml_round_trip(tmp_path):
    cam = _simple_camera()
    path = tmp_path / "camera.yaml"
    save_camera(cam, path)
    back = load_camera(path)
    assert back.image_size == (720, 576)
    for name in ("K", "dist", "R", "t"):
        torch.testing.assert_close(getattr(back, name), getattr(cam, name), rtol=0, atol=0)
    save_stereo_cameras(cam, back, tmp_path / "cameras.yaml")
    left, right = load_stereo_cameras(tmp_path / "cameras.yaml")
    torch.testing.assert_close(left.R, right.R)


def _good_dict() -> dict:
    return camera_to_dict(_simple_camera())


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda d: d.pop("K"), "missing key 'K'"),
        (lambda d: d.update(extra=1), "unknown key 'extra'"),
        (lambda d: d.update(image_size=[720]), "key 'image_size' expects"),
        (lambda d: d.update(image_size=[720.0, 576]), "key 'image_size' expects"),
        (lambda d: d.update(dist=[0.0, 0.0, 0.0, 0.0]), r"key 'dist' expects a 5 list"),
        (lambda d: d.update(K=[[900, 1, 300], [5, 900, 200], [0, 0, 1]]), "upper triangular"),
        (lambda d: d.update(K=[[-900, 0, 300], [0, 900, 200], [0, 0, 1]]), "positive focal"),
        (lambda d: d.update(R=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "det = -1"),
        (lambda d: d.update(R=[[1.1, 0, 0], [0, 1, 0], [0, 0, 1]]), "orthonormal"),
        (lambda d: d.update(t=[0, "a", 1]), "key 't' expects"),
        (lambda d: d.update(t=[0, math.nan, 1]), "key 't' contains non-finite"),
    ],
)
def test_camera_errors_name_file_and_key(tmp_path, edit, message):
    data = _good_dict()
    edit(data)
    with pytest.raises(CameraError, match=message) as info:
        camera_from_dict(data, "subj/camera.yaml")
    assert "subj/camera.yaml" in str(info.value)


def test_load_camera_file_errors(tmp_path):
    with pytest.raises(CameraError, match="camera file not found"):
        load_camera(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("K: [1, 2\n")
    with pytest.raises(CameraError, match="invalid YAML"):
        load_camera(bad)
    bad.write_text("left: {}\n")
    with pytest.raises(CameraError, match="'left' and 'right'"):
        load_stereo_cameras(bad)
    with pytest.raises(CameraError, match=r"\[left\]: missing key 'image_size'"):
        (tmp_path / "s.yaml").write_text("left: {}\nright: {}\n")
        load_stereo_cameras(tmp_path / "s.yaml")


def test_projection_jacobian_matches_central_differences():
    from torchfit.camera import Camera, project_points, projection_jacobian
    from torchfit.viz.preview import nominal_view

    base = nominal_view(distance=3.5, azimuth_deg=30.0, focal=450.0, image_size=(320, 256))
    k = base.K.clone()
    k[:, 0, 1] = 0.7  # a skew, so that every intrinsic term counts
    dist = torch.tensor([[0.12, -0.05, 0.002, -0.003, 0.01]], dtype=torch.float64)
    cam = Camera(K=k, dist=dist, R=base.R, t=base.t, image_size=base.image_size)[[0, 0]]
    g = torch.Generator().manual_seed(0)
    points = 0.5 * torch.randn(2, 60, 3, generator=g, dtype=torch.float64)
    pixels, jac = projection_jacobian(points, cam)
    torch.testing.assert_close(pixels, project_points(points, cam), atol=1e-9, rtol=0)
    h = 1e-6
    cols = []
    for c in range(3):
        step = torch.zeros_like(points)
        step[..., c] = h
        cols.append(
            (project_points(points + step, cam) - project_points(points - step, cam)) / (2 * h)
        )
    central = torch.stack(cols, -1)
    assert central.abs().max() > 50  # pixels per metre: the test has something to check
    torch.testing.assert_close(jac, central, atol=1e-6, rtol=1e-7)


def test_undistort_inverts_distort():
    from torchfit.camera import distort_normalized, undistort_normalized

    xy = torch.rand(2, 50, 2, dtype=torch.float64) * 0.8 - 0.4
    dist = _simple_camera().dist
    back = undistort_normalized(distort_normalized(xy, dist), dist)
    assert torch.allclose(back, xy, atol=1e-10)


def test_floor_points_invert_the_projection_of_floor_points():
    from torchfit.camera import floor_points

    cam = _simple_camera()  # with distortion
    gen = torch.Generator().manual_seed(1)
    floor = torch.zeros(1, 40, 3, dtype=torch.float64)
    floor[..., :2] = torch.rand(1, 40, 2, generator=gen, dtype=torch.float64) * 2 - 1
    pixels = project_points(floor, cam)
    assert torch.allclose(floor_points(pixels, cam), floor, atol=1e-8)
    # a pixel above the horizon sees no floor
    above = project_points(torch.tensor([[[-5.0, 2.0, 3.0]]], dtype=torch.float64), cam)
    assert bool(torch.isnan(floor_points(above, cam)).all())


def test_ray_directions_pass_through_what_the_pixels_see():
    from torchfit.camera import ray_directions, world_to_camera

    cam = _simple_camera()  # with distortion
    gen = torch.Generator().manual_seed(2)
    points = torch.rand(1, 30, 3, generator=gen, dtype=torch.float64) * 1.6 - 0.8
    points[..., 2] += 1.0
    rays = ray_directions(project_points(points, cam), cam)
    depth = world_to_camera(points, cam)[..., 2:]
    centre = camera_centre(cam.R, cam.t)[:, None, :]
    # the camera centre plus depth times the ray is the point itself (unit optical-axis depth)
    torch.testing.assert_close(centre + depth * rays, points, atol=1e-6, rtol=0)
    # undoing the distortion matters here: the rays of the pinhole alone miss by millimetres
    pinhole = Camera(cam.K, torch.zeros_like(cam.dist), cam.R, cam.t, cam.image_size)
    pinhole_rays = ray_directions(project_points(points, cam), pinhole)
    off = (centre + depth * pinhole_rays - points).norm(dim=-1)
    assert float(off.max()) > 1e-3
