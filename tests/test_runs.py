"""Runs you can trust: resume by fingerprint, atomic outputs (a run killed at any moment and
run again ends as a clean run), faults of the environment as one-line errors with documented
exit codes, through tools/fit.py in fresh processes."""

import csv
import importlib.util
import io
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from template_subjects import make_template_subject

from torchfit.body.model import BodyModel

REPO = Path(__file__).resolve().parents[1]
# a short fit, one subject per batch (batch invariance is tested with the fit itself)
FAST = (
    "--set",
    "fit.stages=[{name: all, scales: [all], joints: true, root: true, max_iter: 2}]",
    "--set",
    "fit.contour_stride=3",
    "--set",
    "fit.batch_size=1",
)
#: files of the run folder whose bytes hold wall-clock time (compared without it)
WALL_CLOCK = {"summary.csv": "seconds column", "params.json": "seconds key"}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("runs_data")
    model = BodyModel("mpeg4_full")
    make_template_subject(root / "alice", model, scale=1.0, seed=1)
    make_template_subject(root / "bob", model, scale=1.05, seed=2, azimuth_deg=-60.0)
    return root


def command(dataset, out, *extra):
    return [
        sys.executable,
        str(REPO / "tools" / "fit.py"),
        *("--config", str(REPO / "configs" / "demo.yaml")),
        *("--data", str(dataset), "--out", str(out)),
        *FAST,
        *map(str, extra),
    ]


def fit(dataset, out, *extra, **kwargs):
    return subprocess.run(
        command(dataset, out, *extra), capture_output=True, text=True, timeout=600, **kwargs
    )


@pytest.fixture(scope="module")
def clean(dataset, tmp_path_factory):
    """A clean run of both subjects."""
    out = tmp_path_factory.mktemp("clean") / "run"
    proc = fit(dataset, out)
    assert proc.returncode == 0, proc.stderr
    return out


def snapshot(out: Path) -> dict[str, bytes]:
    """Every file of a run folder but tb/, with the wall-clock fields taken out."""
    files = {}
    for path in sorted(out.rglob("*")):
        rel = path.relative_to(out).as_posix()
        if not path.is_file() or rel.startswith("tb/"):
            continue
        data = path.read_bytes()
        if rel == "config.yaml":  # the same but for where it is
            doc = yaml.safe_load(data)
            assert doc["run"].pop("out") == str(out)
            data = json.dumps(doc).encode()
        elif path.name == "params.json":
            doc = json.loads(data)
            assert isinstance(doc.pop("seconds"), float)
            data = json.dumps(doc).encode()
        elif path.name == "summary.csv":
            rows = list(csv.DictReader(io.StringIO(data.decode())))
            for row in rows:
                assert float(row.pop("seconds")) >= 0
            data = json.dumps(rows).encode()
        files[rel] = data
    return files


def assert_same_outputs(out: Path, reference: Path) -> None:
    got, want = snapshot(out), snapshot(reference)
    assert sorted(got) == sorted(want)
    different = [name for name in want if got[name] != want[name]]
    assert different == []


def count_files(out: Path) -> int:
    if not out.is_dir():
        return 0
    return sum(
        1
        for p in out.rglob("*")
        if p.is_file() and not p.name.endswith(".tmp") and "tb" not in p.relative_to(out).parts
    )


