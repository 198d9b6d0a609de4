"""Calibrated cameras: OpenCV pinhole + distortion projection, look-at (file I/O is in
:mod:`torchfit.io.camera`).

Conventions (design.md section 2):

- ``R``, ``t`` map world to camera: ``x_cam = R @ x_world + t``; the camera looks along its
  +z axis, x to the right and y down in the image.
- Pixel ``(0, 0)`` is the centre of the top-left pixel; u grows to the right, v down.
- Distortion is OpenCV's five-coefficient model ``(k1, k2, p1, p2, k3)``: with normalised
  coordinates ``x = X / Z``, ``y = Y / Z`` and ``r² = x² + y²``::

      x' = x (1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2 x²)
      y' = y (1 + k1 r² + k2 r⁴ + k3 r⁶) + p1 (r² + 2 y²) + 2 p2 x y
      (u, v, 1) = K (x', y', 1)

  which is what ``cv2.projectPoints`` computes (OpenCV ignores the skew ``K[0, 1]``; it is
  applied here, and ``camera.yaml`` files written by calibration tools have it at zero).
- Lengths in metres, image sizes as ``(width, height)`` in pixels.

A :class:`Camera` holds a batch of ``B`` cameras that share one image size; tensors are batch
first. Everything here is differentiable with respect to points and camera parameters.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.autograd.forward_ad as fwad

from torchfit.errors import CameraError, ShapeError, check_shape

__all__ = [
    "Camera",
    "stack_cameras",
    "world_to_camera",
    "distort_normalized",
    "undistort_normalized",
    "project_points",
    "undistort_pixels",
    "ray_directions",
    "floor_points",
    "projection_jacobian",
    "project_with_jacobian",
    "look_at",
    "camera_centre",
    "ROTATION_TOLERANCE",
]

#: Largest allowed ``max |RᵀR - I|`` and ``|det R - 1|`` for a rotation read from a file.
ROTATION_TOLERANCE = 1e-4


@dataclass
class Camera:
    """A batch of ``B`` calibrated pinhole cameras with OpenCV distortion.

    Attributes:
        K: (B, 3, 3) intrinsic matrix, pixels.
        dist: (B, 5) distortion ``(k1, k2, p1, p2, k3)``.
        R: (B, 3, 3) world -> camera rotation.
        t: (B, 3) world -> camera translation, metres.
        image_size: ``(width, height)`` in pixels, shared by the batch.

    Unbatched tensors (``K`` (3, 3), ``dist`` (5,), ``R`` (3, 3), ``t`` (3,)) are accepted and
    get a batch dimension of 1.

    Raises:
        ShapeError: a tensor has the wrong shape or the batch sizes differ.
        CameraError: ``image_size`` is not two positive integers.
    """

    K: torch.Tensor
    dist: torch.Tensor
    R: torch.Tensor
    t: torch.Tensor
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        for name, unbatched in (("K", 2), ("dist", 1), ("R", 2), ("t", 1)):
            value = getattr(self, name)
            if not isinstance(value, torch.Tensor):
                raise ShapeError(f"{name}: expected a torch.Tensor, got {type(value).__name__}")
            if value.dim() == unbatched:
                setattr(self, name, value.unsqueeze(0))
        batch = self.K.shape[0] if self.K.dim() == 3 else None
        check_shape("K", self.K, ("B", 3, 3))
        check_shape("dist", self.dist, (batch, 5))
        check_shape("R", self.R, (batch, 3, 3))
        check_shape("t", self.t, (batch, 3))
        size = tuple(self.image_size)
        if len(size) != 2 or any(
            isinstance(s, bool) or not isinstance(s, int) or s <= 0 for s in size
        ):
            raise CameraError(
                f"image_size: expected (width, height) as two positive integers, "
                f"got {self.image_size!r}"
            )
        self.image_size = (int(size[0]), int(size[1]))

    @property
    def batch_size(self) -> int:
        """The number of cameras ``B``."""
        return self.K.shape[0]

    @property
    def centre(self) -> torch.Tensor:
        """(B, 3) camera centres in world coordinates, metres."""
        return camera_centre(self.R, self.t)

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Camera:
        """A copy with every tensor moved to ``device`` and/or cast to ``dtype``."""
        return dataclasses.replace(
            self,
            K=self.K.to(device=device, dtype=dtype),
            dist=self.dist.to(device=device, dtype=dtype),
            R=self.R.to(device=device, dtype=dtype),
            t=self.t.to(device=device, dtype=dtype),
        )

    def __getitem__(self, index: int | slice | torch.Tensor | Sequence[int]) -> Camera:
        """The sub-batch ``index``: an int (keeps a batch dimension of 1), a slice, or the
        row indices (N,) to gather (repeats allowed)."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        elif not isinstance(index, slice):
            index = torch.as_tensor(index, dtype=torch.long, device=self.K.device)
        return dataclasses.replace(
            self, K=self.K[index], dist=self.dist[index], R=self.R[index], t=self.t[index]
        )

    def expand(self, batch_size: int) -> Camera:
        """Repeat a single camera (B = 1) ``batch_size`` times."""
        if self.batch_size != 1:
            raise ShapeError(f"expand: expected a camera batch of 1, got {self.batch_size}")
        return dataclasses.replace(
            self,
            K=self.K.expand(batch_size, 3, 3),
            dist=self.dist.expand(batch_size, 5),
            R=self.R.expand(batch_size, 3, 3),
            t=self.t.expand(batch_size, 3),
        )


