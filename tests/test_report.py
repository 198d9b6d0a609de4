"""torchfit.eval.report and tools/benchmark.py --results on tiny fake run folders (no anny, no fit).

Each test writes real files: a data folder of subjects holding only truth.json, and a run
folder laid out as torchfit.pipeline writes it (summary.csv, <subject>/measurements.json).
"""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from torchfit.errors import DataError
from torchfit.eval.plot import plot_fitted_vs_true
from torchfit.eval.report import (
    PAPER_TABLE1_PCT,
    REPORT_KEYS,
    SubjectOutcome,
    build_rows,
    collect_truths,
    describe_method,
    format_markdown,
    read_run,
    read_truth,
    summarize,
    write_csv,
    write_report,
)
from torchfit.measurements import MEASUREMENT_KEYS

REPO = Path(__file__).resolve().parents[1]

TRUTH = {
    "height_m": 1.70,
    "arm_span_m": 1.72,
    "lower_leg_m": 0.50,
    "thigh_m": 0.40,
    "upper_arm_m": 0.28,
    "forearm_m": 0.25,
    "shoulder_width_m": 0.36,
    "trunk_m": 0.55,
}


def scaled(values: dict[str, float], factor: float) -> dict[str, float]:
    return {k: v * factor for k, v in values.items()}


def make_data(root: Path, truths: dict[str, dict | None]) -> Path:
    """Subject folders with truth.json (None: a subject without one)."""
    for name, truth in truths.items():
        (root / name).mkdir(parents=True)
        if truth is not None:
            (root / name / "truth.json").write_text(json.dumps(truth))
    return root


