"""Dataset layout (design.md section 3): subject folders, their files and their validation.

A dataset is a folder of subject folders, or a manifest file listing subject folders (one per
line, relative to the manifest; blank lines and ``#`` comments are skipped). Nothing here
decodes images: a :class:`Subject` holds paths, the camera and the ground truth. Loading never
stops at a bad subject; each :class:`Subject` carries the list of its ``problems`` (empty when
it is usable) so that a batch run can skip it and report why.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path

from torchfit.camera import Camera
from torchfit.errors import CameraError, DataError
from torchfit.io.camera import load_camera, load_stereo_cameras
from torchfit.io.validate import (
    CAPTURE_NAMES,
    FACT_KEYS,
    HEIGHT_RANGE_M,
    N_POSES,
    SEXES,
    load_facts,
    validate_facts,
    validate_truth,
)

__all__ = [
    "IMAGE_EXTENSIONS",
    "N_POSES",
    "MIN_BACKGROUND_FRAMES",
    "CAPTURE_NAMES",
    "SEGMENTATION_METHODS",
    "StereoInfo",
    "Subject",
    "load_subject",
    "resolve_method",
    "validate_subject",
    "validate_truth",
    "validate_facts",
    "FACT_KEYS",
    "SEXES",
    "HEIGHT_RANGE_M",
    "load_dataset",
]

#: Image file extensions recognised as frames (lower case).
IMAGE_EXTENSIONS: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
#: Fewest background frames a subject (and each stereo view) needs.
MIN_BACKGROUND_FRAMES = 5
#: Where the silhouettes come from (``segmentation.method``): ``auto`` takes a subject's own
#: ``masks/`` where it has them and background subtraction otherwise.
SEGMENTATION_METHODS: tuple[str, ...] = ("auto", "background", "masks", "chroma_key")


@dataclass
class StereoInfo:
    """The optional stereo pair of a subject (design.md section 7).

    Attributes:
        left, right: the two calibrated cameras (B = 1 each).
        background_left, background_right: background frame paths per view, sorted.
        left_image, right_image: the person in posture 5, one image per view.
    """

    left: Camera
    right: Camera
    background_left: list[Path]
    background_right: list[Path]
    left_image: Path
    right_image: Path


@dataclass
class Subject:
    """One subject folder.

    Attributes:
        name: the folder name.
        folder: the folder path.
        camera: the calibrated camera (B = 1), or None where ``camera.yaml`` is bad.
        background: background frame paths, sorted by name.
        poses: the six posture image paths ``pose1`` … ``pose6``, in order (a missing one is
            the path where it was expected).
        truth: the parsed ``truth.json``, or None where absent or invalid.
        facts: what the optional ``subject.yaml`` says (keys of :data:`FACT_KEYS`); empty
            where absent or invalid.
        stereo: the stereo pair, or None where absent or invalid.
        masks: the user's silhouettes ``masks/pose1`` … ``masks/pose6`` in order (8-bit,
            > 127 is the person), or None where the silhouettes do not come from ``masks/``.
        method: how this subject's silhouettes are made: ``masks``, ``background`` or
            ``chroma_key`` (``auto`` resolved).
        problems: what is wrong, one message per problem naming the file; empty when usable.
        warnings: what is off but does not prevent fitting (e.g. a bad optional stereo folder).
    """

    name: str
    folder: Path
    camera: Camera | None = None
    background: list[Path] = field(default_factory=list)
    poses: list[Path] = field(default_factory=list)
    truth: dict | None = None
    facts: dict = field(default_factory=dict)
    stereo: StereoInfo | None = None
    masks: list[Path] | None = None
    method: str = "background"
    problems: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when the subject can be fitted (no problems)."""
        return not self.problems

    @property
    def status(self) -> str:
        """``"ok"`` or ``"invalid"``."""
        return "ok" if self.ok else "invalid"

    def raise_if_invalid(self) -> None:
        """Raise :class:`DataError` listing the problems, if any."""
        if self.problems:
            raise DataError(f"subject {self.name!r} is invalid: " + "; ".join(self.problems))


# --------------------------------------------------------------------------------------------
# Files


def _frames(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS)


def _find_image(folder: Path, stem: str) -> Path | None:
    for ext in IMAGE_EXTENSIONS:
        for candidate in (folder / f"{stem}{ext}", folder / f"{stem}{ext.upper()}"):
            if candidate.is_file():
                return candidate
    return None


