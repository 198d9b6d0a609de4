"""The residuals of the first paper (section 6), as pure functions.

For one subject and one pose with person contour C_P (pixels x_i) and model contour C_M:

- ``e_P,i = d(x_i, C_M) / sqrt(|C_P|)``: distance from each person contour pixel to the
  model contour, normalised by the contour length;
- ``e_M = sqrt( mean_{m in C_M} D_P(m)^2 )``: root-mean-square of the person's contour
  distance map D_P sampled at the model contour points;
- ``e_B``: barrier terms, zero inside the allowed interval, growing linearly outside it.

All in pixels (e_B in the units of its parameter times a weight). Ragged contours are padded
and carry validity masks.
"""

from __future__ import annotations

import torch

__all__ = ["person_to_model", "model_to_person", "barrier", "padded_row_sum"]

#: e_M for a pose whose model contour is entirely out of view: a large constant, so the cost
#: stays finite and the solver rejects steps that move the model out of the image.
NO_CONTOUR_PENALTY = 1e3

#: Chunk length of :func:`padded_row_sum`.
SUM_CHUNK = 64


def padded_row_sum(values: torch.Tensor) -> torch.Tensor:
    """Sum over the last dimension that trailing zero padding does not change, bit for bit.

    A plain ``sum`` groups a row's terms by its length (vector lanes, tails), so the same
    terms padded to a batch's longest row round differently from the row alone. Here the row
    is cut into chunks of :data:`SUM_CHUNK` (the last one zero-filled), each chunk summed on
    its own, and the chunk sums added one after another: extra zero chunks add exact zeros.

    Args:
        values: (..., n) terms, zero-padded on the right (dual tensors allowed).

    Returns:
        (...) sums.
    """
    # contiguous, so that each chunk is summed by the same kernel whether or not it was padded
    # here (a strided view, e.g. a transposed one, takes another reduction order)
    values = values.contiguous()
    n = values.shape[-1]
    chunks = max(1, -(-n // SUM_CHUNK))
    pad = chunks * SUM_CHUNK - n
    if pad:
        values = torch.cat([values, values.new_zeros(*values.shape[:-1], pad)], -1)
    partial = values.reshape(*values.shape[:-1], chunks, SUM_CHUNK).sum(-1)
    total = partial[..., 0]
    for c in range(1, chunks):
        total = total + partial[..., c]
    return total


def person_to_model(distances: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """e_P: distances (B, C) of person contour pixels to the model contour, valid (B, C).

    Returns:
        (B, C) residuals ``d / sqrt(|C_P|)``, zero on padding.
    """
    count = valid.sum(dim=1, keepdim=True).clamp_min(1).to(distances.dtype)
    return torch.where(valid, distances, torch.zeros_like(distances)) / count.sqrt()


def model_to_person(distances: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """e_M: RMS of the person distance map D_P sampled at the model contour points.

    Args:
        distances: (B, N) D_P at the model contour points, pixels (e.g. from
            :func:`torchfit.image.sample_distance_map`).
        valid: (B, N) bool.

    Returns:
        (B,) residuals; :data:`NO_CONTOUR_PENALTY` where no point is valid.
    """
    d = distances
    d2 = torch.where(valid, d * d, torch.zeros_like(d))
    n = valid.sum(dim=1)
    # padding of the model contour (to a batch's longest) must not change a subject's value
    mean = padded_row_sum(d2) / n.clamp_min(1).to(d.dtype)
    # sqrt(mean) with a smooth floor so a perfect fit has a finite derivative
    e = torch.sqrt(mean + 1e-12)
    return torch.where(n > 0, e, torch.full_like(e, NO_CONTOUR_PENALTY))


def barrier(
    x: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor, weight: float | torch.Tensor
) -> torch.Tensor:
    """e_B: ``weight * (max(0, lower - x) + max(0, x - upper))`` elementwise.

    Args:
        x: (B, P) parameters; lower, upper: (P,) or (B, P) interval ends (±inf for none).

    Returns:
        (B, P) barrier residuals, zero inside the interval.
    """
    below = torch.clamp(lower - x, min=0)
    above = torch.clamp(x - upper, min=0)
    return weight * (below + above)
