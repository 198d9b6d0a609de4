"""Accuracy benchmark: fit every subject with truth.json and report errors against the truth.

    python tools/benchmark.py --config configs/demo.yaml --data DIR --out DIR [--set key=value]
    python tools/benchmark.py --results RUN_DIR [--data DIR] [--out DIR]
    python tools/benchmark.py --template-baseline --config configs/demo.yaml --data DIR --out DIR

The first form runs the pipeline (torchfit.pipeline.run) on the subjects of --data that have
truth.json (the others are skipped with a note) into the run folder --out, from scratch unless
--resume, then writes the report there. The second form builds the report from an existing run
folder (its summary.csv and <subject>/measurements.json) without refitting; the data folder
comes from --data or the run's config.yaml, and the report goes to --out (default RUN_DIR).
The third form fits nothing: it reports the template's own measurements (unit scales) for
every subject, the no-fit baseline a fit must beat (status "template", seconds not measured).

Report files: report.md (method, mean absolute % error per measurement beside the first
paper's Table 1, per-subject true / fitted / error %), report.csv (per subject),
report_summary.csv (per measurement) and report.png (fitted against true). Beside each
measurement's error the report gives the error of the trivial predictor, a leave-one-out
regression on the true height fitted to the same subjects' truth, and marks which measurements
beat it; its header says which subjects had known facts (``subject.yaml``; make a copy of a
synthetic set with them by ``tools/add_known_facts.py``). The method line
says whether the numbers are a fit or the template baseline (status "template", no fit).
Exit status: 0, 1 when some subjects failed (the report is still written), 2 on an error.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import yaml  # noqa: E402
from tqdm import tqdm  # noqa: E402

from torchfit.config import replace_keys  # noqa: E402
from torchfit.config.cli import (  # noqa: E402
    add_config_args,
    config_from_args,
    exit_code,
    run_folder,
)
from torchfit.errors import ConfigError, DataError, TorchfitError  # noqa: E402
from torchfit.eval.report import (  # noqa: E402
    LABELS,
    REPORT_KEYS,
    TEMPLATE,
    SubjectOutcome,
    build_rows,
    collect_truths,
    read_run,
    summarize,
    write_report,
)
from torchfit.io.dataset import load_dataset  # noqa: E402


def _progress(arg: object) -> tqdm:
    """The pipeline's progress hook: a bar over the subject list, or a bar of ``total``."""
    if isinstance(arg, int):
        return tqdm(total=arg, desc="subjects", unit="subject")
    return tqdm(arg, desc="subjects", unit="subject")


def _facts_setting(subjects: list, names) -> dict[str, str]:
    """A header line saying which of the subjects ``names`` had known facts
    (``subject.yaml``), if any."""
    subjects = [s for s in subjects if s.name in names and s.facts]
    if not subjects:
        return {"known facts (subject.yaml)": "none"}
    keys = sorted({k for s in subjects for k in s.facts})
    counts = ", ".join(f"{k} for {sum(k in s.facts for s in subjects)}" for k in keys)
    return {"known facts (subject.yaml)": f"{counts} of {len(names)} subjects"}


class _Run(NamedTuple):
    results: list  # one pipeline SubjectResult or report SubjectOutcome per subject
    truths: dict[str, dict[str, float]]
    data: Path
    run_dir: Path
    notes: list[str]
    settings: dict[str, str]


def _truths(config) -> tuple[dict[str, dict[str, float]], list[str], list]:
    """The subjects' truths, notes on those without, and the subjects as loaded."""
    if not config.data.root:
        raise ConfigError("data.root is not set: pass --data DIR or set data.root in the config")
    subjects = load_dataset(config.data.root, config.data.subjects)
    truths, notes = collect_truths({s.name: s.folder for s in subjects})
    if not truths:
        raise DataError(f"no subject with a valid truth.json in {config.data.root}")
    return truths, notes, subjects


def _fit(args: argparse.Namespace) -> _Run:
    config = replace_keys(config_from_args(args), {"run.resume": args.resume})
    truths, notes, subjects = _truths(config)
    config = replace_keys(config, {"data.subjects": tuple(truths)})
    run_dir = run_folder(config)
    from torchfit.pipeline import run  # imports the body model stack

    results = run(config, run_dir, progress=_progress)
    settings = {**_settings(run_dir), **_facts_setting(subjects, truths)}
    return _Run(results, truths, Path(config.data.root), run_dir, notes, settings)