def stack_cameras(cameras: Sequence[Camera]) -> Camera:
    """Concatenate cameras along the batch dimension.

    Raises:
        CameraError: the list is empty or the image sizes differ.
    """
    if not cameras:
        raise CameraError("cameras: expected at least one camera, got an empty list")
    sizes = {c.image_size for c in cameras}
    if len(sizes) != 1:
        raise CameraError(f"cameras: all image sizes must be equal, got {sorted(sizes)}")
    return Camera(
        K=torch.cat([c.K for c in cameras]),
        dist=torch.cat([c.dist for c in cameras]),
        R=torch.cat([c.R for c in cameras]),
        t=torch.cat([c.t for c in cameras]),
        image_size=cameras[0].image_size,
    )


# --------------------------------------------------------------------------------------------
# Geometry


def camera_centre(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Camera centre ``C = -Rᵀ t`` in world coordinates.

    Args:
        R: (B, 3, 3) world -> camera rotation.
        t: (B, 3) world -> camera translation.

    Returns:
        (B, 3) centres, metres.
    """
    check_shape("R", R, ("B", 3, 3))
    check_shape("t", t, (R.shape[0], 3))
    return -(R.transpose(1, 2) @ t.unsqueeze(-1)).squeeze(-1)


def look_at(
    centre: torch.Tensor,
    target: torch.Tensor,
    up: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation and translation of a camera at ``centre`` looking at ``target``.

    The camera's +z axis points at the target, its +x axis is horizontal (perpendicular to
    ``up``) and its +y axis points down in the image (``up`` projects upwards).

    Args:
        centre: (B, 3) camera centres, world frame, metres.
        target: (B, 3) points looked at, world frame.
        up: (3,) or (B, 3) world up direction; default ``+z``.

    Returns:
        ``(R, t)``: (B, 3, 3) world -> camera rotations and (B, 3) translations.

    Raises:
        CameraError: ``centre`` equals ``target`` or the viewing direction is parallel to up.
    """
    check_shape("centre", centre, ("B", 3))
    check_shape("target", target, (centre.shape[0], 3))
    if up is None:
        up = torch.tensor([0.0, 0.0, 1.0], dtype=centre.dtype, device=centre.device)
    up = up.to(centre).expand_as(centre)
    forward = target - centre
    norm = torch.linalg.vector_norm(forward, dim=-1, keepdim=True)
    if bool((norm < 1e-9).any()):
        raise CameraError("look_at: centre and target coincide")
    z = forward / norm
    x = torch.linalg.cross(z, up)
    xnorm = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    if bool((xnorm < 1e-9).any()):
        raise CameraError("look_at: the viewing direction is parallel to the up vector")
    x = x / xnorm
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z], dim=1)
    t = -(R @ centre.unsqueeze(-1)).squeeze(-1)
    return R, t


def _is_dual(tensor: torch.Tensor) -> bool:
    return fwad.unpack_dual(tensor).tangent is not None


def _lift(constant: torch.Tensor, dual: bool) -> torch.Tensor:
    """``constant`` as a dual tensor with zero tangent when ``dual`` (an operation between a
    forward-mode dual and a plain tensor takes a slow path; see :mod:`torchfit._dual`)."""
    if not dual or _is_dual(constant):
        return constant
    constant = constant.contiguous()
    return fwad.make_dual(constant, torch.zeros_like(constant))


