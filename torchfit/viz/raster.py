"""Rasterise projected meshes: exact silhouettes and a shaded preview.

Pixel convention (design.md section 2): pixel (0, 0) is the centre of the top-left pixel,
u to the right, v down. Drawing uses OpenCV with 4 bits of sub-pixel precision.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "render_silhouette",
    "render_fixed",
    "fixed_points",
    "edge_outline",
    "render_shaded",
    "draw_polyline",
    "outer_outlines",
]

_SHIFT = 4  # sub-pixel bits for cv2 drawing


def fixed_points(points: np.ndarray) -> np.ndarray:
    """(N, 2) pixels -> the (N, 2) int32 fixed-point coordinates the drawing uses (a
    :func:`render_fixed` of them is :func:`render_silhouette` of ``points``)."""
    return np.round(np.asarray(points, dtype=np.float64) * (1 << _SHIFT)).astype(np.int32)


def render_silhouette(
    pixels: np.ndarray, faces: np.ndarray, image_size: tuple[int, int]
) -> np.ndarray:
    """Binary silhouette of a projected triangle mesh.

    Args:
        pixels: (V, 2) projected vertices ``(u, v)``.
        faces: (F, 3) triangle vertex indices.
        image_size: ``(width, height)``.

    Returns:
        (H, W) uint8 mask, 255 inside the silhouette, 0 outside.
    """
    return render_fixed(fixed_points(pixels), faces, image_size)


def render_fixed(fixed: np.ndarray, faces: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """:func:`render_silhouette` of vertices already in fixed point (:func:`fixed_points`)."""
    import cv2

    w, h = image_size
    mask = np.zeros((h, w), np.uint8)
    tris = fixed[np.asarray(faces)]
    # one call per triangle: a single fillPoly over all of them applies the even-odd rule,
    # which would cut overlapping triangles out of the silhouette; positional arguments (the
    # binding's keyword parsing took a third of the time of the thousands of calls)
    fill, line = cv2.fillConvexPoly, cv2.LINE_8
    for tri in tris:
        fill(mask, tri, 255, line, _SHIFT)
    return mask


def edge_outline(
    pixels: np.ndarray,
    edges: np.ndarray,
    faces: np.ndarray,
    image_size: tuple[int, int],
    fixed: np.ndarray | None = None,
) -> np.ndarray:
    """The pixels (n, 2) int64 ``(u, v)`` of the outer outline of a projected mesh in the
    image.

    The outer boundary of a projected mesh runs along its silhouette edges (those between a
    front- and a back-facing triangle, and the mesh's borders), so where the mesh lies within
    the image, the outer outline of those edges drawn as lines is its silhouette's, at a
    fraction of the cost of filling every triangle (the two rasterisations part by at most a
    pixel). Where the image's frame cuts the mesh, the part inside the image is what counts:
    a gap between two limbs that the frame opens is outside, as it is in the person's
    silhouette, and lines alone cannot tell that gap from the inside of the body; the
    triangles ``faces`` are filled on the image then (and the outline runs along the frame
    where the frame cuts the mesh).

    Args:
        pixels: (V, 2) projected vertices.
        edges: (E, 2) vertex indices of the silhouette edges.
        faces: (F, 3) the mesh's triangles.
        image_size: ``(width, height)``.
        fixed: :func:`fixed_points` of ``pixels``, where the caller has them.
    """
    import cv2

    w, h = image_size
    if not len(edges):
        return np.zeros((0, 2), np.int64)
    fixed = fixed_points(pixels) if fixed is None else fixed
    used = pixels[np.asarray(edges).ravel()]  # the edges' box (a vertex may repeat)
    lo = np.floor(used.min(0)).astype(np.int64) - 1
    hi = np.ceil(used.max(0)).astype(np.int64) + 1
    if lo.min() < 0 or hi[0] > w - 1 or hi[1] > h - 1:
        outlines = outer_outlines(render_fixed(fixed, faces, image_size))
        return (np.concatenate(outlines) if outlines else np.zeros((0, 2))).astype(np.int64)
    # the lines on the edges' box: one two-point polyline per edge, (E, 2, 2)
    canvas = np.zeros((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), np.uint8)
    lines = fixed[edges] - (lo << _SHIFT).astype(np.int32)
    cv2.polylines(canvas, lines, False, 255, 1, cv2.LINE_8, _SHIFT)
    contours, _ = cv2.findContours(canvas, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    return np.concatenate([c[:, 0, :] for c in contours]).astype(np.int64) + lo


def render_shaded(
    pixels: np.ndarray,
    depth: np.ndarray,
    faces: np.ndarray,
    normals_cam: np.ndarray,
    image: np.ndarray,
    color: tuple[int, int, int] = (200, 170, 150),
) -> np.ndarray:
    """Lambert-shaded preview of a mesh drawn over ``image`` (painter's order, far to near).

    Args:
        pixels: (V, 2) projected vertices.
        depth: (V,) camera-frame depths.
        faces: (F, 3) triangles.
        normals_cam: (F, 3) unit face normals in the camera frame.
        image: (H, W, 3) uint8 BGR background (copied).
        color: base BGR colour.

    Returns:
        (H, W, 3) uint8 BGR image.
    """
    import cv2

    out = image.copy()
    faces = np.asarray(faces)
    order = np.argsort(-depth[faces].mean(axis=1))
    shade = np.clip(-normals_cam[:, 2], 0.0, 1.0) * 0.75 + 0.25
    tris = fixed_points(pixels)[faces]
    base = np.asarray(color, dtype=np.float64)
    for f in order:
        c = tuple(int(x) for x in base * shade[f])
        cv2.fillConvexPoly(out, tris[f], c, lineType=cv2.LINE_AA, shift=_SHIFT)
    return out


def draw_polyline(
    image: np.ndarray,
    points: np.ndarray,
    color: tuple[int, int, int],
    closed: bool = True,
    thickness: int = 1,
) -> np.ndarray:
    """Draw a sub-pixel polyline (N, 2) on ``image`` in place and return it."""
    import cv2

    if len(points):
        cv2.polylines(image, [fixed_points(points)], closed, color, thickness, cv2.LINE_AA, _SHIFT)
    return image


def draw_label(
    image: np.ndarray,
    text: str,
    origin: tuple[int, int],
    scale: float,
    ink: tuple[int, int, int] = (0, 0, 0),
    box: tuple[int, int, int] = (255, 255, 255),
) -> np.ndarray:
    """Draw ``text`` (baseline at ``origin``) on a filled box in place and return the image.

    A box rather than an outline drawn with a thicker stroke: OpenCV spaces the glyphs by the
    stroke width, so a thick outline does not line up with thin text.
    """
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    (w, h), base = cv2.getTextSize(text, font, scale, 1)
    pad = max(2, round(4 * scale))
    x, y = origin
    cv2.rectangle(image, (x - pad, y - h - pad), (x + w + pad, y + base), box, cv2.FILLED)
    cv2.putText(image, text, (x, y), font, scale, ink, 1, cv2.LINE_AA)
    return image


def outer_outlines(mask: np.ndarray) -> list[np.ndarray]:
    """Outer contours of every region of a binary (H, W) mask, each (N, 2) ``(u, v)`` float64."""
    import cv2

    contours, _ = cv2.findContours(
        np.ascontiguousarray(mask, dtype=np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
    )
    return [c[:, 0, :].astype(np.float64) for c in contours]
