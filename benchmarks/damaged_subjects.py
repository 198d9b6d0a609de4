"""Deliberately damaged subjects: does the judge catch a fit that a damage drags away?

    python benchmarks/damaged_subjects.py --data DIR --out DIR [--subjects A B] \
        [--damages band_arm blob_arm ...] [--config configs/benchmark.yaml] [--set key=value]

For each subject with truth.json and each damage, a copy of the subject folder is damaged
(its images or camera), all copies are fitted in one run (``tools/benchmark.py``), and every
fitted subject is classed by its worst error over the report's measurements (height … shoulder
width) against the truth: ``within`` (all within 10 %), ``caught`` (some error over 10 % and
the status is not ``ok``) or ``MISSED`` (over 10 % and ``ok``). The clean copies are fitted
too (``clean``): there a status other than ``ok`` is a false alarm.

Damages (pixel positions from the subject's truth masks):

- ``band_arm``: a dark grey band, like a wall shadow, glued below the arm that reaches furthest
  sideways and running 30 % of the arm's reach past the hand, in the T-pose (pose 4);
- ``band_arm_all``: the same in every posture;
- ``blob_arm``: a disc of the clothes' colour (40 px across) glued to the furthest hand in
  poses 1 and 4;
- ``cut_pose``: the lower half of the person in pose 2 painted over with the background;
- ``camera_high``: camera.yaml says the camera is 0.25 m higher than it is.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from torchfit.eval.records import REPORT_KEYS  # noqa: E402

DAMAGES = ("band_arm", "band_arm_all", "blob_arm", "cut_pose", "camera_high")


def _arm_extreme(mask: np.ndarray) -> tuple[int, int, int, int]:
    """(side, column of the hand tip, row of the arm, arm thickness) of the arm reaching
    furthest from the body's centre column."""
    ys, xs = np.nonzero(mask)
    centre = int(np.median(xs))
    left, right = xs.min(), xs.max()
    side = -1 if centre - left > right - centre else 1
    tip = left if side < 0 else right
    near = np.abs(xs - tip) < 25
    rows = ys[near]
    return side, int(tip), int(np.median(rows)), max(int(rows.max() - rows.min()), 6)


def _band(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    side, tip, row, thick = _arm_extreme(mask)
    reach = abs(tip - int(np.median(np.nonzero(mask)[1])))
    out = image.copy()
    x0, x1 = sorted((tip - side * reach // 2, tip + side * int(0.3 * reach)))
    y0, y1 = row, row + thick // 2 + max(thick, 10)
    region = out[max(y0, 0) : y1, max(x0, 0) : x1].astype(np.float32)
    out[max(y0, 0) : y1, max(x0, 0) : x1] = (0.35 * region).astype(np.uint8)
    return out


def _blob(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    side, tip, row, _ = _arm_extreme(mask)
    ys, xs = np.nonzero(mask)
    colour = np.median(image[ys, xs], axis=0).astype(int).tolist()
    out = image.copy()
    cv2.circle(out, (tip + side * 14, row), 20, colour, -1)
    return out


def _cut(image: np.ndarray, mask: np.ndarray, background: np.ndarray) -> np.ndarray:
    ys, _ = np.nonzero(mask)
    mid = (ys.min() + ys.max()) // 2
    out = image.copy()
    out[mid:] = background[mid:]
    return out


def damage_subject(src: Path, dst: Path, damage: str) -> None:
    """Copy subject ``src`` to ``dst`` and apply ``damage`` (one of :data:`DAMAGES`)."""
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("stereo"))
    if damage == "camera_high":
        cam = yaml.safe_load((dst / "camera.yaml").read_text())
        r, t = np.asarray(cam["R"]), np.asarray(cam["t"])
        centre = -r.T @ t + np.array([0.0, 0.0, 0.25])
        cam["t"] = (-r @ centre).tolist()
        (dst / "camera.yaml").write_text(yaml.safe_dump(cam))
        return
    poses = {"band_arm": [4], "band_arm_all": [1, 2, 3, 4, 5, 6], "blob_arm": [1, 4]}
    poses["cut_pose"] = [2]
    background = cv2.imread(str(sorted((dst / "background").glob("*.png"))[0]))
    for j in poses[damage]:
        path = dst / "poses" / f"pose{j}.png"
        image = cv2.imread(str(path))
        mask = cv2.imread(str(dst / "truth_masks" / f"pose{j}.png"), cv2.IMREAD_GRAYSCALE) > 0
        if damage.startswith("band"):
            image = _band(image, mask)
        elif damage == "blob_arm":
            image = _blob(image, mask)
        else:
            image = _cut(image, mask, background)
        cv2.imwrite(str(path), image)


def classify(run_dir: Path, data: Path) -> list[dict]:
    """One row per fitted subject: damage, status, worst measurement and its error, class."""
    rows = []
    with (run_dir / "summary.csv").open() as f:
        for r in csv.DictReader(f):
            truth = json.loads((data / r["subject"] / "truth.json").read_text())
            errors = {
                k: abs(float(r[k]) / truth[k] - 1) if r.get(k) else float("inf")
                for k in REPORT_KEYS
            }
            worst = max(errors, key=errors.get)
            damage = r["subject"].split("__")[-1]
            bad = errors[worst] > 0.10
            if damage == "clean":
                verdict = "ok" if r["status"] == "ok" else "FALSE ALARM"
                verdict += " (over 10 %)" if bad else ""
            else:
                verdict = ("caught" if r["status"] != "ok" else "MISSED") if bad else "within"
            rows.append(
                {
                    "subject": r["subject"],
                    "status": r["status"],
                    "worst": worst,
                    "error_pct": round(100 * errors[worst], 1),
                    "verdict": verdict,
                    "message": r["message"][:120],
                }
            )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--subjects", nargs="*")
    parser.add_argument("--damages", nargs="*", default=list(DAMAGES))
    parser.add_argument("--no-clean", action="store_true", help="fit the damaged copies only")
    parser.add_argument("--config", default=str(ROOT / "configs" / "benchmark.yaml"))
    parser.add_argument("--set", action="append", default=[])
    args = parser.parse_args()
    subjects = args.subjects or sorted(p.name for p in args.data.iterdir() if p.is_dir())
    data = args.out / "data"
    if not data.is_dir():
        data.mkdir(parents=True)
        for s in subjects:
            if not args.no_clean:
                skip = shutil.ignore_patterns("stereo")
                shutil.copytree(args.data / s, data / f"{s}__clean", ignore=skip)
            for d in args.damages:
                damage_subject(args.data / s, data / f"{s}__{d}", d)
    cmd = [sys.executable, str(ROOT / "tools" / "benchmark.py"), "--config", args.config]
    cmd += ["--data", str(data), "--out", str(args.out / "run")]
    for s in args.set:
        cmd += ["--set", s]
    subprocess.run(cmd, check=False)
    rows = classify(args.out / "run", data)
    with (args.out / "damaged.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    for r in rows:
        sys.stdout.write(
            f"{r['subject']:28s} {r['status']:9s} {r['worst']:17s} {r['error_pct']:6.1f} % "
            f"{r['verdict']:12s} {r['message']}\n"
        )
    missed = sum(r["verdict"] == "MISSED" for r in rows)
    alarms = sum(r["verdict"].startswith("FALSE") for r in rows)
    sys.stdout.write(f"missed: {missed}, false alarms: {alarms}, fitted: {len(rows)}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
