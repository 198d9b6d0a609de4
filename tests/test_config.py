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