def make_run(run_dir: Path, subjects: list[tuple], data_root: Path | None = None) -> Path:
    """A run folder: ``subjects`` = [(name, status, measurements or None, seconds, message)]."""
    run_dir.mkdir(parents=True)
    columns = ["subject", "status", *MEASUREMENT_KEYS, "final_cost", "iterations"]
    columns += ["seconds", "message"]
    with (run_dir / "summary.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        for name, status, values, seconds, message in subjects:
            row = {"subject": name, "status": status, "seconds": seconds, "message": message}
            # summary.csv is rounded on purpose: the report must read measurements.json
            row.update({k: round(v, 1) for k, v in (values or {}).items()})
            writer.writerow(row)
            if values is not None:
                (run_dir / name).mkdir()
                data = {**values, "status": status}
                (run_dir / name / "measurements.json").write_text(json.dumps(data))
    if data_root is not None:
        (run_dir / "config.yaml").write_text(yaml.safe_dump({"data": {"root": str(data_root)}}))
    return run_dir


@pytest.fixture
def folders(tmp_path):
    """Three subjects: +10 % on every measurement, -10 %, and one failed; one without truth."""
    data = make_data(
        tmp_path / "data",
        {"alice": TRUTH, "bob": scaled(TRUTH, 1.25), "carol": TRUTH, "dave": None},
    )
    run = make_run(
        tmp_path / "run",
        [
            ("alice", "template", scaled(TRUTH, 1.10), 2.0, "no fit"),
            ("bob", "template", scaled(TRUTH, 1.25 * 0.90), 4.0, "no fit"),
            ("carol", "failed", None, 0.5, "pose4.png: missing posture image"),
        ],
        data_root=data,
    )
    return data, run


def report_rows(data: Path, run: Path):
    truths, notes = collect_truths({p.name: p for p in sorted(data.iterdir())})
    rows, more = build_rows(read_run(run), truths)
    return rows, notes + more


def test_known_errors_show_as_ten_percent(folders):
    rows, notes = report_rows(*folders)
    assert [r.subject for r in rows] == ["alice", "bob", "carol"]
    assert rows[0].error_pct("height_m") == pytest.approx(10.0)
    assert rows[1].error_pct("forearm_m") == pytest.approx(-10.0)
    assert rows[2].error_pct("height_m") is None  # failed
    summary = summarize(rows)
    for key in REPORT_KEYS:
        stats = summary.stats[key]
        assert stats.n == 2
        assert stats.mean_abs_pct == pytest.approx(10.0)
        assert stats.mean_signed_pct == pytest.approx(0.0, abs=1e-9)
        assert stats.max_abs_pct == pytest.approx(10.0)
    assert summary.n_subjects == 3 and summary.n_failed == 1
    assert summary.mean_seconds == pytest.approx(3.0)  # the failed subject's time is left out
    assert summary.method == "template (no fit)"
    assert notes == ["dave: skipped, no truth.json in " + str(folders[0] / "dave")]


def test_read_run_takes_values_from_measurements_json(folders):
    outcomes = read_run(folders[1])
    alice = outcomes[0]
    assert alice.status == "template" and alice.seconds == 2.0
    assert alice.measurements["height_m"] == pytest.approx(1.87)  # summary.csv says 1.9
    assert set(alice.measurements) == set(REPORT_KEYS)
    assert outcomes[2].status == "failed" and outcomes[2].measurements == {}


def test_markdown_table(folders):
    rows, notes = report_rows(*folders)
    text = format_markdown(
        rows, summarize(rows), data="DATA", run_dir="RUN", notes=notes, plot="report.png"
    )
    lines = text.splitlines()
    assert lines[0] == "# Accuracy benchmark: template (no fit)"
    assert "Baseline, not a fit result" in text
    assert "failed: 1 (excluded from the means)" in text
    assert "| height | 2 | 10.0 | +0.0 | 10.0 | — | — | 2.1 |" in lines
    assert "| thigh | 2 | 10.0 | +0.0 | 10.0 | — | — | — |" in lines
    for key, pct in PAPER_TABLE1_PCT.items():
        assert any(line.endswith(f"| {pct:.1f} |") and key[:3] in line for line in lines)
    alice = next(line for line in lines if line.startswith("| alice |"))
    cells = [c.strip() for c in alice.strip("|").split("|")]
    assert cells[:3] == ["alice", "template", "2.0"]
    assert cells[3] == "1.700 / 1.870 (+10.0)"
    assert len(cells) == 3 + len(REPORT_KEYS)
    assert "| carol | failed | 0.5 | 1.700 / — (—)" in text
    assert "- carol: pose4.png: missing posture image" in text
    assert "## Skipped (1)" in text and "dave: skipped" in text
    assert "![fitted against true](report.png)" in text


@pytest.mark.parametrize(
    ("statuses", "method"),
    [
        ({"template": 3, "failed": 1}, "template (no fit)"),
        ({"ok": 2}, "fit"),
        ({"ok": 2, "template": 1}, "mixed: 2 fit, 1 template (no fit)"),
        ({"failed": 2}, "none (all failed)"),
    ],
)
def test_method_from_statuses(statuses, method):
    assert describe_method(statuses) == method


def test_fit_results_are_not_called_a_baseline(tmp_path):
    data = make_data(tmp_path / "data", {"alice": TRUTH})
    run = make_run(tmp_path / "run", [("alice", "ok", scaled(TRUTH, 1.02), 9.0, "converged")])
    rows, notes = report_rows(data, run)
    text = format_markdown(rows, summarize(rows), notes=notes)
    assert text.startswith("# Accuracy benchmark: fit\n")
    assert "Baseline" not in text
    assert "| height | 1 | 2.0 | +2.0 | 2.0 | — | — | 2.1 |" in text


def test_csv(folders, tmp_path):
    rows, _ = report_rows(*folders)
    path = tmp_path / "report.csv"
    write_csv(rows, path)
    with path.open(newline="") as f:
        table = list(csv.DictReader(f))
    assert [r["subject"] for r in table] == ["alice", "bob", "carol"]
    assert float(table[0]["height_m_true"]) == 1.7
    assert float(table[0]["height_m_fitted"]) == pytest.approx(1.87)
    assert float(table[0]["height_error_pct"]) == 10.0
    assert float(table[1]["shoulder_width_error_pct"]) == -10.0
    assert table[2]["status"] == "failed"
    assert table[2]["height_m_fitted"] == "" and table[2]["height_error_pct"] == ""
    assert table[2]["message"] == "pose4.png: missing posture image"


def test_png_is_written_and_not_blank(folders, tmp_path):
    rows, _ = report_rows(*folders)
    path = tmp_path / "plot.png"
    grid = plot_fitted_vs_true(rows, summarize(rows), path, panel_size=300)
    image = cv2.imread(str(path))
    assert image is not None and image.shape == grid.shape == (600, 1200, 3)
    ink = (image < 128).all(axis=2).mean()
    assert 0.005 < ink < 0.2  # axes, ticks and labels, on a mostly white page
    dots = (np.abs(image.astype(int) - (200, 90, 20)).sum(axis=2) < 30).sum()
    assert dots > 2 * 7 * 40  # two subjects in seven panels, filled discs


def test_write_report_files(folders, tmp_path):
    rows, notes = report_rows(*folders)
    paths = write_report(tmp_path / "out", rows, notes=notes)
    assert sorted(p.name for p in paths.values()) == [
        "report.csv",
        "report.md",
        "report.png",
        "report_summary.csv",
    ]
    assert all(p.is_file() and p.stat().st_size > 0 for p in paths.values())
    with paths["summary_csv"].open(newline="") as f:
        summary = {r["measurement"]: r for r in csv.DictReader(f)}
    assert float(summary["lower_leg_m"]["mean_abs_error_pct"]) == 10.0
    assert summary["lower_leg_m"]["paper_table1_pct"] == "7.600"
    assert summary["height_m"]["method"] == "template (no fit)"


# --------------------------------------------------------------------------------------------
# Error paths


def test_read_run_missing_folder_and_summary(tmp_path):
    with pytest.raises(DataError, match="run folder not found: .*nowhere"):
        read_run(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"empty/summary.csv: summary.csv not found"):
        read_run(tmp_path / "empty")


def test_read_run_bad_summary(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "summary.csv").write_text("name,height_m\nalice,1.7\n")
    with pytest.raises(DataError, match=r"summary.csv: missing columns \['subject', 'status'\]"):
        read_run(run)
    (run / "summary.csv").write_text("subject,status\n")
    with pytest.raises(DataError, match="no subjects in summary.csv"):
        read_run(run)


def test_missing_measurements_json_fails_that_subject(tmp_path):
    run = make_run(
        tmp_path / "run",
        [("alice", "template", TRUTH, 1.0, ""), ("bob", "template", TRUTH, 1.0, "")],
    )
    (run / "bob" / "measurements.json").unlink()
    alice, bob = read_run(run)
    assert alice.status == "template"
    assert bob.status == "failed"
    assert str(run / "bob" / "measurements.json") in bob.message
    assert "not found" in bob.message


def test_read_truth_errors(tmp_path):
    with pytest.raises(DataError, match=r"alice/truth.json: truth.json not found"):
        read_truth(tmp_path / "alice" / "truth.json")
    path = tmp_path / "truth.json"
    path.write_text("{not json")
    with pytest.raises(DataError, match=r"truth.json: cannot read truth.json"):
        read_truth(path)
    path.write_text(json.dumps({"height_m": -1.0}))
    with pytest.raises(DataError, match="key 'height_m' expects a positive number"):
        read_truth(path)
    data = make_data(tmp_path / "data", {"eve": {"height_m": "tall"}})
    truths, notes = collect_truths({"eve": data / "eve"})
    assert truths == {} and "eve: skipped" in notes[0] and "height_m" in notes[0]


def test_build_rows_skips_results_without_truth_and_empty_report_raises(tmp_path):
    rows, notes = build_rows([SubjectOutcome("zed", "template", "", {"height_m": 1.7}, 1.0)], {})
    assert rows == [] and notes == ["zed: skipped, no ground truth"]
    with pytest.raises(DataError, match="rows: no subject with ground truth"):
        write_report(tmp_path, rows)


def test_resumed_subjects_are_not_timed():
    rows, _ = build_rows(
        [SubjectOutcome("a", "template", "resumed: outputs on disk", {"height_m": 1.7}, 0.0)],
        {"a": TRUTH},
    )
    assert rows[0].seconds is None
    summary = summarize(rows)
    assert summary.n_timed == 0 and summary.mean_seconds is None
    assert "not measured" in format_markdown(rows, summary)


# --------------------------------------------------------------------------------------------
# tools/benchmark.py --results (no fitting)


@pytest.fixture(scope="module")
def benchmark_tool():
    spec = importlib.util.spec_from_file_location("benchmark_tool", REPO / "tools/benchmark.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_tool_report_from_results(benchmark_tool, folders, tmp_path, capsys):
    data, run = folders
    out = tmp_path / "report"
    code = benchmark_tool.main(["--results", str(run), "--out", str(out)])  # data from config
    assert code == 1  # one subject failed; the report is still written
    stdout = capsys.readouterr().out
    assert "method: template (no fit)" in stdout
    assert "3 with truth, 1 failed" in stdout
    text = (out / "report.md").read_text()
    assert f"- Data: `{data}`" in text
    assert "| lower leg | 2 | 10.0 | +0.0 | 10.0 | — | — | 7.6 |" in text
    assert (out / "report.png").stat().st_size > 10_000


def test_tool_results_needs_a_data_folder(benchmark_tool, tmp_path, capsys):
    run = make_run(tmp_path / "run", [("alice", "template", TRUTH, 1.0, "")])
    assert benchmark_tool.main(["--results", str(run)]) == 2
    err = capsys.readouterr().err
    assert f"{run / 'config.yaml'}: not found; pass --data DIR" in err
    data = make_data(tmp_path / "data", {"alice": TRUTH})
    assert benchmark_tool.main(["--results", str(run), "--data", str(data)]) == 0
    assert (run / "report.md").is_file()  # default: the report goes into the run folder


def test_tool_template_baseline(benchmark_tool, tmp_path, capsys):
    data = make_data(tmp_path / "data", {"alice": TRUTH, "bob": scaled(TRUTH, 1.1), "eve": None})
    out = tmp_path / "out"
    args = ["--template-baseline", "--config", str(REPO / "configs/demo.yaml")]
    assert benchmark_tool.main([*args, "--data", str(data), "--out", str(out)]) == 0
    assert "method: template (no fit)" in capsys.readouterr().out
    with (out / "report.csv").open(newline="") as f:
        table = list(csv.DictReader(f))
    assert [r["status"] for r in table] == ["template", "template"]
    assert table[0]["height_m_fitted"] == table[1]["height_m_fitted"]  # one template for all
    assert 1.0 < float(table[0]["height_m_fitted"]) < 2.5
    text = (out / "report.md").read_text()
    assert "Baseline, not a fit result" in text and "eve: skipped, no truth.json" in text
    assert "- config template: `mpeg4_full`" in text


def test_progress_hook_takes_a_total_or_a_list(benchmark_tool):
    bar = benchmark_tool._progress(3)
    assert bar.total == 3
    bar.close()
    assert list(benchmark_tool._progress(["a", "b"])) == ["a", "b"]
