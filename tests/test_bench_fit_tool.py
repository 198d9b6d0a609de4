"""benchmarks/bench_fit.py's subject links: a relative ``--data`` still points at the subjects."""

import os
from pathlib import Path

from scripts import load_script


def test_links_to_a_relative_data_folder_resolve(tmp_path, monkeypatch):
    bench_fit = load_script("benchmarks/bench_fit.py")
    (tmp_path / "sets" / "subject_000").mkdir(parents=True)
    monkeypatch.chdir(tmp_path)
    folder = bench_fit.link_subjects(Path("sets"), ["subject_000", "subject_000"], tmp_path / "t")
    links = sorted(folder.iterdir())
    assert [p.name for p in links] == ["000_subject_000", "001_subject_000"]
    assert all(p.is_dir() for p in links)  # not dangling, seen from any folder
    assert all(os.path.isabs(os.readlink(p)) for p in links)
