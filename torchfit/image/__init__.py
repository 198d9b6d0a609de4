"""Image side of torchfit: background subtraction, clean-up, contours and distance maps.

Conventions shared by the modules: images are ``(B, 3, H, W)`` RGB in ``[0, 1]``; masks and
maps are ``(B, 1, H, W)`` (masks ``bool``, ``True`` = person); pixel ``(0, 0)`` is the centre of
the top-left pixel and points are ``(u, v)`` with ``v`` down (``docs/design.md`` section 2).

- :mod:`~torchfit.image.background`: colour features and the per-pixel background model.
- :mod:`~torchfit.image.shadow`: the explicit cast-shadow test.
- :mod:`~torchfit.image.edges`: the outline's mixed pixels (person or background).
- :mod:`~torchfit.image.morphology`: opening, closing, largest region, hole filling.
- :mod:`~torchfit.image.photometric`: per-channel gains (exposure, white balance) undone.
- :mod:`~torchfit.image.segment`: :class:`SegmentationOptions` and the whole chain.
- :mod:`~torchfit.image.plausibility`: what a person's silhouette cannot look like.
- :mod:`~torchfit.image.contours`: ordered outer contours.
- :mod:`~torchfit.image.distance`: distance transforms and bilinear sampling of the maps.
"""

from torchfit.image.background import (
    BackgroundModel,
    color_features,
    fit_background,
    mahalanobis_distance,
)
from torchfit.image.contours import (
    contour_mask,
    contour_normals,
    outer_contours,
    outline_mask,
    trace_outer_contour,
)
from torchfit.image.distance import (
    chamfer_distance_transform,
    distance_map,
    euclidean_distance_transform,
    mask_to_distance_map,
    sample_distance_map,
)
from torchfit.image.edges import refine_edges
from torchfit.image.morphology import (
    binary_closing,
    binary_opening,
    fill_holes,
    largest_component,
    pack_mask,
    unpack_mask,
)
from torchfit.image.photometric import (
    PhotometricResult,
    compensate,
    estimate_gains,
    match_background,
)
from torchfit.image.plausibility import PlausibilityOptions, implausible, silhouette_shape
from torchfit.image.segment import (
    SegmentationOptions,
    SegmentationResult,
    cast_shadow,
    clean_mask,
    finish_silhouettes,
    segment,
)
from torchfit.image.shadow import bridged, lower_band, shadow_mask

__all__ = [
    "BackgroundModel",
    "color_features",
    "fit_background",
    "mahalanobis_distance",
    "shadow_mask",
    "lower_band",
    "bridged",
    "binary_opening",
    "binary_closing",
    "largest_component",
    "pack_mask",
    "unpack_mask",
    "fill_holes",
    "refine_edges",
    "PhotometricResult",
    "estimate_gains",
    "compensate",
    "match_background",
    "PlausibilityOptions",
    "silhouette_shape",
    "implausible",
    "SegmentationOptions",
    "SegmentationResult",
    "cast_shadow",
    "finish_silhouettes",
    "clean_mask",
    "segment",
    "trace_outer_contour",
    "outer_contours",
    "contour_mask",
    "outline_mask",
    "contour_normals",
    "chamfer_distance_transform",
    "euclidean_distance_transform",
    "distance_map",
    "mask_to_distance_map",
    "sample_distance_map",
]
