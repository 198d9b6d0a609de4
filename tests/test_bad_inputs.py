"""Every kind of bad input in one run: each bad subject fails with a message that names the
problem, and the good subject in the same run (and in the same batches) still gets its
results. The corpus is tests/bad_inputs.py; config errors are in tests/test_pipeline.py."""

import csv
import re

import pytest
from bad_inputs import make_corpus
from template_subjects import make_template_subject
from test_pipeline import FAST, REPO, fit

from torchfit.body.model import BodyModel


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    root = tmp_path_factory.mktemp("corpus")
    make_template_subject(root / "good", BodyModel("mpeg4_full"), scale=1.0, seed=1)
    return root, make_corpus(root, root / "good")


def test_each_bad_subject_fails_with_its_reason_and_the_good_one_is_fitted(corpus, tmp_path):
    root, expected = corpus
    out = tmp_path / "run"
    # batches of 3: the good subject shares its batch with bad ones
    proc = fit(
        "--config", REPO / "configs/demo.yaml", "--data", root, "--out", out, *FAST,
        "--set", "fit.batch_size=3", "--set", "output.overlays=false",
    )  # fmt: skip
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    rows = {r["subject"]: r for r in csv.DictReader((out / "summary.csv").open())}
    assert set(rows) == {"good", *expected}
    assert rows["good"]["status"] == "ok", rows["good"]["message"]
    assert float(rows["good"]["height_m"]) > 1.0
    assert (out / "good" / "measurements.json").is_file()
    for name, pattern in expected.items():
        assert rows[name]["status"] == "failed", (name, rows[name]["message"])
        assert re.search(pattern, rows[name]["message"]), (name, rows[name]["message"])
        assert not (out / name / "measurements.json").exists()
