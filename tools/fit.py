"""Fit body models to a dataset of six-posture captures.

    python tools/fit.py --config configs/demo.yaml [--data DIR] [--out DIR] [--set key=value ...]
        [--executor local|ray] [--address auto|HOST:PORT] [--workers N]

Segments the six posture images of every subject, fits the template body (batched
Levenberg-Marquardt, autograd Jacobian; ``--set fit.method=minpack_rendered`` runs the
paper's rendered-contour MINPACK baseline instead) and writes runs/<run.name>/ (or --out):
config.yaml, summary.csv, tb/ and per subject measurements.json, params.json,
model.urdf + meshes/, model.glb, overlay_pose1..6.png and fingerprint.json. A rerun keeps
the subjects whose fingerprint is unchanged and refits the others (with either executor).
``--executor ray`` fits the batches as Ray tasks: on a local cluster started for the run, or
on the cluster at ``--address``; ``--workers`` batches at once.

Exit codes: 0 every subject fitted (ok or poor_fit), 1 some subject failed, 2 bad config or
arguments, 3 the run folder cannot be written, 4 the dataset is missing or unreadable.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tqdm import tqdm  # noqa: E402

from torchfit.config.cli import (  # noqa: E402
    EXIT_FAILED,
    EXIT_OK,
    add_config_args,
    add_executor_args,
    config_from_args,
    exit_code,
    run_folder,
)
from torchfit.errors import TorchfitError  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_config_args(parser)
    add_executor_args(parser)
    args = parser.parse_args(argv)
    try:
        config = config_from_args(args)
        run_dir = run_folder(config)
        from torchfit.pipeline import run

        results = run(
            config,
            run_dir,
            progress=lambda n: tqdm(total=n, desc="subjects", unit="subject", position=0),
            stage_progress=lambda desc, n: tqdm(
                total=n, desc=desc, unit="it", position=1, leave=False
            ),
        )
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exit_code(exc)
    failed = [r for r in results if r.status == "failed"]
    for r in results:
        height = r.measurements.get("height_m")
        h = f"height {height:.3f} m" if height is not None else ""
        kept = " (kept from an earlier run)" if r.resumed else ""
        print(f"{r.name:>16}  {r.status:<8} {h}  {r.message}{kept}")
    print(f"outputs in {run_dir}/ ({len(results) - len(failed)} of {len(results)} subjects)")
    return EXIT_FAILED if failed else EXIT_OK


if __name__ == "__main__":
    raise SystemExit(main())
