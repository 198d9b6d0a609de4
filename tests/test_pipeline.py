"""tools/fit.py end to end on subjects rendered from the template (no ../shared needed)."""

import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from template_subjects import make_template_subject

from torchfit.body.model import BodyModel

REPO = Path(__file__).resolve().parents[1]
# a short fit: the pipeline is under test here, not the accuracy (see tests/test_fitting.py)
FAST = (
    "--set",
    "fit.stages=[{name: all, scales: [all], joints: true, root: true, max_iter: 2}]",
    "--set",
    "fit.contour_stride=3",
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("dataset")
    model = BodyModel("mpeg4_full")
    make_template_subject(root / "alice", model, scale=1.0, seed=1)
    make_template_subject(root / "bob", model, scale=1.05, seed=2, azimuth_deg=-60.0)
    shutil.copytree(root / "alice", root / "broken")
    (root / "broken" / "poses" / "pose4.png").unlink()
    return root


def tool(script: str, *args, cwd=REPO):
    """Run ``tools/<script>`` with ``args`` in a fresh process."""
    return subprocess.run(
        [sys.executable, str(REPO / "tools" / script), *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


def fit(*args, cwd=REPO):
    return tool("fit.py", *args, cwd=cwd)


def demo_fit(dataset, out, *settings):
    """``tools/fit.py`` with the demo config on ``dataset`` into ``out``, short, with
    ``--set`` ``settings``."""
    sets = [a for key in settings for a in ("--set", key)]
    return fit(
        "--config", REPO / "configs/demo.yaml", "--data", dataset, "--out", out, *sets, *FAST
    )


def test_fit_cli_writes_outputs_and_survives_a_bad_subject(dataset, tmp_path):
    out = tmp_path / "run"
    proc = demo_fit(dataset, out, "run.name=test")
    assert proc.returncode == 1, proc.stderr  # one subject failed
    rows = {r["subject"]: r for r in csv.DictReader((out / "summary.csv").open())}
    assert set(rows) == {"alice", "bob", "broken"}
    assert rows["broken"]["status"] == "failed"
    assert "pose4" in rows["broken"]["message"]
    for name in ("alice", "bob"):
        assert rows[name]["status"] == "ok", rows[name]["message"]
        folder = out / name
        for f in (
            "measurements.json",
            "params.json",
            "model.urdf",
            "model.bvh",
            "model.glb",
            *(f"overlay_pose{i}.png" for i in range(1, 7)),
        ):
            assert (folder / f).is_file(), f
        params = json.loads((folder / "params.json").read_text())
        assert set(params["poses"]) == {f"pose{i}" for i in range(1, 7)}
    assert list((out / "tb").glob("events.out.tfevents*")), "no TensorBoard event file"
    resolved = yaml.safe_load((out / "config.yaml").read_text())
    assert resolved["run"]["name"] == "test"
    assert resolved["data"]["root"] == str(dataset)

    # a second run resumes: finished subjects are not redone
    before = (out / "alice" / "measurements.json").stat().st_mtime_ns
    again = fit("--config", REPO / "configs/demo.yaml", "--data", dataset, "--out", out, *FAST)
    assert again.stdout.count("kept from an earlier run") == 2, again.stdout
    assert (out / "alice" / "measurements.json").stat().st_mtime_ns == before


def test_subjects_of_two_image_sizes_share_a_run(tmp_path):
    """Cameras of two resolutions in one dataset: each size is batched on its own (a batch
    stacks its images), and every subject is fitted."""
    from torchfit.io.dataset import load_dataset
    from torchfit.pipeline.run import batches

    root = tmp_path / "data"
    model = BodyModel("mpeg4_full")
    make_template_subject(root / "a_small", model, seed=1)
    make_template_subject(root / "b_large", model, scale=1.05, seed=2, image_size=(480, 384))
    shutil.copytree(root / "a_small", root / "c_small")
    subjects = load_dataset(root)
    grouped = batches(subjects, 2)
    assert [[s.name for s in b] for b in grouped] == [["a_small", "c_small"], ["b_large"]]
    out = tmp_path / "run"
    proc = demo_fit(root, out, "fit.batch_size=3", "output.overlays=false")
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["subject"] for r in rows] == ["a_small", "b_large", "c_small"]  # dataset order
    assert all(r["status"] == "ok" for r in rows), [r["message"] for r in rows]


def test_fit_cli_config_errors(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("solver:\n  max_iters: 3\n")
    proc = fit("--config", bad)
    assert proc.returncode == 2
    assert "unknown key 'solver.max_iters'" in proc.stderr and str(bad) in proc.stderr
    proc = fit("--config", REPO / "configs/demo.yaml", "--data", tmp_path / "nothing")
    assert proc.returncode == 4  # the dataset is missing
    assert "not found" in proc.stderr


@pytest.mark.parametrize(
    ("keys", "message"),
    [
        (
            ["fit.prior.pose_weight=0.5", "fit.prior.pose_joints=[elbow_flex]"],
            "fit.prior.pose_joints: ['elbow_flex'] name no joint",
        ),
        (["fit.prior.name=nope"], "fit.prior.name: unknown prior 'nope'"),
        (["fit.free_joints={pose1: [l_elbow_flex]}"], "unknown joint DOFs ['l_elbow_flex']"),
        (
            ["fit.stages=[{name: a, scales: [legz], joints: true, root: true}]"],
            "unknown scale group 'legz'",
        ),
    ],
)
def test_fit_cli_stops_on_a_name_the_template_or_prior_lacks(dataset, tmp_path, keys, message):
    out = tmp_path / "run"
    sets = [a for k in keys for a in ("--set", k)]
    proc = fit("--config", REPO / "configs/demo.yaml", "--data", dataset, "--out", out, *sets)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert message in proc.stderr
    assert not (out / "summary.csv").exists()  # stopped before any subject was fitted


def test_invalid_subjects_take_no_valid_subject_s_place_in_a_batch(dataset):
    """A valid subject's batch is the one it has without the invalid ones (its result does
    not move with them, not even in the last digits)."""
    from torchfit.io.dataset import load_dataset
    from torchfit.pipeline.run import batches

    subjects = load_dataset(dataset)  # alice, bob, broken (pose4.png missing)
    assert [s.name for s in subjects] == ["alice", "bob", "broken"]
    subjects = [subjects[0], subjects[2], subjects[1]]
    grouped = batches(subjects, 2)
    assert [[s.name for s in b] for b in grouped] == [["alice", "bob"], ["broken"]]


def test_measure_stereo_cli_says_when_no_subject_has_a_pair(dataset, tmp_path):
    # the template subjects have no stereo/ folder: the tool says so and writes nothing,
    # instead of a run of skipped subjects
    out = tool(
        "measure_stereo.py",
        *("--config", REPO / "configs" / "stereo.yaml"),
        *("--data", dataset, "--out", tmp_path / "stereo"),
    )
    assert out.returncode == 2, out.stderr
    assert f"no subject in {dataset} has a usable stereo/ folder" in out.stderr
    assert not (tmp_path / "stereo").exists()


class _Bar:
    """A progress bar that records what it is told (the tqdm calls the pipeline makes)."""

    made: list["_Bar"] = []

    def __init__(self, desc, total):
        self.desc, self.total, self.n, self.postfix, self.closed = desc, total, 0, {}, False
        _Bar.made.append(self)

    def update(self, n=1):
        self.n += n

    def set_postfix(self, **kw):
        self.postfix = kw

    def close(self):
        self.closed = True


def test_progress_per_subject_and_per_solver_iteration(dataset, tmp_path):
    from torchfit.config import load_config, replace_keys
    from torchfit.pipeline import run

    config = load_config(REPO / "configs/demo.yaml", list(FAST[1::2]))
    config = replace_keys(
        config,
        {"data.root": str(dataset), "data.subjects": ("alice",), "output.overlays": False},
    )
    _Bar.made = []
    subjects = []
    run(
        config,
        tmp_path / "run",
        progress=lambda n: subjects.append(_Bar("subjects", n)) or subjects[-1],
        stage_progress=lambda desc, n: _Bar(desc, n),
    )
    assert subjects[0].total == 1 and subjects[0].n == 1 and subjects[0].closed
    stage = [b for b in _Bar.made if b.desc.startswith("stage1_all")]
    assert len(stage) == 1 and stage[0].closed
    assert 1 <= stage[0].n <= stage[0].total == 2  # one update per solver iteration
    assert float(stage[0].postfix["cost"]) > 0 and stage[0].postfix["running"].endswith("/1")


def test_params_and_overlay_carry_the_knees_mark(dataset, tmp_path):
    """With fit.bends on, params.json records posture 3's knee mark and the model's knee,
    and the overlay draws them (a magenta cross, a green dot) where it records them."""
    import cv2
    import numpy as np

    from torchfit.viz.overlay import fit_overlay

    out = tmp_path / "run"
    proc = demo_fit(
        dataset, out, "data.subjects=[alice]", "fit.bends.weight=1.0", "output.tensorboard=false"
    )
    assert proc.returncode == 0, proc.stderr
    params = json.loads((out / "alice" / "params.json").read_text())
    knee = params["bends"]["pose3"]["l_knee"]
    assert set(knee) == {"target_px", "model_px", "offset_px"}
    assert knee["target_px"] is not None  # the template subject's knee is found
    u, v = (int(round(c)) for c in knee["target_px"])
    overlay = cv2.imread(str(out / "alice" / "overlay_pose3.png"))[..., ::-1]  # RGB
    # the cross's arms, beyond the model knee's dot (the two are within a pixel here)
    arms = [(v, u - 6), (v, u + 6)]
    assert all(np.array_equal(overlay[p], [255, 0, 255]) for p in arms)
    # drawn by the overlay itself, not the person's magenta outline passing there
    blank = np.zeros((40, 40, 3), np.uint8)
    empty = np.zeros((40, 40), bool)
    drawn = fit_overlay(blank, empty, empty, "", None, [((20.0, 20.0), (10.0, 30.0))])
    bare = fit_overlay(blank, empty, empty, "", None)
    for p in [(20, 15), (20, 25), (15, 20), (25, 20)]:
        assert np.array_equal(drawn[p], [255, 0, 255]) and not bare[p].any()
    assert np.array_equal(drawn[30, 10], [0, 200, 0])  # the model's knee
