from pathlib import Path

import pytest
import yaml

from torchfit.config import Config, config_to_dict, load_config, save_config
from torchfit.errors import ConfigError


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "c.yaml"
    path.write_text(text)
    return path


def test_defaults_round_trip(tmp_path):
    cfg = load_config(None)
    assert isinstance(cfg, Config)
    save_config(cfg, tmp_path / "out.yaml")
    again = load_config(tmp_path / "out.yaml")
    assert config_to_dict(again) == config_to_dict(cfg)


def test_yaml_and_overrides(tmp_path):
    path = write(tmp_path, "run:\n  name: demo\nsolver:\n  max_iter: 7\n")
    cfg = load_config(path, ["solver.ftol=1e-3", "segmentation.gamma=1", "run.out=null"])
    assert cfg.run.name == "demo"
    assert cfg.solver.max_iter == 7
    assert cfg.solver.ftol == pytest.approx(1e-3)
    assert isinstance(cfg.segmentation.gamma, float)
    assert cfg.run.out is None


def test_stage_list(tmp_path):
    path = write(tmp_path, "fit:\n  stages:\n    - {name: a, scales: [legs]}\n    - {name: b}\n")
    cfg = load_config(path)
    assert [s.name for s in cfg.fit.stages] == ["a", "b"]
    assert cfg.fit.stages[0].scales == ("legs",)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("solver:\n  maxiter: 3\n", r"unknown key 'solver.maxiter'"),
        ("bogus: 1\n", r"unknown key 'bogus'"),
        ("solver:\n  max_iter: many\n", r"key 'solver.max_iter' expects an integer"),
        ("solver:\n  max_iter: true\n", r"key 'solver.max_iter' expects an integer"),
        ("run:\n  dtype: float16\n", r"key 'run.dtype' must be one of"),
        ("fit:\n  stages:\n    - {name: a, scale: [x]}\n", r"unknown key 'fit.stages\[0\].scale'"),
        ("solver: [1, 2]\n", r"key 'solver' expects a mapping"),
        ("- 1\n- 2\n", r"top level must be a mapping"),
        ("solver: {max_iter: 3\n", r"invalid YAML"),
    ],
)
def test_errors_name_key_and_file(tmp_path, text, message):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_missing_file_and_bad_override(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="must look like key.sub=value"):
        load_config(None, ["solver.max_iter"])
    with pytest.raises(ConfigError, match="unknown key 'solver.nope'"):
        load_config(None, ["solver.nope=1"])


def test_saved_config_is_plain_yaml(tmp_path):
    cfg = load_config(None, ["fit.poses=[1, 2]"])
    save_config(cfg, tmp_path / "c.yaml")
    data = yaml.safe_load((tmp_path / "c.yaml").read_text())
    assert data["fit"]["poses"] == [1, 2]


def test_errors_list_the_valid_keys_and_choices(tmp_path):
    path = write(tmp_path, "solver:\n  maxiter: 3\n")
    with pytest.raises(ConfigError, match=r"valid keys under 'solver': accel_ratio, .*jacobian"):
        load_config(path)
    with pytest.raises(
        ConfigError,
        match=r"key 'solver.jacobian' must be one of \['autograd', 'forward', 'reverse', "
        r"'numeric'\], got 'fwd'",
    ):
        load_config(None, ["solver.jacobian=fwd"])
    with pytest.raises(ConfigError, match=r"'fit.method' must be one of \['autograd_lm', 'minpack"):
        load_config(None, ["fit.method=numeric"])
    with pytest.raises(ConfigError, match=r"key 'segmentation.shadow_ratio' expects a list of 2"):
        load_config(None, ["segmentation.shadow_ratio=[0.5]"])
    with pytest.raises(ConfigError, match=r"key 'fit': fit.poses: expected distinct postures"):
        load_config(None, ["fit.poses=[1, 1]"])
    with pytest.raises(ConfigError, match=r"key 'solver': LMOptions.max_iter: expected >= 1"):
        load_config(None, ["solver.max_iter=0"])


def test_sections_are_the_numeric_options(tmp_path):
    from torchfit.fit import FitOptions, StageOptions
    from torchfit.image import SegmentationOptions
    from torchfit.parts import PartsOptions
    from torchfit.solver import LMOptions

    cfg = load_config(None, ["solver.jacobian=forward", "solver.max_iter=9"])
    assert isinstance(cfg.fit, FitOptions) and isinstance(cfg.fit.stages[0], StageOptions)
    assert isinstance(cfg.segmentation, SegmentationOptions)
    assert isinstance(cfg.parts, PartsOptions)
    assert cfg.solver.jacobian == "forward"
    # every other field as LMOptions', but the fit's robust loss (Huber at 3 px), tolerances
    # and scaling floor
    assert cfg.solver.lm_options(4) == LMOptions(
        max_iter=4, loss="huber", loss_scale=3.0, ftol=1e-6, xtol=1e-6, min_diag=1.0
    )
    assert type(cfg.solver.lm_options()) is LMOptions and cfg.solver.lm_options().max_iter == 9


