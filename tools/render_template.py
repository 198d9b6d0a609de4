"""Render a template body at the six nominal postures and print its measurements.

    python tools/render_template.py [--template mpeg4_full] [--out runs/template_preview]

Writes ``pose1.png`` … ``pose6.png`` (a shaded body with its silhouette outline, seen by a
camera 3.5 m away at chest height) and ``postures.png`` (the six side by side).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from torchfit.body.measure import measure_model  # noqa: E402
from torchfit.body.model import BodyModel  # noqa: E402
from torchfit.body.postures import POSTURES  # noqa: E402
from torchfit.viz.preview import nominal_view, render_pose_preview  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--template", default="mpeg4_full", help="template name or URDF path")
    parser.add_argument("--out", type=Path, default=Path("runs/template_preview"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    import cv2

    model = BodyModel(args.template)
    args.out.mkdir(parents=True, exist_ok=True)
    camera = nominal_view()
    tiles = []
    for posture in POSTURES:
        image = render_pose_preview(model, camera, posture)
        cv2.putText(
            image,
            f"{posture.index} {posture.name}",
            (10, 30),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.9,
            (0, 0, 0),
            2,
        )
        cv2.imwrite(str(args.out / f"pose{posture.index}.png"), image)
        tiles.append(image)
    sheet = np.concatenate([np.concatenate(tiles[:3], 1), np.concatenate(tiles[3:], 1)], 0)
    cv2.imwrite(str(args.out / "postures.png"), cv2.resize(sheet, None, fx=0.5, fy=0.5))
    scales = torch.ones(1, model.num_segments, 3, dtype=model.dtype)
    values = {k: round(float(v[0]), 4) for k, v in measure_model(model, scales).items()}
    print(json.dumps({"template": model.template.name, **values}, indent=2))
    print(f"wrote {args.out}/pose1.png … pose6.png and postures.png", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
