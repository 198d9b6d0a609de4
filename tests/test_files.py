"""Atomic output files, input digests, complete-file checks before decoding, the fingerprint of
a subject's outputs and config paths relative to the config file."""

import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchfit.config import load_config, replace_keys
from torchfit.errors import DataError, OutputError
from torchfit.io.files import (
    copy_atomic,
    files_digest,
    make_dirs,
    remove_temporary,
    write_atomic,
)
from torchfit.io.images import read_image, read_mask, write_image

REPO = Path(__file__).resolve().parents[1]


def test_write_atomic_replaces_whole_files_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "a" / "b.json"
    write_atomic(path, "first")
    write_atomic(path, b"second")
    assert path.read_text() == "second"
    assert sorted(p.name for p in path.parent.iterdir()) == ["b.json"]
    (tmp_path / "plain").write_text("")  # the permissions open() gives
    assert path.stat().st_mode == (tmp_path / "plain").stat().st_mode
    copy_atomic(path, tmp_path / "c.json")
    assert (tmp_path / "c.json").read_bytes() == b"second"


def test_write_errors_name_the_path_and_the_reason(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match=r"cannot create folder .*file/sub: Not a directory"):
        write_atomic(tmp_path / "file" / "sub" / "x.json", "{}")
    with pytest.raises(OutputError, match="Not a directory"):
        make_dirs(tmp_path / "file" / "sub")
    with pytest.raises(DataError, match="cannot read .*missing"):
        copy_atomic(tmp_path / "missing", tmp_path / "y")


def test_remove_temporary_clears_what_a_crash_left(tmp_path):
    (tmp_path / ".summary.csv.abc123.tmp").write_text("part")
    (tmp_path / "summary.csv").write_text("whole")
    remove_temporary(tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["summary.csv"]


def test_files_digest_follows_names_and_contents(tmp_path):
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    a.write_bytes(b"1")
    b.write_bytes(b"2")
    first = files_digest([a, b], tmp_path)
    assert files_digest([a, b], tmp_path) == first
    assert files_digest([b, a], tmp_path) != first
    b.write_bytes(b"3")
    assert files_digest([a, b], tmp_path) != first
    with pytest.raises(DataError, match="cannot read"):
        files_digest([tmp_path / "nope"])


@pytest.fixture
def png(tmp_path):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, size=(40, 50, 3), dtype=np.uint8)
    path = tmp_path / "image.png"
    write_image(path, image)
    return path, image


def test_write_image_round_trips(png):
    path, image = png
    np.testing.assert_array_equal(read_image(path), image)


@pytest.mark.parametrize("cut", ["half", "no_iend", "checksum"])
def test_a_damaged_png_is_one_error(png, tmp_path, cut):
    path, _ = png
    data = bytearray(path.read_bytes())
    if cut == "half":
        data = data[: len(data) // 2]
    elif cut == "no_iend":
        data = data[:-12]
    else:
        data[60] ^= 0xFF  # inside the first IDAT chunk
    bad = tmp_path / "bad.png"
    bad.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"cannot read image .*bad\.png: (truncated|damaged) PNG"):
        read_image(bad)
    with pytest.raises(DataError, match="cannot read mask"):
        read_mask(bad)


