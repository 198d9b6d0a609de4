"""The layout rules of ARCHITECTURE.md, checked on the source (AST imports, line counts)."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "torchfit"
MAX_LINES = 450


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(path: Path) -> set[str]:
    """Every module name imported anywhere in the file (also inside functions)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


MODULES = _modules()


def _importers(prefix: str) -> list[str]:
    return sorted(
        m
        for m, path in MODULES.items()
        if any(i == prefix or i.startswith(prefix + ".") for i in _imports(path))
    )


def _outside(importers: list[str], *allowed: str) -> list[str]:
    return [m for m in importers if not any(m == a or m.startswith(a + ".") for a in allowed)]


def test_only_the_pipeline_and_the_config_import_the_config():
    assert _outside(_importers("torchfit.config"), "torchfit.config", "torchfit.pipeline") == []


def test_the_solver_knows_nothing_of_bodies_or_images():
    solver = [m for m in MODULES if m.startswith("torchfit.solver")]
    for m in solver:
        bad = [
            i
            for i in _imports(MODULES[m])
            if i.startswith("torchfit.")
            and not i.startswith(("torchfit.solver", "torchfit.errors"))
        ]
        assert bad == [], f"{m} imports {bad}"


@pytest.mark.parametrize(
    ("library", "home"),
    [
        ("pytorch_kinematics", "torchfit.body.kinematics"),
        ("kornia", "torchfit.image"),
        ("trimesh", "torchfit.io"),
        ("torch.utils.tensorboard", "torchfit.pipeline.tensorboard"),
        ("pydantic", "torchfit.config"),
        ("ray", "torchfit.pipeline.ray_executor"),
    ],
)
def test_each_dependency_has_one_home(library, home):
    assert _outside(_importers(library), home) == []


def test_no_library_module_is_over_the_limit():
    long = {m: n for m, p in MODULES.items() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert long == {}


def test_import_torchfit_stays_light():
    top = _imports(MODULES["torchfit"])
    assert {i for i in top if i.startswith("torchfit.")} <= {
        "torchfit.errors",
        *(f"torchfit.errors.{n}" for n in ("CameraError", "ConfigError", "DataError")),
        *(f"torchfit.errors.{n}" for n in ("ModelError", "SegmentationError", "ShapeError")),
        "torchfit.errors.TorchfitError",
    }


#: ARCHITECTURE.md's table: what each package may import (besides torchfit.errors).
ALLOWED = {
    "status": set(),
    "camera": set(),
    "measurements": set(),
    "_dual": set(),
    "solver": set(),
    "io": {"camera", "measurements"},
    "image": set(),
    "body": {"io", "measurements", "_dual"},
    "parts": {"camera", "image"},
    "viz": {"body", "camera", "parts"},
    "fit": {"body", "camera", "image", "parts", "solver", "viz", "_dual"},
    "eval": {"io", "measurements", "status"},
    "synth": {"camera", "io", "measurements", "viz"},
    "capture": {"body", "camera", "image", "io", "viz"},
    "track": {"body", "camera", "fit", "image", "solver", "viz"},
    "config": {"fit", "image", "parts", "solver"},
    "pipeline": {
        "body",
        "camera",
        "config",
        "fit",
        "image",
        "io",
        "measurements",
        "parts",
        "solver",
        "status",
        "track",
        "viz",
        "_dual",
    },
}


def test_packages_import_only_what_the_architecture_allows():
    seen: dict[str, set[str]] = {}
    for name, path in MODULES.items():
        parts = name.split(".")
        if len(parts) < 2:
            continue
        src = parts[1]
        for i in _imports(path):
            if i.startswith("torchfit.") and (dst := i.split(".")[1]) not in (src, "errors"):
                seen.setdefault(src, set()).add(dst)
    extra = {p: sorted(d - ALLOWED.get(p, set())) for p, d in seen.items()}
    assert {p: d for p, d in extra.items() if d} == {}