def _png_size(path: Path) -> tuple[int, int] | None:
    """``(width, height)`` from a PNG header without decoding; None for other files."""
    if path.suffix.lower() != ".png":
        return None
    try:
        with path.open("rb") as fh:
            head = fh.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", head[16:24])


def _check_frames(
    paths: list[Path], size: tuple[int, int] | None, problems: list[str], what: str
) -> None:
    for p in paths:
        if p.stat().st_size == 0:
            problems.append(f"{p}: empty {what} file")
            continue
        if p.suffix.lower() == ".png":
            found = _png_size(p)
            if found is None:
                problems.append(f"{p}: not a valid PNG file")
            elif size is not None and tuple(found) != tuple(size):
                problems.append(
                    f"{p}: {what} is {found[0]}x{found[1]} pixels, camera.yaml image_size is "
                    f"{size[0]}x{size[1]}"
                )


# --------------------------------------------------------------------------------------------
# truth.json


# --------------------------------------------------------------------------------------------
# Subjects


def _load_stereo(folder: Path, warnings: list[str]) -> StereoInfo | None:
    stereo = folder / "stereo"
    if not stereo.is_dir():
        return None
    problems: list[str] = []
    try:
        left, right = load_stereo_cameras(stereo / "cameras.yaml")
    except CameraError as exc:
        warnings.append(f"stereo pair ignored: {exc}")
        return None
    bg_left = _frames(stereo / "background" / "left")
    bg_right = _frames(stereo / "background" / "right")
    for side, frames, cam in (("left", bg_left, left), ("right", bg_right, right)):
        if len(frames) < MIN_BACKGROUND_FRAMES:
            problems.append(
                f"{stereo / 'background' / side}: expected >= {MIN_BACKGROUND_FRAMES} "
                f"background frames, found {len(frames)}"
            )
        _check_frames(frames, cam.image_size, problems, "background frame")
    images = {}
    for side, cam in (("left", left), ("right", right)):
        found = _find_image(stereo, side)
        if found is None:
            problems.append(f"{stereo / (side + '.png')}: missing stereo image")
        else:
            _check_frames([found], cam.image_size, problems, "stereo image")
            images[side] = found
    if problems:
        warnings.extend(f"stereo pair ignored: {p}" for p in problems)
        return None
    return StereoInfo(left, right, bg_left, bg_right, images["left"], images["right"])


def _load_masks(folder: Path, size: tuple[int, int] | None, problems: list[str]) -> list[Path]:
    """The six ``masks/pose<k>`` files (a missing one is the path where it was expected)."""
    masks = []
    for i in range(1, N_POSES + 1):
        found = _find_image(folder / "masks", f"pose{i}")
        if found is None:
            expected = folder / "masks" / f"pose{i}.png"
            problems.append(f"{expected}: missing mask (masks/ needs pose1 … pose{N_POSES})")
            masks.append(expected)
        else:
            _check_frames([found], size, problems, "mask")
            masks.append(found)
    return masks


def resolve_method(folder: Path, method: str) -> str:
    """``segmentation.method`` for one subject or sequence folder: ``auto`` becomes ``masks``
    where the folder has ``masks/``, else ``background``.

    Raises:
        DataError: an unknown method.
    """
    if method not in SEGMENTATION_METHODS:
        raise DataError(
            f"segmentation method: expected one of {', '.join(SEGMENTATION_METHODS)}, "
            f"got {method!r}"
        )
    if method == "auto":
        return "masks" if (folder / "masks").is_dir() else "background"
    return method