def kill_after(dataset, out: Path, n_files: int) -> int:
    """Start a run, SIGKILL it once ``n_files`` output files are in place; the count then."""
    proc = subprocess.Popen(
        command(dataset, out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        while count_files(out) < n_files:
            assert proc.poll() is None, f"the run ended before writing {n_files} files"
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    return count_files(out)


def check_kill_and_resume(dataset, clean, out, n_files):
    kill_after(dataset, out, n_files)
    again = fit(dataset, out)
    assert again.returncode == 0, again.stderr
    assert "Traceback" not in again.stderr
    assert not [p for p in out.rglob("*.tmp")], "temporary files left"
    assert_same_outputs(out, clean)


def test_killed_run_resumes_to_the_clean_outputs(dataset, clean, tmp_path):
    # killed in the middle of the first subject's files (its overlays and meshes)
    check_kill_and_resume(dataset, clean, tmp_path / "run", 12)


@pytest.mark.slow
@pytest.mark.parametrize("fraction", [0.0, 0.25, 0.5, 0.75, 0.95])
def test_killed_at_five_moments_resumes_to_the_clean_outputs(dataset, clean, tmp_path, fraction):
    # 0.0: after config.yaml only; 0.5: about when the first subject is done; 0.95: near the end
    total = count_files(clean)
    check_kill_and_resume(dataset, clean, tmp_path / "run", max(1, int(fraction * total)))


def test_rerun_keeps_finished_subjects_and_refits_a_changed_template(dataset, clean, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(clean, out)
    stamp = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    again = fit(dataset, out)
    assert again.returncode == 0, again.stderr
    assert again.stdout.count("kept from an earlier run") == 2
    assert (out / "summary.csv").read_bytes() == (clean / "summary.csv").read_bytes()
    changed = [p for p, t in stamp.items() if p.stat().st_mtime_ns != t and p.parent.name != "run"]
    assert changed == []  # only config.yaml and summary.csv are rewritten

    simple = fit(dataset, out, "--set", "model.template=mpeg4_simple")
    assert simple.returncode == 0, simple.stderr
    assert "kept from an earlier run" not in simple.stdout
    assert "refitting (template changed)" in simple.stderr
    for name in ("alice", "bob"):
        params = json.loads((out / name / "params.json").read_text())
        assert params["template"] == "mpeg4_simple"
        before = json.loads((clean / name / "fingerprint.json").read_text())
        after = json.loads((out / name / "fingerprint.json").read_text())
        assert after["template"] != before["template"]
        assert after["inputs"] == before["inputs"] and after["config"] == before["config"]
    # the rows of summary.csv are those of the new fits, complete
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert all(r["final_cost"] and r["iterations"] == "2" and r["message"] for r in rows)


# --------------------------------------------------------------------------------------------
# Faults of the environment: one line, a documented exit code, no traceback, and the subjects
# finished before complete


def assert_one_line_error(proc, code: int, *words: str) -> str:
    assert proc.returncode == code, proc.stderr
    assert "Traceback" not in proc.stderr
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, proc.stderr
    for word in words:
        assert word in errors[0], errors[0]
    return errors[0]


def test_out_below_a_regular_file_is_exit_3(dataset, tmp_path):
    (tmp_path / "file").write_text("not a folder")
    proc = fit(dataset, tmp_path / "file" / "run")
    assert_one_line_error(proc, 3, str(tmp_path / "file" / "run"), "Not a directory")


def _alice_done(clean: Path, out: Path) -> dict[str, bytes]:
    """A run folder where alice is finished and bob never started; alice's files."""
    shutil.copytree(clean, out)
    shutil.rmtree(out / "bob")
    return {p.name: p.read_bytes() for p in (out / "alice").rglob("*") if p.is_file()}


def _limit_file_size(limit: int):
    def preexec():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes fail with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return preexec


def test_full_disk_is_exit_3_and_keeps_finished_subjects(dataset, clean, tmp_path):
    out = tmp_path / "run"
    alice = _alice_done(clean, out)
    # files may grow to half an overlay: config.yaml, summary.csv and json fit, overlays not
    limit = min(p.stat().st_size for p in (clean / "bob").glob("overlay_pose*.png")) // 2
    assert limit > max(len(b) for n, b in alice.items() if n.endswith(".json"))
    proc = fit(dataset, out, preexec_fn=_limit_file_size(limit))
    assert_one_line_error(proc, 3, str(out / "bob"), "File too large")
    assert {p.name: p.read_bytes() for p in (out / "alice").rglob("*") if p.is_file()} == alice
    assert not (out / "bob" / "fingerprint.json").exists()
    assert not list(out.rglob("*.tmp"))
    # with room again, the run completes as a clean one
    again = fit(dataset, out)
    assert again.returncode == 0, again.stderr
    assert_same_outputs(out, clean)


def _mount(*args: str) -> bool:
    return subprocess.run(["mount", *args], capture_output=True).returncode == 0


@pytest.fixture
def tmpfs(tmp_path):
    """A small tmpfs (skips where mounting is not permitted)."""
    point = tmp_path / "mnt"
    point.mkdir()
    if shutil.which("mount") is None or not _mount("-t", "tmpfs", "-o", "size=8m", "x", str(point)):
        pytest.skip("cannot mount a tmpfs here")
    yield point
    subprocess.run(["umount", "-l", str(point)], capture_output=True)


def test_read_only_out_is_exit_3(dataset, clean, tmpfs):
    out = tmpfs / "run"
    alice = _alice_done(clean, out)
    if not _mount("-o", "remount,ro", str(tmpfs)):
        pytest.skip("cannot remount read-only")
    proc = fit(dataset, out)
    assert_one_line_error(proc, 3, str(out), "Read-only file system")
    assert {p.name: p.read_bytes() for p in (out / "alice").rglob("*") if p.is_file()} == alice


def test_no_space_left_is_exit_3_and_keeps_finished_subjects(dataset, clean, tmpfs):
    out = tmpfs / "run"
    alice = _alice_done(clean, out)
    # leave about 48 kB free: config.yaml and summary.csv fit, bob's overlays do not
    stat = os.statvfs(tmpfs)
    filler = stat.f_bavail * stat.f_frsize - 48 * 1024
    with open(tmpfs / "filler", "wb") as fh:
        fh.write(b"\0" * filler)
    proc = fit(dataset, out, "--set", "output.tensorboard=false")
    assert_one_line_error(proc, 3, str(out / "bob"), "No space left on device")
    assert {p.name: p.read_bytes() for p in (out / "alice").rglob("*") if p.is_file()} == alice
    assert not list(out.rglob("*.tmp"))


@pytest.fixture(scope="module")
def fit_tool():
    spec = importlib.util.spec_from_file_location("fit_tool", REPO / "tools" / "fit.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize(
    ("extra", "code", "words"),
    [
        (("--data", "nothing"), 4, ("not found", "nothing")),
        (("--set", "model.template=no_such_template"), 2, ("no_such_template",)),
        (("--set", "solver.max_iter=many"), 2, ("solver.max_iter", "an integer", "'many'")),
        (("--set", "fit.no_such_key=1"), 2, ("unknown key 'fit.no_such_key'",)),
        (("--set", "fit.batch_size=[1]"), 2, ("fit.batch_size", "an integer")),
    ],
)
def test_errors_before_fitting_leave_no_run_folder(
    fit_tool, dataset, tmp_path, capsys, extra, code, words
):
    out = tmp_path / "run"
    argv = ["--config", str(REPO / "configs" / "demo.yaml"), "--data", str(dataset)]
    assert fit_tool.main([*argv, "--out", str(out), *FAST, *extra]) == code
    errors = [line for line in capsys.readouterr().err.splitlines() if line.startswith("error")]
    assert len(errors) == 1 and all(w in errors[0] for w in words), errors
    assert not out.exists()
