"""The Ray executor: the same outputs, summary, exit code and resume as a local run, on a real
local Ray cluster of two workers, through tools/fit.py in fresh processes, and the thread counts
of both executors. One short run on a cluster is in the default test run (the ``dev`` extra
installs Ray); the resume, the retried worker and the whole demo on Ray are marked slow
(starting a cluster takes 10-20 s on a busy two-core machine)."""

import csv
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from torchfit.config.loader import load_config
from torchfit.config.schema import RunConfig
from torchfit.pipeline.fingerprint import config_digest

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "data" / "demo"
# a short fit: segmentation, two iterations, every output
FAST = (
    "--set",
    "fit.stages=[{name: all, scales: [all], joints: true, root: true, max_iter: 2}]",
    "--set",
    "fit.contour_stride=3",
)
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
#: the tests that start a Ray cluster need the optional extra
needs_ray = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None,
    reason='needs Ray: pip install -e ".[ray]"',
)


def fit(data: Path, out: Path, *extra: str, timeout: float = 600, **kwargs):
    command = [
        sys.executable,
        str(REPO / "tools" / "fit.py"),
        *("--config", str(REPO / "configs" / "demo.yaml")),
        *("--data", str(data), "--out", str(out)),
        *extra,
    ]
    return subprocess.run(
        command, capture_output=True, text=True, timeout=timeout, env=ENV, **kwargs
    )


def measurements(out: Path) -> dict[str, dict]:
    return {
        p.parent.name: json.loads(p.read_text()) for p in sorted(out.glob("*/measurements.json"))
    }


def summary(out: Path) -> list[dict]:
    """summary.csv without its wall-clock column."""
    with (out / "summary.csv").open() as fh:
        return [{k: v for k, v in row.items() if k != "seconds"} for row in csv.DictReader(fh)]


def assert_same_summary(a: list[dict], b: list[dict]) -> None:
    """The same rows; numbers to 1e-9 (relative): thread counts may move the last bits."""
    assert [r.keys() for r in a] == [r.keys() for r in b]
    for row_a, row_b in zip(a, b, strict=True):
        for key, value in row_a.items():
            try:
                x, y = float(value), float(row_b[key])
            except ValueError:
                assert value == row_b[key], key
                continue
            assert abs(x - y) <= 1e-9 * max(1.0, abs(x)), (row_a["subject"], key, x, y)


def assert_same_measurements(a: dict, b: dict, tol: float = 1e-9) -> None:
    assert a.keys() == b.keys()
    for name in a:
        assert a[name]["status"] == b[name]["status"], name
        for key, value in a[name].items():
            if isinstance(value, float):
                assert abs(value - b[name][key]) <= tol, (name, key, value, b[name][key])


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """The two demo subjects and a third whose posture image is not an image."""
    root = tmp_path_factory.mktemp("ray_data")
    for name in ("subject_000", "subject_001"):
        shutil.copytree(DEMO / name, root / name)
    shutil.copytree(DEMO / "subject_001", root / "subject_002")
    (root / "subject_002" / "poses" / "pose3.png").write_bytes(b"not a png")
    return root