@pytest.mark.parametrize("cut", ["half", "checksum"])
def test_a_damaged_png_gives_no_libpng_noise(tmp_path, cut):
    # libpng's own error handler prints to the C stderr (buffered until the process ends),
    # so the check runs in a fresh process
    image = np.random.default_rng(1).integers(0, 255, size=(100, 100, 3), dtype=np.uint8)
    data = bytearray(cv2.imencode(".png", image)[1].tobytes())
    if cut == "half":
        data = data[: len(data) // 2]
    else:
        data[60] ^= 0xFF
    bad = tmp_path / "bad.png"
    bad.write_bytes(bytes(data))
    script = (
        "import sys, cv2; from torchfit.io.images import read_image\n"
        "if sys.argv[1] == 'cv2': cv2.imread(sys.argv[2])\n"
        "else:\n"
        "    try: read_image(sys.argv[2])\n"
        "    except Exception as exc: print(exc)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}

    def stderr(how):
        proc = subprocess.run(
            [sys.executable, "-c", script, how, str(bad)], capture_output=True, text=True, env=env
        )
        return proc.stdout, proc.stderr

    assert "libpng" in stderr("cv2")[1]  # what OpenCV alone prints
    out, err = stderr("torchfit")
    assert "PNG file" in out and err == ""


def test_a_truncated_jpeg_is_an_error_not_grey_pixels(tmp_path):
    image = np.full((32, 32, 3), 120, np.uint8)
    ok, encoded = cv2.imencode(".jpg", image)
    path = tmp_path / "frame.jpg"
    path.write_bytes(encoded.tobytes()[:-200])
    with pytest.raises(DataError, match="truncated JPEG"):
        read_image(path)


# --------------------------------------------------------------------------------------------
# The fingerprint


def test_config_digest_ignores_only_the_keys_that_do_not_change_results():
    from torchfit.pipeline.fingerprint import UNFINGERPRINTED_KEYS, config_digest

    base = load_config(REPO / "configs" / "demo.yaml")
    digest = config_digest(base)
    same = {
        "run.name": "other",
        "run.out": "/elsewhere",
        "run.resume": False,
        "run.num_threads": 1,
        "run.keep_heap": True,
        "data.root": "/other/data",
        "data.subjects": ("a",),
        "model.template": "mpeg4_simple",  # hashed by content instead
        "segmentation.compile": True,
        "fit.batch_size": 16,
        "output.tensorboard": False,
        "run.executor": "ray",  # where the fits run: a run resumes across executors
        "run.address": "auto",
        "run.workers": 4,
        "run.contour_workers": 3,  # the same choice in worker processes
        "parts.smoothing_px": 7.0,  # the parts options count only for the parts start
    }
    assert set(same) - {"parts.smoothing_px"} == set(UNFINGERPRINTED_KEYS)
    for key, value in same.items():
        assert config_digest(replace_keys(base, {key: value})) == digest, key
    for key, value in {
        "solver.ftol": 1e-3,
        "fit.contour_stride": 5,
        "segmentation.gamma": 0.5,
        "model.scale_max": 2.0,
        "run.dtype": "float32",
        "output.overlays": False,
        "output.mesh_format": "obj",
        "fit.initial_guess": "parts",
    }.items():
        assert config_digest(replace_keys(base, {key: value})) != digest, key
    parts = replace_keys(base, {"fit.initial_guess": "parts"})
    other = replace_keys(parts, {"parts.smoothing_px": 7.0})
    assert config_digest(other) != config_digest(parts)


def test_template_and_inputs_digests(tmp_path):
    import shutil

    from torchfit.body.template import load_template
    from torchfit.io.dataset import load_subject
    from torchfit.pipeline.fingerprint import Fingerprint, inputs_digest, template_digest

    full, simple = load_template("mpeg4_full"), load_template("mpeg4_simple")
    assert template_digest(full) == template_digest(load_template(full.urdf_path))
    assert template_digest(full) != template_digest(simple)

    subject = tmp_path / "s"
    shutil.copytree(REPO / "data" / "demo" / "subject_000", subject)
    before = inputs_digest(load_subject(subject))
    (subject / "truth.json").write_text("{}")  # evaluation only: not an input of the fit
    assert inputs_digest(load_subject(subject)) == before
    pose = subject / "poses" / "pose3.png"
    image = cv2.imread(str(pose))
    image[0, 0] ^= 1
    cv2.imwrite(str(pose), image)
    after = inputs_digest(load_subject(subject))
    assert after != before
    fp = Fingerprint("c", "t", after)
    assert fp.changes(fp.to_dict()) == ""
    assert fp.changes(Fingerprint("c", "t", before).to_dict()) == "input files changed"
    assert fp.changes(Fingerprint("c", "u", after).to_dict()) == "template changed"
    assert fp.changes(None) == "no complete outputs"


# --------------------------------------------------------------------------------------------
# Paths in a config file


def test_data_root_is_relative_to_the_config_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    demo = load_config(REPO / "configs" / "demo.yaml")
    assert Path(demo.data.root) == REPO / "data" / "demo"
    assert (Path(demo.data.root) / "subject_000" / "camera.yaml").is_file()
    # a relative config path from another folder
    monkeypatch.chdir(REPO / "tools")
    assert Path(load_config(Path("../configs/demo.yaml")).data.root) == REPO / "data" / "demo"

    folder = tmp_path / "cfg"
    folder.mkdir()
    (folder / "c.yaml").write_text("data: {root: subjects}\nmodel: {template: body/model.urdf}\n")
    cfg = load_config(folder / "c.yaml")
    assert cfg.data.root == str(folder / "subjects")
    assert cfg.model.template == str(folder / "body" / "model.urdf")
    assert load_config(folder / "c.yaml", ["model.template=mpeg4_simple"]).model.template == (
        "mpeg4_simple"
    )
    # on the command line, relative to the current directory
    monkeypatch.chdir(tmp_path)
    cfg = load_config(folder / "c.yaml", ["data.root=mine"])
    assert cfg.data.root == str(tmp_path / "mine")


def test_a_tensorboard_file_that_cannot_be_written_is_one_warning(tmp_path):
    # the event file is written by TensorBoard's writer thread; with a file-size limit its
    # writes fail (EFBIG): one warning from the run, no traceback from the thread
    script = (
        "import logging, resource, signal, numpy as np\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))\n"
        "logging.basicConfig(format='%(levelname)s %(message)s')\n"
        "from torchfit.pipeline.tensorboard import TensorBoardCallback\n"
        "tb = TensorBoardCallback(__import__('sys').argv[1], 'fit')\n"
        "image = np.random.default_rng(0).integers(0, 255, (200, 200, 3), dtype=np.uint8)\n"
        "for step in range(5):\n"
        "    tb.add_image('overlay', image, step)\n"
        "    tb.add_scalar('cost', 1.0, step)\n"
        "    tb.flush()\n"
        "tb.close()\n"
        "print('finished')\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path / "tb")],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
    )
    assert proc.returncode == 0 and "finished" in proc.stdout, proc.stderr
    assert "Traceback" not in proc.stderr and "Exception in thread" not in proc.stderr
    warnings = [line for line in proc.stderr.splitlines() if "TensorBoard" in line]
    assert len(warnings) == 1 and "File too large" in warnings[0], proc.stderr
    assert str(tmp_path / "tb") in warnings[0]


def test_resume_keeps_only_subjects_with_the_same_fingerprint(tmp_path, caplog):
    import json

    from torchfit.body.template import load_template
    from torchfit.io.dataset import load_dataset
    from torchfit.pipeline.fingerprint import Fingerprint, config_digest, template_digest
    from torchfit.pipeline.run import _kept

    config = load_config(REPO / "configs" / "demo.yaml")
    subjects = load_dataset(config.data.root)
    run_fp = Fingerprint(config_digest(config), template_digest(load_template("mpeg4_full")))
    run_dir = tmp_path / "run"
    for subject in subjects:  # a finished subject's files, as fit_batch writes them
        folder = run_dir / subject.name
        folder.mkdir(parents=True)
        stages = [{"stage": "all", "status": "FTOL", "message": "m", "cost": 2.5, "iterations": 7}]
        params = {"status": "ok", "message": "m", "stages": stages, "seconds": 1.25}
        (folder / "params.json").write_text(json.dumps(params))
        (folder / "measurements.json").write_text(json.dumps({"height_m": 1.7, "status": "ok"}))
        fingerprint = run_fp.for_subject(subject).to_dict()
        (folder / "fingerprint.json").write_text(json.dumps(fingerprint))
    kept, fingerprints = _kept(subjects, run_fp, run_dir, resume=True)
    assert sorted(kept) == sorted(fingerprints) == ["subject_000", "subject_001"]
    row = kept["subject_000"].row()
    assert (row["final_cost"], row["iterations"], row["seconds"], row["message"]) == (
        2.5,
        7,
        1.25,
        "m",
    )
    assert _kept(subjects, run_fp, run_dir, resume=False)[0] == {}
    changed = Fingerprint(
        config_digest(replace_keys(config, {"solver.ftol": 1e-3})), run_fp.template
    )
    with caplog.at_level("INFO"):
        assert _kept(subjects, changed, run_dir, resume=True)[0] == {}
    assert "subject_000: refitting (config changed)" in caplog.text
    (run_dir / "subject_001" / "params.json").write_text("{")  # damaged by hand
    assert sorted(_kept(subjects, run_fp, run_dir, resume=True)[0]) == ["subject_000"]