def load_subject(folder: str | Path, method: str = "auto") -> Subject:
    """Read one subject folder; never raises for bad content (see ``Subject.problems``).

    Problems (the subject cannot be fitted): missing folder, missing or invalid
    ``camera.yaml``, fewer than :data:`MIN_BACKGROUND_FRAMES` background frames (not needed
    when the silhouettes come from ``masks/``), a missing posture image or mask, an image or
    mask whose size differs from the camera's, an invalid ``truth.json`` or ``subject.yaml``.
    An invalid optional ``stereo/`` folder is only a warning (``stereo`` is None).

    Args:
        folder: the subject folder.
        method: ``segmentation.method`` (:data:`SEGMENTATION_METHODS`): ``masks`` needs
            ``masks/pose1`` … ``pose6``; ``background`` and ``chroma_key`` need the background
            frames; ``auto`` takes ``masks/`` where the folder exists.

    Raises:
        DataError: an unknown ``method``.
    """
    folder = Path(folder)
    subject = Subject(name=folder.name, folder=folder, method=resolve_method(folder, method))
    problems = subject.problems
    if not folder.is_dir():
        problems.append(f"{folder}: subject folder not found")
        return subject
    if not (folder / "poses").is_dir() and (folder / "frames").is_dir():
        # a tracking sequence beside the subjects (tools/make_sequence.py writes both)
        problems.append(
            f"{folder}: a sequence (frames/, for tools/track.py), not a subject (poses/); "
            "name the subjects to fit with data.subjects"
        )
        return subject
    try:
        subject.camera = load_camera(folder / "camera.yaml")
    except CameraError as exc:
        problems.append(str(exc))
    size = subject.camera.image_size if subject.camera is not None else None

    if subject.method == "masks":
        subject.masks = _load_masks(folder, size, problems)
    subject.background = _frames(folder / "background")
    if subject.method != "masks" and len(subject.background) < MIN_BACKGROUND_FRAMES:
        problems.append(
            f"{folder / 'background'}: expected >= {MIN_BACKGROUND_FRAMES} background frames, "
            f"found {len(subject.background)}"
        )
    _check_frames(subject.background, size, problems, "background frame")

    for i in range(1, N_POSES + 1):
        found = _find_image(folder / "poses", f"pose{i}")
        if found is None:
            expected = folder / "poses" / f"pose{i}.png"
            problems.append(f"{expected}: missing posture image")
            subject.poses.append(expected)
        else:
            _check_frames([found], size, problems, "posture image")
            subject.poses.append(found)

    truth_path = folder / "truth.json"
    if truth_path.is_file():
        try:
            truth = json.loads(truth_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            problems.append(f"{truth_path}: invalid JSON: {exc}")
        else:
            truth_problems = validate_truth(truth, str(truth_path))
            problems.extend(truth_problems)
            subject.truth = None if truth_problems else truth

    facts_path = folder / "subject.yaml"
    if facts_path.is_file():
        subject.facts = load_facts(facts_path, problems)

    subject.stereo = _load_stereo(folder, subject.warnings)
    return subject


def validate_subject(folder: str | Path) -> list[str]:
    """The problems of one subject folder, each naming the file (empty when valid)."""
    return load_subject(folder).problems


def _read_manifest(path: Path) -> list[Path]:
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: cannot read the manifest: {exc}") from exc
    entries = []
    for line in lines:
        line = line.split("#", 1)[0].strip()
        if line:
            entry = Path(line)
            entries.append(entry if entry.is_absolute() else path.parent / entry)
    return entries


def load_dataset(
    root: str | Path, subjects: list[str] | None = None, method: str = "auto"
) -> list[Subject]:
    """Load every subject of a dataset.

    Args:
        root: a folder of subject folders (every sub-folder is a subject; hidden ones are
            skipped) or a manifest file with one subject folder per line.
        subjects: keep only these subject names (folder names), in this order; a name that is
            not in the dataset gives a subject with a "not found" problem.
        method: ``segmentation.method``, as :func:`load_subject`.

    Returns:
        One :class:`Subject` per subject folder, sorted by name unless ``subjects`` gives the
        order; check ``subject.ok`` / ``subject.problems`` before fitting.

    Raises:
        DataError: ``root`` does not exist, is itself a subject folder, or the manifest cannot
            be read.
    """
    root = Path(root)
    if (root / "camera.yaml").is_file() and (root / "poses").is_dir():
        raise DataError(
            f"root: {root} is a subject folder (it holds camera.yaml and poses/); pass the "
            f"folder that holds it ({root.parent}), with data.subjects=[{root.name}] to fit "
            "this subject alone"
        )
    if root.is_dir():
        try:
            folders = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
        except OSError as exc:
            raise DataError(f"root: cannot list {root}: {exc.strerror}") from None
    elif root.is_file():
        folders = _read_manifest(root)
    else:
        raise DataError(f"root: dataset folder or manifest not found: {root}")
    if subjects is not None:
        by_name = {f.name: f for f in folders}
        base = root if root.is_dir() else root.parent
        folders = [by_name.get(name, base / name) for name in subjects]
    return [load_subject(f, method) for f in folders]
