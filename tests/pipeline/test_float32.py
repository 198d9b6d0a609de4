"""The demo in float32 on the CPU (``run.device: cpu, run.dtype: float32``): the code path a GPU
run takes for its dtype, checked against the float64 run."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
#: The measured float32 - float64 difference on the demo is 3.9 mm (subject_000, arm span) and
#: 4.9 mm (subject_001, shoulder width). It cannot be held to a millimetre: a float64 fit started
#: 1e-12 away from the template moves dev measurements by up to 4 cm (benchmarks/RESULTS.md,
#: "float32"). This bound catches a broken float32 path, which moves them by far more.
TOLERANCE_M = 0.01


def fit(out: Path, *extra: str) -> subprocess.CompletedProcess:
    command = [
        sys.executable,
        str(REPO / "tools" / "fit.py"),
        *("--config", str(REPO / "configs" / "demo.yaml"), "--out", str(out)),
        *("--set", "output.overlays=false", "--set", "output.tensorboard=false"),
        *extra,
    ]
    return subprocess.run(command, capture_output=True, text=True, env=ENV, timeout=900)


@pytest.mark.slow
def test_demo_in_float32_measures_as_float64(tmp_path):
    results = {}
    for dtype in ("float64", "float32"):
        proc = fit(tmp_path / dtype, "--set", f"run.dtype={dtype}", "--set", "run.device=cpu")
        assert proc.returncode == 0, proc.stderr
        results[dtype] = {
            p.parent.name: json.loads(p.read_text())
            for p in sorted((tmp_path / dtype).glob("*/measurements.json"))
        }
    assert results["float32"].keys() == results["float64"].keys() == {"subject_000", "subject_001"}
    for name, f64 in results["float64"].items():
        f32 = results["float32"][name]
        # fitted, whatever the judge says (a status is the judge's call on the measurements,
        # not a float32 question)
        assert f32["status"] != "failed" and f64["status"] != "failed"
        for key, value in f64.items():
            if isinstance(value, float):
                assert abs(f32[key] - value) <= TOLERANCE_M, (name, key, f32[key], value)
