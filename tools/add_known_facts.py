"""Copy a synthetic dataset with a ``subject.yaml`` per subject, its facts taken from the truth.

    python tools/add_known_facts.py --data DIR --out DIR [--facts height_m sex]

Every subject folder of --data that has ``truth.json`` becomes a folder of --out whose entries
are symbolic links to the original files (nothing is copied) plus a ``subject.yaml`` with the
chosen facts: ``height_m`` from ``truth.json``, ``sex`` from the generator's ``synth.json``
(where present). Benchmarking --out measures the fit given those facts
(``tools/benchmark.py --data OUT``). Exit status: 0, 2 on bad arguments, 4 when --data is
missing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml
from tqdm import tqdm

FACTS = ("height_m", "sex")


def facts_of(folder: Path, wanted: tuple[str, ...]) -> dict:
    """The chosen facts of one subject folder, from its truth.json and synth.json."""
    truth = json.loads((folder / "truth.json").read_text())
    synth_path = folder / "synth.json"
    synth = json.loads(synth_path.read_text()) if synth_path.is_file() else {}
    out = {}
    if "height_m" in wanted and "height_m" in truth:
        out["height_m"] = round(float(truth["height_m"]), 4)
    if "sex" in wanted and synth.get("sex") in ("female", "male"):
        out["sex"] = synth["sex"]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="the synthetic dataset")
    parser.add_argument("--out", type=Path, required=True, help="the new dataset folder")
    parser.add_argument("--facts", nargs="+", default=["height_m"], choices=FACTS)
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        print(f"error: dataset folder not found: {args.data}", file=sys.stderr)
        return 4
    if args.out.resolve() == args.data.resolve():
        print("error: --out must differ from --data", file=sys.stderr)
        return 2
    subjects = sorted(p for p in args.data.iterdir() if (p / "truth.json").is_file())
    for folder in tqdm(subjects, desc="subjects", unit="subject"):
        target = args.out / folder.name
        target.mkdir(parents=True, exist_ok=True)
        for entry in folder.iterdir():
            if entry.name == "subject.yaml":
                continue
            link = target / entry.name
            if not link.is_symlink():
                link.symlink_to(entry.resolve())
        facts = facts_of(folder, tuple(args.facts))
        (target / "subject.yaml").write_text(yaml.safe_dump(facts, sort_keys=False))
    print(f"{len(subjects)} subjects with {', '.join(args.facts)} in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