@pytest.fixture(scope="module")
def local(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "run"
    proc = fit(data, out, *FAST)
    assert proc.returncode == 1, proc.stderr  # subject_002 failed
    return out


@pytest.fixture(scope="module")
def on_ray(data, tmp_path_factory):
    """The same run on a local Ray cluster of two workers (10-20 s to start on a busy two-core
    machine)."""
    out = tmp_path_factory.mktemp("ray") / "run"
    proc = fit(data, out, *FAST, "--executor", "ray", "--workers", "2")
    return out, proc


@needs_ray
def test_ray_run_equals_the_local_run(on_ray, local):
    out, proc = on_ray
    assert proc.returncode == 1, proc.stderr  # the same exit code: one subject failed
    assert "2 workers x 1 torch threads" in proc.stderr
    rows = summary(out)
    assert_same_summary(rows, summary(local))
    assert [r["status"] == "failed" for r in rows] == [False, False, True]
    assert "pose3" in rows[2]["message"]
    assert_same_measurements(measurements(out), measurements(local))
    for name in ("subject_000", "subject_001"):
        files = sorted(p.relative_to(local / name) for p in (local / name).rglob("*"))
        assert sorted(p.relative_to(out / name) for p in (out / name).rglob("*")) == files
    assert not (out / "subject_002" / "fingerprint.json").exists()
    # one TensorBoard folder: the event files of the tasks (one per batch)
    assert len(list((out / "tb").glob("events.out.tfevents.*"))) == 2


@pytest.mark.slow  # three more runs, two of them on a Ray cluster
@needs_ray
def test_a_run_resumes_across_executors(data, local, on_ray, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(on_ray[0], out)
    # a local rerun keeps the Ray run's subjects ...
    proc = fit(data, out, *FAST)
    assert proc.returncode == 1, proc.stderr
    assert proc.stdout.count("kept from an earlier run") == 2
    # ... and a Ray rerun refits only the subject whose outputs are incomplete
    (out / "subject_001" / "fingerprint.json").unlink()
    before = (out / "subject_000" / "params.json").stat().st_mtime_ns
    proc = fit(data, out, *FAST, "--executor", "ray", "--workers", "2")
    assert proc.returncode == 1, proc.stderr
    assert proc.stdout.count("kept from an earlier run") == 1
    assert (out / "subject_000" / "params.json").stat().st_mtime_ns == before
    assert (out / "subject_001" / "fingerprint.json").is_file()
    assert_same_measurements(measurements(out), measurements(local))


@pytest.mark.slow
@needs_ray
def test_demo_on_ray_with_two_workers_equals_the_local_demo(tmp_path):
    """The README demo, whole: ``--executor ray --workers 2`` against the local run."""
    local_out, ray_out = tmp_path / "local", tmp_path / "ray"
    proc = fit(DEMO, local_out)
    assert proc.returncode == 0, proc.stderr
    proc = fit(DEMO, ray_out, "--executor", "ray", "--workers", "2")
    assert proc.returncode == 0, proc.stderr
    assert_same_summary(summary(ray_out), summary(local_out))
    assert_same_measurements(measurements(ray_out), measurements(local_out))


def _task_processes() -> list[int]:
    """Process ids of Ray workers running a fit task (Ray names them after the function)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmdline = (proc / "cmdline").read_bytes()
        except OSError:
            continue
        if cmdline.startswith(b"ray::_fit_task"):
            pids.append(int(proc.name))
    return pids


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds the Ray workers in /proc")
@needs_ray
def test_a_killed_worker_has_its_batch_retried(data, local, tmp_path):
    out = tmp_path / "run"
    command = [
        sys.executable,
        str(REPO / "tools" / "fit.py"),
        *("--config", str(REPO / "configs" / "demo.yaml")),
        *("--data", str(data), "--out", str(out)),
        *FAST,
        *("--executor", "ray", "--workers", "2"),
    ]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV)
    killed = None
    deadline = time.monotonic() + 300
    while killed is None and time.monotonic() < deadline and proc.poll() is None:
        pids = _task_processes()
        if pids:
            killed = pids[0]
            os.kill(killed, signal.SIGKILL)
        time.sleep(0.2)
    stdout, stderr = proc.communicate(timeout=600)
    assert killed is not None, "no fit task was seen running"
    assert proc.returncode == 1, stderr.decode()
    assert [r["status"] == "failed" for r in summary(out)] == [False, False, True]
    assert_same_measurements(measurements(out), measurements(local))


def test_without_ray_the_executor_says_how_to_install_it(tmp_path):
    # Python's own way to make a module absent: None in sys.modules fails its import
    code = (
        "import sys; sys.modules['ray'] = None; "
        f"sys.argv = ['fit.py', '--config', {str(REPO / 'configs' / 'demo.yaml')!r}, "
        f"'--out', {str(tmp_path / 'run')!r}, '--executor', 'ray']; "
        f"import runpy; runpy.run_path({str(REPO / 'tools' / 'fit.py')!r}, run_name='__main__')"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=ENV, timeout=120
    )
    assert proc.returncode == 2
    assert "ray is not installed" in proc.stderr
    assert 'pip install "torchfit[ray]"' in proc.stderr
    assert not (tmp_path / "run").exists()


def test_the_executor_does_not_change_the_fingerprint():
    config = load_config(REPO / "configs" / "demo.yaml")
    ray = load_config(
        REPO / "configs" / "demo.yaml",
        ["run.executor=ray", "run.address=auto", "run.workers=3", "run.num_threads=2"],
    )
    assert config_digest(ray) == config_digest(config)


@pytest.mark.parametrize("cpus", [1, 2, 7, 16])
@pytest.mark.parametrize(("workers", "threads"), [(None, None), (2, None), (None, 2), (3, 1)])
def test_workers_times_threads_never_exceed_the_cpus(cpus, workers, threads):
    from torchfit.pipeline.ray_executor import plan

    w, t = plan(RunConfig(workers=workers, num_threads=threads), cpus)
    assert w >= 1 and t >= 1
    assert w == (workers or max(1, cpus // (threads or 1)))
    assert t == (threads or max(1, cpus // w))
    if threads is None:  # the default threads fit the CPUs
        assert w * t <= max(cpus, w)


@pytest.mark.parametrize(
    ("num_threads", "workers", "omp", "expected"),
    [
        (None, None, None, 8),
        (None, 2, None, 4),
        (None, 3, None, 2),
        (None, 16, None, 1),
        (3, 2, None, 3),
        (None, None, "2", 2),
        (None, 4, "6", 2),
        (5, None, "1", 5),
    ],
)
def test_local_threads_share_the_cpus(monkeypatch, num_threads, workers, omp, expected):
    from torchfit.pipeline.runtime import local_threads

    if omp is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", omp)
    run = RunConfig(num_threads=num_threads, workers=workers)
    assert local_threads(run, cores=8) == expected


def test_a_run_sets_its_thread_count(monkeypatch):
    import torch

    from torchfit.pipeline.runtime import apply_runtime, cpu_count

    before = torch.get_num_threads()
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    try:
        apply_runtime(RunConfig(workers=cpu_count()))
        assert torch.get_num_threads() == 1
        apply_runtime(RunConfig(num_threads=2))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_device_torch_cannot_use_is_a_config_error():
    import torch

    from torchfit.errors import ConfigError
    from torchfit.pipeline.runtime import apply_runtime

    before = torch.get_num_threads()
    try:
        with pytest.raises(ConfigError, match="run.device"):
            apply_runtime(RunConfig(device="tpu"))
        if not torch.cuda.is_available():
            with pytest.raises(ConfigError, match="no CUDA device"):
                apply_runtime(RunConfig(device="cuda"))
    finally:
        torch.set_num_threads(before)


@needs_ray
@pytest.mark.slow
@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("run.num_threads=64", "largest Ray node has"),
        ("run.device=cuda", "no node of the Ray cluster has a GPU"),
    ],
)
def test_a_task_no_node_can_run_is_exit_2(tmp_path, setting, message):
    if setting == "run.device=cuda":
        import torch

        if torch.cuda.is_available():
            pytest.skip("this machine has a GPU")
    proc = fit(DEMO, tmp_path / "run", "--executor", "ray", "--set", setting, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr
    assert not (tmp_path / "run").exists()  # nothing written