def _template_baseline(args: argparse.Namespace) -> _Run:
    import torch

    from torchfit.body.measure import measure_model
    from torchfit.body.model import BodyModel

    config = config_from_args(args)
    truths, notes, _ = _truths(config)
    dtype = torch.float64 if config.run.dtype == "float64" else torch.float32
    model = BodyModel(config.model.template, device=config.run.device, dtype=dtype)
    scales = torch.ones(1, model.num_segments, 3, dtype=dtype, device=model.device)
    values = {k: float(v[0]) for k, v in measure_model(model, scales).items()}
    message = f"template {config.model.template!r} measurements, unit scales (no fit)"
    results = [SubjectOutcome(name, TEMPLATE, message, dict(values)) for name in truths]
    settings = {"config template": config.model.template}
    return _Run(results, truths, Path(config.data.root), run_folder(config), notes, settings)


def _from_results(args: argparse.Namespace) -> _Run:
    run_dir = Path(args.results)
    results = read_run(run_dir)
    if args.data is not None:
        root = args.data
    else:
        saved = run_dir / "config.yaml"
        if not saved.is_file():
            raise ConfigError(f"{saved}: not found; pass --data DIR to name the dataset")
        try:  # only data.root is needed: read it without the (changing) config schema
            root = (yaml.safe_load(saved.read_text()) or {}).get("data", {}).get("root")
        except (OSError, yaml.YAMLError, AttributeError) as exc:
            raise ConfigError(f"{saved}: cannot read data.root ({exc}); pass --data DIR") from exc
        if not root:
            raise ConfigError(f"{saved}: data.root is not set; pass --data DIR")
    subjects = load_dataset(root)
    folders = {s.name: s.folder for s in subjects}
    wanted = {r.name: folders[r.name] for r in results if r.name in folders}
    truths, notes = collect_truths(wanted)
    notes += [
        f"{r.name}: skipped, no subject folder in {root}" for r in results if r.name not in wanted
    ]
    settings = {**_settings(run_dir), **_facts_setting(subjects, truths)}
    return _Run(results, truths, Path(root), run_dir, notes, settings)


def _settings(run_dir: Path) -> dict[str, str]:
    """Header lines from the run's resolved config.yaml (absent for a template baseline)."""
    try:
        saved = yaml.safe_load((run_dir / "config.yaml").read_text()) or {}
        solver, model = saved.get("solver", {}), saved.get("model", {})
        method = (saved.get("fit") or {}).get("method")
    except (OSError, yaml.YAMLError, AttributeError):
        return {}
    keys = {"template": model.get("template"), "jacobian": solver.get("jacobian")}
    prior = (saved.get("fit") or {}).get("prior") or {}
    if prior:
        keys["prior"] = f"{prior.get('name')}, weight {prior.get('weight')}"
        if prior.get("pose_weight"):
            keys["posture prior"] = (
                f"weight {prior.get('pose_weight')}, {prior.get('pose_sigma_deg')} deg"
            )
    if method not in (None, "autograd_lm"):  # the baseline's runs say so
        keys["method"] = method
    return {f"config {k}": str(v) for k, v in keys.items() if v is not None}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="With --results, --out is the report folder (default: the run folder).",
    )
    add_config_args(parser)
    parser.add_argument(
        "--results", type=Path, help="build the report from this run folder, without fitting"
    )
    parser.add_argument(
        "--template-baseline",
        action="store_true",
        help="fit nothing: report the template's measurements (the no-fit baseline)",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="keep subjects already done in the run folder (their time is then not measured)",
    )
    args = parser.parse_args(argv)
    try:
        if args.results is not None:
            if args.template_baseline:
                parser.error("--results and --template-baseline exclude each other")
            if args.config is not None or args.overrides:
                parser.error("--config and --set do not apply with --results (nothing is fitted)")
            done = _from_results(args)
            out_dir = args.out or done.run_dir
        else:
            done = _template_baseline(args) if args.template_baseline else _fit(args)
            out_dir = done.run_dir
        rows, more = build_rows(done.results, done.truths)
        notes = done.notes + more
        paths = write_report(
            out_dir,
            rows,
            data=done.data,
            run_dir=done.run_dir,
            notes=notes,
            settings=done.settings,
        )
    except TorchfitError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exit_code(exc)
    summary = summarize(rows)
    print(f"method: {summary.method}")
    print(
        f"subjects: {summary.n_subjects} with truth, {summary.n_failed} failed "
        f"(excluded from the means), {len(notes)} skipped"
    )
    for key in REPORT_KEYS:
        st = summary.stats[key]
        mae = "—" if st.mean_abs_pct is None else f"{st.mean_abs_pct:5.1f} %"
        print(f"  {LABELS[key]:>15}: mean abs. error {mae}  (n={st.n})")
    for note in notes:
        print(f"note: {note}")
    print("report: " + ", ".join(str(p) for p in paths.values()))
    return 1 if summary.n_failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