def world_to_camera(points: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Camera-frame coordinates ``R x + t``.

    Args:
        points: (B, N, 3) world points, metres.
        camera: a batch of B cameras (or 1, broadcast).

    Returns:
        (B, N, 3) camera-frame points; the last coordinate is the depth along the optical axis.
    """
    check_shape("points", points, ("B", "N", 3))
    if camera.batch_size not in (1, points.shape[0]):
        raise ShapeError(
            f"camera: batch size {camera.batch_size} does not match points batch "
            f"{points.shape[0]} (expected 1 or {points.shape[0]})"
        )
    if points.dtype != camera.R.dtype or points.device != camera.R.device:
        raise ShapeError(
            f"points: dtype/device {points.dtype}/{points.device} differ from the camera's "
            f"{camera.R.dtype}/{camera.R.device} (use camera.to(device, dtype))"
        )
    # Broadcast multiply-adds, not a batched matmul: on forward-mode dual points a 3x3 matmul
    # takes a slow decomposition; the constants are lifted to duals for the same reason
    # (:mod:`torchfit._dual`). Same sums in the same order as the matmul.
    dual = _is_dual(points)
    rt = _lift(camera.R.transpose(1, 2), dual).unsqueeze(1)  # rt[:, :, k]: column k of R
    t = _lift(camera.t, dual)
    x, y, z = points[..., 0:1], points[..., 1:2], points[..., 2:3]
    return x * rt[:, :, 0] + y * rt[:, :, 1] + z * rt[:, :, 2] + t.unsqueeze(1)


def distort_normalized(xy: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """Apply OpenCV's radial + tangential distortion to normalised image coordinates.

    Args:
        xy: (B, N, 2) undistorted normalised coordinates ``(X/Z, Y/Z)``.
        dist: (B, 5) ``(k1, k2, p1, p2, k3)`` (B may be 1, broadcast).

    Returns:
        (B, N, 2) distorted normalised coordinates.
    """
    check_shape("xy", xy, ("B", "N", 2))
    check_shape("dist", dist, (None, 5))
    dist = _lift(dist, _is_dual(xy))
    k1, k2, p1, p2, k3 = (dist[:, i : i + 1] for i in range(5))
    x, y = xy[..., 0], xy[..., 1]
    # written without Python number operands, which are slow on forward-mode dual tensors
    xx, yy, xy_ = x * x, y * y, x * y
    r2 = xx + yy
    poly = r2 * (k1 + r2 * (k2 + r2 * k3))  # radial factor minus one
    xy2 = xy_ + xy_
    xd = x + x * poly + p1 * xy2 + p2 * (r2 + xx + xx)
    yd = y + y * poly + p1 * (r2 + yy + yy) + p2 * xy2
    return torch.stack([xd, yd], dim=-1)


def undistort_normalized(
    xy: torch.Tensor, dist: torch.Tensor, iterations: int = 20
) -> torch.Tensor:
    """(B, N, 2) undistorted normalised coordinates of distorted ones ``xy`` (B, N, 2), lens
    ``dist`` (B or 1, 5) ``(k1, k2, p1, p2, k3)``: :func:`distort_normalized` inverted by
    fixed-point iteration as ``cv2.undistortPoints`` does (20 steps reach 1e-10 for real
    lenses)."""
    check_shape("xy", xy, ("B", "N", 2))
    check_shape("dist", dist, (None, 5))
    k1, k2, p1, p2, k3 = (dist[:, i : i + 1] for i in range(5))
    xd, yd = xy[..., 0], xy[..., 1]
    x, y = xd, yd
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return torch.stack([x, y], dim=-1)


def undistort_pixels(pixels: torch.Tensor, camera: Camera, iterations: int = 20) -> torch.Tensor:
    """(B, N, 2) undistorted normalised coordinates ``(X/Z, Y/Z)`` of (B, N, 2) pixels
    ``(u, v)`` of B cameras (or one, broadcast): ``K`` undone (skew included), then the lens."""
    check_shape("pixels", pixels, ("B", "N", 2))
    K = camera.K.to(pixels)
    yd = (pixels[..., 1] - K[:, 1:2, 2]) / K[:, 1:2, 1]
    xd = (pixels[..., 0] - K[:, 0:1, 2] - K[:, 0:1, 1] * yd) / K[:, 0:1, 0]
    return undistort_normalized(torch.stack([xd, yd], dim=-1), camera.dist.to(pixels), iterations)


def ray_directions(pixels: torch.Tensor, camera: Camera) -> torch.Tensor:
    """(B, N, 3) world directions of the rays through pixels (B, N, 2), the lens distortion
    undone, scaled to unit depth along the optical axis: the camera centre plus ``d`` times a
    direction is the point at depth ``d`` (metres) the pixel sees."""
    xy = undistort_pixels(pixels, camera)
    d_cam = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1)
    return d_cam @ camera.R.to(pixels)  # (R^T d)^T = d^T R, row vectors


def floor_points(pixels: torch.Tensor, camera: Camera) -> torch.Tensor:
    """The points of the floor (world z = 0) seen at pixels.

    Args:
        pixels: (B, N, 2) pixels ``(u, v)``.
        camera: B cameras.

    Returns:
        (B, N, 3) world points on the floor; NaN where the pixel's ray does not go down to the
        floor in front of the camera (at or above the horizon).
    """
    rays = ray_directions(pixels, camera)
    centre = camera_centre(camera.R.to(pixels), camera.t.to(pixels))[:, None, :]
    depth = -centre[..., 2] / rays[..., 2]
    depth = torch.where(depth > 0, depth, torch.full_like(depth, float("nan")))
    return centre + depth[..., None] * rays


def project_points(
    points: torch.Tensor, camera: Camera, return_depth: bool = False
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Project world points to pixels with the OpenCV camera model.

    Points at or behind the camera (depth <= 0) give meaningless pixels; use ``return_depth``
    to mask them.

    Args:
        points: (B, N, 3) world points, metres.
        camera: B cameras (or one, broadcast over the batch).
        return_depth: also return the camera-frame depth.

    Returns:
        (B, N, 2) pixel coordinates ``(u, v)``; with ``return_depth`` also (B, N) depths in
        metres.
    """
    cam = world_to_camera(points, camera)
    pixels = _camera_frame_to_pixels(cam, camera)
    return (pixels, cam[..., 2]) if return_depth else pixels


def _camera_frame_to_pixels(cam: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Pixels (B, N, 2) of camera-frame points (B, N, 3): division, distortion, intrinsics."""
    xy = cam[..., :2] / cam[..., 2].unsqueeze(-1)
    xy = distort_normalized(xy, camera.dist)
    K = _lift(camera.K, _is_dual(xy))
    u = K[:, 0:1, 0] * xy[..., 0] + K[:, 0:1, 1] * xy[..., 1] + K[:, 0:1, 2]
    v = K[:, 1:2, 1] * xy[..., 1] + K[:, 1:2, 2]
    return torch.stack([u, v], dim=-1)


def projection_jacobian(points: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels of world points and their derivatives w.r.t. the points, in closed form.

    ``pixel = K · distort(x / z, y / z)`` of the camera-frame point ``R X + t``: the product of
    the intrinsics' 2x2 block, the distortion's Jacobian (OpenCV's radial and tangential
    model, :func:`distort_normalized`), the perspective division's 2x3 and ``R``.

    Args:
        points: (B, N, 3) world points, metres.
        camera: B cameras (or one, broadcast).

    Returns:
        (B, N, 2) pixels (bit for bit those of :func:`project_points`) and (B, N, 2, 3)
        ``∂pixel/∂X``.
    """
    cam = world_to_camera(points, camera)
    inv_z = 1.0 / cam[..., 2]
    x, y = cam[..., 0] * inv_z, cam[..., 1] * inv_z
    k1, k2, p1, p2, k3 = (camera.dist[:, i : i + 1] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
    # the distortion's Jacobian w.r.t. (x, y)
    dxx = radial + 2 * x * x * d_radial + 2 * p1 * y + 6 * p2 * x
    dxy = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    dyy = radial + 2 * y * y * d_radial + 6 * p1 * y + 2 * p2 * x
    fx, s = camera.K[:, 0:1, 0], camera.K[:, 0:1, 1]
    fy = camera.K[:, 1:2, 1]
    # the pixels exactly as project_points gives them (the same operations in the same order)
    pixels = _camera_frame_to_pixels(cam, camera)
    # pixel w.r.t. (x, y): K's 2x2 block times the distortion's (symmetric off-diagonal)
    a = torch.stack([fx * dxx + s * dxy, fx * dxy + s * dyy, fy * dxy, fy * dyy], -1)
    a = a.reshape(*x.shape, 2, 2)
    # (x, y) w.r.t. the camera-frame point, then w.r.t. the world point (R)
    zero = torch.zeros_like(x)
    persp = torch.stack([inv_z, zero, -x * inv_z, zero, inv_z, -y * inv_z], -1)
    persp = persp.reshape(*x.shape, 2, 3)
    rot = camera.R.expand(points.shape[0], -1, -1)[:, None]  # (B, 1, 3, 3)
    return pixels, a @ persp @ rot


def project_with_jacobian(
    points: torch.Tensor, d_points: torch.Tensor, camera: Camera
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels of world points and their derivatives w.r.t. parameters, by the chain rule.

    Args:
        points: (B, N, 3) world points, metres.
        d_points: (B, N, 3, P) the points' derivatives w.r.t. P parameters.
        camera: B cameras (or one, broadcast).

    Returns:
        (B, N, 2) pixels (as :func:`projection_jacobian`) and (B, N, 2, P) their derivatives.
    """
    pixels, d_pix = projection_jacobian(points, camera)
    # a 2x3 by 3xP product per point, as three broadcast multiply-adds (a batched matmul of
    # tiny matrices is slower, and rounds a row by its batch)
    out = d_pix[..., 0, None] * d_points[:, :, None, 0]
    out += d_pix[..., 1, None] * d_points[:, :, None, 1]
    out += d_pix[..., 2, None] * d_points[:, :, None, 2]
    return pixels, out
