"""Make a test sequence from real motion capture: an anny body, its six postures, and a clip of
it moving in one of the generator's rooms.

    python tools/make_sequence.py --bvh FILE --out DIR --frames N [--start F] [--step K] --seed S

``FILE`` is a CMU ``.bvh`` clip or an ``.amc`` motion (its ``.asf`` skeleton beside it, e.g.
``11_01.amc`` and ``11.asf``). Writes ``DIR/subject/`` (the body's six postures with truth;
fit it with ``tools/fit.py --data DIR`` restricted to it) and ``DIR/sequence/`` (camera.yaml,
background/, frames/000000.png …, truth.json with the joints per frame). Needs the ``synth``
extra.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tqdm import tqdm  # noqa: E402

from torchfit.config import load_config  # noqa: E402
from torchfit.errors import TorchfitError  # noqa: E402
from torchfit.synth.options import SynthConfig  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bvh", required=True, help="motion clip (.bvh, or .amc with its .asf)")
    parser.add_argument("--out", required=True, help="output folder")
    parser.add_argument("--frames", type=int, required=True, help="frames to render")
    parser.add_argument(
        "--start",
        type=int,
        default=0,
        help="first clip frame, counted from the motion's first (a rest pose the file starts "
        "with, as the CMU BVH conversions' T-pose, is not kept)",
    )
    parser.add_argument("--step", type=int, default=1, help="clip frames per rendered frame")
    parser.add_argument("--seed", type=int, required=True, help="body, room and camera seed")
    parser.add_argument(
        "--max-travel",
        type=float,
        default=0.6,
        help="largest horizontal distance (m) of the hips from their start; a clip that "
        "travels further is shrunk horizontally to stay in view",
    )
    parser.add_argument("--config", default=None, help="YAML file of SynthConfig keys")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        cfg = load_config(args.config, args.set, schema=SynthConfig)
        cfg.stereo = False
        from torchfit.synth.sequence import make_sequence

        summary = make_sequence(
            args.out,
            args.bvh,
            args.frames,
            args.seed,
            start=args.start,
            step=args.step,
            cfg=cfg,
            progress=lambda r: tqdm(r, desc="frames"),
            max_travel_m=args.max_travel,
        )
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({k: v for k, v in summary.items() if k != "subject"}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
