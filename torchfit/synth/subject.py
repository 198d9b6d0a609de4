"""Random subjects of the synthetic generator: phenotype, height and clothing colours.

Lengths in metres; colours linear RGB in [0, 1]. Everything is drawn from the caller's
``numpy.random.Generator`` (the order of the draws is part of a dataset's reproducibility).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from torchfit.synth.body import AnnyBody, Phenotype

__all__ = ["sample_phenotype", "body_with_height", "sample_albedo"]


_SKIN = np.array(
    [
        [0.93, 0.76, 0.65],
        [0.87, 0.66, 0.52],
        [0.76, 0.55, 0.40],
        [0.60, 0.41, 0.29],
        [0.45, 0.30, 0.21],
        [0.33, 0.22, 0.16],
    ]
)
_CLOTHES = np.array(
    [
        [0.10, 0.15, 0.35],
        [0.15, 0.30, 0.60],
        [0.12, 0.40, 0.20],
        [0.55, 0.10, 0.12],
        [0.20, 0.20, 0.22],
        [0.45, 0.45, 0.48],
        [0.05, 0.05, 0.06],
        [0.30, 0.15, 0.40],
        [0.10, 0.45, 0.50],
        [0.85, 0.85, 0.88],
        [0.70, 0.60, 0.10],
    ]
)
_HAIR = np.array([[0.05, 0.04, 0.03], [0.22, 0.13, 0.07], [0.55, 0.42, 0.22], [0.6, 0.6, 0.6]])


def sample_phenotype(rng: np.random.Generator) -> tuple[Phenotype, str]:
    """A random adult phenotype (its ``height`` still 0.5) and its sex."""
    sex = "female" if rng.random() < 0.5 else "male"
    gender = rng.uniform(0.85, 1.0) if sex == "female" else rng.uniform(0.0, 0.15)
    phen = Phenotype(
        gender=gender,
        age=rng.uniform(0.6, 0.95),
        muscle=rng.uniform(0.1, 0.9),
        weight=rng.uniform(0.05, 0.95),
        height=0.5,
        proportions=rng.uniform(0.3, 0.7),
    )
    return phen, sex


def _neutral_height(body: AnnyBody) -> float:
    v = body.pose({}).vertices
    return float(v[:, 2].max() - v[:, 2].min())


def body_with_height(phen: Phenotype, target: float, model: Any) -> AnnyBody:
    """Bisection on anny's height parameter for a neutral standing height of ``target``."""
    lo, hi = 0.0, 1.0
    body = None
    for _ in range(12):
        phen.height = 0.5 * (lo + hi)
        body = AnnyBody(phen, model)
        h = _neutral_height(body)
        if abs(h - target) < 2e-3:
            break
        lo, hi = (phen.height, hi) if h < target else (lo, phen.height)
    return body


def sample_albedo(body: AnnyBody, rng: np.random.Generator) -> np.ndarray:
    """(V, 3) albedo: skin for hands, face and neck; shirt, trousers, shoes, hair."""
    bones = body.dominant_bones()
    skin = _SKIN[rng.integers(len(_SKIN))] * rng.uniform(0.95, 1.05)
    picks = rng.choice(len(_CLOTHES), size=2, replace=False)
    shirt, trousers = _CLOTHES[picks[0]], _CLOTHES[picks[1]]
    shoes = rng.choice(np.array([[0.05, 0.05, 0.05], [0.25, 0.15, 0.08], [0.8, 0.8, 0.8]]))
    hair = _HAIR[rng.integers(len(_HAIR))]
    neutral = body.pose({}).vertices
    joints = body.pose({}).joints
    hip_z = 0.5 * (joints["l_hip"][2] + joints["r_hip"][2])
    waist = hip_z + 0.45 * (joints["neck"][2] - hip_z) * rng.uniform(0.35, 0.5)
    out = np.zeros((len(bones), 3))
    head_z = []
    for k, b in enumerate(bones):
        if b.startswith(("wrist", "finger", "metacarpal", "neck", "head", "eye")):
            out[k] = skin
            if b in ("head", "eye.L", "eye.R"):
                head_z.append(k)
        elif b.startswith(("foot", "toe")):
            out[k] = shoes
        elif b.startswith(("upperleg", "lowerleg")) or (
            b.startswith(("pelvis", "root", "spine05", "spine04")) and neutral[k, 2] < waist
        ):
            out[k] = trousers
        else:
            out[k] = shirt
    head = np.array(head_z)
    top = neutral[body.head_top_vertex]
    hv = neutral[head]
    eye = top[2] - 0.11 * (top[2] - neutral[:, 2].min()) / 1.75
    centre_y = hv[:, 1].mean()
    hairy = (hv[:, 2] > eye + 0.04) | ((hv[:, 1] > centre_y + 0.02) & (hv[:, 2] > eye - 0.07))
    out[head[hairy]] = hair
    return out * rng.uniform(0.97, 1.03, size=(len(bones), 1))  # slight fabric/skin variation
