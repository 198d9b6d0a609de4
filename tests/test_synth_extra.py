"""Without anny (the ``synth`` extra) the generators stop with one line that says how to
install it, exit code 2, instead of a traceback."""

import sys

import pytest
from scripts import load_script

from torchfit.errors import ModelError
from torchfit.synth.body import load_anny


@pytest.fixture
def no_anny(monkeypatch):
    monkeypatch.setitem(sys.modules, "anny", None)  # `import anny` raises ImportError
    load_anny.cache_clear()
    yield
    load_anny.cache_clear()


def test_load_anny_names_the_extra(no_anny):
    with pytest.raises(ModelError, match=r'pip install -e "\.\[synth\]"'):
        load_anny()


def _check(code: int, err: str) -> None:
    assert code == 2
    assert err.startswith("error: the synthetic bodies need anny"), err
    assert 'pip install -e ".[synth]"' in err and "Traceback" not in err


def test_make_subjects_without_anny(no_anny, tmp_path, capsys):
    main = load_script("tools/make_subjects.py").main
    _check(main(["--out", str(tmp_path / "out"), "--n", "1"]), capsys.readouterr().err)
    assert not (tmp_path / "out").exists()


def test_make_sequence_without_anny(no_anny, tmp_path, capsys, shared_data):
    clip = shared_data / "cmu-mocap-sample" / "01_01.bvh"
    if not clip.is_file():
        pytest.skip(f"{clip} is not available")
    main = load_script("tools/make_sequence.py").main
    args = ["--bvh", str(clip), "--out", str(tmp_path / "seq"), "--frames", "2", "--seed", "0"]
    _check(main(args), capsys.readouterr().err)
