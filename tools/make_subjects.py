"""Generate synthetic subjects (anny bodies in the six postures) in the dataset layout.

    python tools/make_subjects.py --out DIR --n N --seed S [--config FILE] [--set key=value]
    python tools/make_subjects.py --out DIR --n N --seed S --masks-only   # add truth masks

``--masks-only`` (re)writes only the evaluation masks (``truth_masks/``) of subjects generated
earlier with the same seed and config, without writing their images again.

Hard rooms: ``--config configs/synth_hard.yaml`` turns on every condition of
:mod:`torchfit.synth.hard` (the body's shadow on the walls and furniture beside the arms and
head, a bookshelf, cabinet and door, patterned walls and posters, exposure and white-balance
changes between the background frames and each posture with a slow drift, stronger sensor
noise and a JPEG round trip, a wider range of camera heights and distances); each is its own
key, so ``--set`` switches one on or off (e.g. ``--set wall_shadows=true`` alone). With none
of them (the default) the subjects are bit-identical to those made before these keys existed.
``truth_masks/poseK_shadow.png`` then holds the cast shadow on every surface, not only the floor.

    python tools/make_subjects.py --config configs/synth_hard.yaml --out data_hard_dev --n 8 \
        --seed 3000 --contact-sheet data_hard_dev/contact_sheet.png

Needs the ``synth`` extra (``pip install -e ".[synth]"``). The same seed gives the same
subjects; subject ``i`` does not depend on ``--n``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tqdm import tqdm  # noqa: E402

from torchfit.config import load_config  # noqa: E402
from torchfit.errors import TorchfitError  # noqa: E402
from torchfit.synth.generate import SynthConfig, make_subject  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    """Exit codes: 0 done, 2 a bad config or argument, or anny (the ``synth`` extra) missing."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="output folder (one sub-folder per subject)")
    parser.add_argument("--n", type=int, required=True, help="number of subjects")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--first", type=int, default=0, help="index of the first subject")
    parser.add_argument("--config", default=None, help="YAML file of SynthConfig keys")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument(
        "--contact-sheet", default=None, metavar="PNG", help="also write a contact sheet here"
    )
    parser.add_argument(
        "--masks-only",
        action="store_true",
        help="write only the truth masks of existing subjects (same seed and config)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        cfg = load_config(args.config, args.set, schema=SynthConfig)
        from torchfit.synth.body import load_anny  # imports anny (the synth extra) lazily

        model = load_anny()
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    folders = []
    for i in tqdm(range(args.first, args.first + args.n), desc="subjects"):
        start = time.perf_counter()
        folders.append(out / f"subject_{i:03d}")
        summary = make_subject(folders[-1], args.seed, i, cfg, model, args.masks_only)
        summary["seconds"] = round(time.perf_counter() - start, 1)
        logging.info(json.dumps(summary))
    if args.contact_sheet and not args.masks_only:
        from torchfit.synth.sheet import contact_sheet

        contact_sheet(folders, args.contact_sheet)
    return 0


if __name__ == "__main__":
    sys.exit(main())