def _differences(a, b, prefix: str = "") -> list[str]:
    """The dotted keys where two configs differ."""
    import dataclasses

    if dataclasses.is_dataclass(a):
        return [
            d
            for f in dataclasses.fields(a)
            for d in _differences(getattr(a, f.name), getattr(b, f.name), f"{prefix}.{f.name}")
        ]
    return [] if a == b else [prefix[1:]]


CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def test_the_defaults_are_the_accuracy_configuration():
    """A config that names no fit or solver key fits as configs/benchmark.yaml does (the
    configuration behind the accuracy figures), and the demo differs from it only in its run
    name, data and batch size."""
    default = load_config(None)
    assert _differences(default, load_config(CONFIGS / "benchmark.yaml")) == ["run.name"]
    demo = load_config(CONFIGS / "demo.yaml")
    assert _differences(default, demo) == ["run.name", "data.root", "fit.batch_size"]
    assert default.fit.prior.weight == 0.3 and default.fit.prior.pose_weight == 0.5
    assert default.fit.bends.weight == 1.0 and default.solver.min_diag == 1.0
    assert default.fit.contour_orientation_px == 8.0
    assert [s.max_iter for s in default.fit.stages] == [30, 50]


def test_the_tracker_s_defaults_are_configs_track_yaml():
    from torchfit.pipeline.track import TrackConfig

    shipped = load_config(CONFIGS / "track.yaml", schema=TrackConfig)
    assert _differences(TrackConfig(), shipped) == []


def test_configs_are_frozen_and_replaced_by_key():
    import dataclasses

    from torchfit.config import replace_keys

    cfg = load_config(None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.run.resume = False
    new = replace_keys(cfg, {"run.resume": False, "fit.batch_size": 7})
    assert (new.run.resume, new.fit.batch_size, cfg.run.resume) == (False, 7, True)
    with pytest.raises(ConfigError, match="unknown key 'run.nope'"):
        replace_keys(cfg, {"run.nope": 1})


def test_a_partial_prior_or_bends_section_keeps_the_fit_s_other_defaults(tmp_path):
    """Setting one key of fit.prior or fit.bends leaves the others at the fit's defaults (the
    population prior at 0.3, the posture prior at 0.5, the knee marks at 1.0), not at the
    library's "off"."""
    cfg = load_config(None, ["fit.prior.pose_sigma_deg=10", "fit.bends.shown_px=3"])
    assert cfg.fit.prior.pose_sigma_deg == 10.0
    assert cfg.fit.prior.weight == 0.3 and cfg.fit.prior.pose_weight == 0.5
    assert cfg.fit.bends.weight == 1.0 and cfg.fit.bends.shown_px == 3.0
    path = write(tmp_path, "fit:\n  prior:\n    height_tolerance_m: 0.01\n")
    assert load_config(path).fit.prior.weight == 0.3


@pytest.mark.parametrize(
    ("key", "message"),
    [("fit.batch_size=0", "fit.batch_size"), ("fit.stages=[]", "fit.stages")],
)
def test_a_fit_without_batches_or_stages_is_a_config_error(key, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [key])


@pytest.mark.parametrize(
    ("key", "message"),
    [
        ("segmentation.threshold=-5", "segmentation.threshold: expected a number > 0"),
        ("segmentation.close_kernel=4", "segmentation.close_kernel: expected an odd number"),
        ("segmentation.open_kernel=-1", "segmentation.open_kernel: expected an odd number"),
        ("segmentation.shadow_ratio=[0.5, 0.2]", "segmentation.shadow_ratio: expected"),
        ("segmentation.gamma=2", r"segmentation.gamma: expected a number in \[0, 1\]"),
        ("fit.translation_max_m=-1", "fit.translation_max_m: expected a number >= 0"),
        ("fit.contour_stride=0", "fit.contour_stride: expected a number >= 1"),
    ],
)
def test_out_of_range_numbers_are_config_errors_naming_the_key(key, message):
    """A value no segmentation or fit can use stops at the config (exit code 2 in the tools)
    instead of failing every subject or changing the result unnoticed."""
    with pytest.raises(ConfigError, match=message):
        load_config(None, [key])
    load_config(None, ["segmentation.close_kernel=1", "segmentation.open_kernel=0"])  # skipped
