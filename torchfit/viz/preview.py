"""Quick looks at a body model: a nominal camera and shaded posture previews."""

from __future__ import annotations

import numpy as np
import torch

from torchfit.body.model import BodyModel
from torchfit.body.postures import Posture, pose_nominal
from torchfit.camera import Camera, camera_centre, look_at, project_points
from torchfit.viz.raster import draw_polyline, outer_outlines, render_shaded, render_silhouette

__all__ = ["nominal_view", "render_pose_preview"]


def nominal_view(
    distance: float = 3.5,
    height: float = 1.2,
    azimuth_deg: float = 0.0,
    focal: float = 900.0,
    image_size: tuple[int, int] = (720, 576),
) -> Camera:
    """A camera ``distance`` metres from the floor mark at ``height``, looking at (0, 0, 0.95)."""
    az = np.radians(azimuth_deg)
    centre = torch.tensor(
        [[distance * np.cos(az), distance * np.sin(az), height]], dtype=torch.float64
    )
    R, t = look_at(centre, torch.tensor([[0.0, 0.0, 0.95]], dtype=torch.float64))
    w, h = image_size
    K = torch.tensor(
        [[focal, 0.0, (w - 1) / 2], [0.0, focal, (h - 1) / 2], [0.0, 0.0, 1.0]], dtype=torch.float64
    )
    return Camera(K=K, dist=torch.zeros(5, dtype=torch.float64), R=R, t=t, image_size=image_size)


def render_pose_preview(
    model: BodyModel,
    camera: Camera,
    posture: int | Posture,
    scales: torch.Tensor | None = None,
    background: np.ndarray | None = None,
    outline: bool = True,
) -> np.ndarray:
    """Shaded body at a posture's nominal angles, with its silhouette outline in green.

    Args:
        model: the body model.
        camera: one camera.
        posture: 1..6 or a :class:`Posture`.
        scales: (1, S, 3) segment scales (default: the template).
        background: (H, W, 3) uint8 BGR image to draw on (default: light grey).
        outline: draw the silhouette outline.

    Returns:
        (H, W, 3) uint8 BGR image.
    """
    if scales is None:
        scales = torch.ones(1, model.num_segments, 3, dtype=model.dtype)
    _, out = pose_nominal(model, scales, posture, camera_centre(camera.R, camera.t))
    verts = out.vertices
    px, depth = project_points(verts, camera.to(dtype=verts.dtype), return_depth=True)
    px, depth = px[0].numpy(), depth[0].numpy()
    faces = model.faces.cpu().numpy()
    cam_pts = (camera.R[0] @ verts[0].T).T.numpy()
    tri = cam_pts[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True) + 1e-12
    w, h = camera.image_size
    image = background if background is not None else np.full((h, w, 3), 235, np.uint8)
    image = render_shaded(px, depth, faces, normals, image)
    if outline:
        for contour in outer_outlines(render_silhouette(px, faces, (w, h))):
            draw_polyline(image, contour, (0, 160, 0), thickness=2)
    return image
