"""The fingerprint of a subject's outputs: everything that determines them, hashed.

A fitted subject's folder ends with ``fingerprint.json``, written after every other file, so
its presence means the outputs are complete. It holds SHA-256 digests of

- ``config``: the resolved config without the keys that do not change a subject's outputs
  (:data:`UNFINGERPRINTED_KEYS`; the ``parts`` section counts only with
  ``fit.initial_guess: parts``);
- ``template``: the template's files (URDF, ``template.json``, the meshes the URDF names);
- ``inputs``: the subject's ``camera.yaml``, background frames and posture images (names and
  contents);
- ``torchfit``: the version,

and ``fingerprint``, the digest of the four. A rerun keeps a subject whose fingerprint is the
one it would write now, and refits every other (README "Resuming").
"""

from __future__ import annotations

import copy
import hashlib
import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import torchfit
from torchfit.body.template import Template
from torchfit.config.loader import config_to_dict
from torchfit.config.schema import Config
from torchfit.io.dataset import Subject
from torchfit.io.export import write_json
from torchfit.io.files import files_digest

__all__ = [
    "FINGERPRINT_FILE",
    "UNFINGERPRINTED_KEYS",
    "Fingerprint",
    "config_digest",
    "template_digest",
    "inputs_digest",
    "read_fingerprint",
    "write_fingerprint",
]

#: The last file of a finished subject's folder.
FINGERPRINT_FILE = "fingerprint.json"

#: Config keys that do not change a subject's outputs: where outputs go and what is resumed
#: (``run.name``, ``run.out``, ``run.resume``), which subjects a run holds (``data.*``: the
#: inputs are hashed by content instead; ``model.template``: the template is hashed by
#: content), speed settings (``run.num_threads``, ``run.keep_heap``,
#: ``segmentation.compile``, ``fit.batch_size``: a subject's fit does not depend on the
#: others of its batch), where the fits run (``run.executor``, ``run.address``,
#: ``run.workers``, ``run.contour_workers``: a run resumes across executors) and the run-level
#: TensorBoard files (``output.tensorboard``).
UNFINGERPRINTED_KEYS = (
    "run.name",
    "run.out",
    "run.resume",
    "run.num_threads",
    "run.keep_heap",
    "run.executor",
    "run.address",
    "run.workers",
    "run.contour_workers",
    "data.root",
    "data.subjects",
    "model.template",
    "segmentation.compile",
    "fit.batch_size",
    "output.tensorboard",
)


def _digest(data: object) -> str:
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def config_digest(config: Config) -> str:
    """SHA-256 of the config keys that determine a subject's outputs."""
    data = copy.deepcopy(config_to_dict(config))
    for key in UNFINGERPRINTED_KEYS:
        section, name = key.split(".")
        data[section].pop(name, None)
    if config.fit.initial_guess != "parts":
        data.pop("parts")
    return _digest(data)


def template_digest(template: Template) -> str:
    """SHA-256 of a template's files: the URDF, ``template.json`` beside it (if any) and
    every mesh file the URDF names, in the URDF's order."""
    folder = template.urdf_path.parent
    files = [template.urdf_path]
    if (folder / "template.json").is_file():
        files.append(folder / "template.json")
    for mesh in ET.fromstring(template.urdf).iter("mesh"):
        if mesh.get("filename"):
            files.append(folder / mesh.get("filename"))
    return files_digest(files, folder)


def inputs_digest(subject: Subject) -> str:
    """SHA-256 of what the fit reads of a subject: ``camera.yaml``, the background frames,
    the six posture images, the masks where the subject's silhouettes come from ``masks/``,
    and the optional ``subject.yaml`` (names relative to the subject folder, and contents).

    Raises:
        DataError: a file cannot be read.
    """
    files = [subject.folder / "camera.yaml", *subject.background, *subject.poses]
    files += subject.masks or []
    if (subject.folder / "subject.yaml").is_file():
        files.append(subject.folder / "subject.yaml")
    return files_digest(files, subject.folder)


@dataclass(frozen=True)
class Fingerprint:
    """The digests that determine a subject's outputs (see the module docstring)."""

    config: str
    template: str
    inputs: str = ""
    torchfit: str = torchfit.__version__

    @property
    def digest(self) -> str:
        """The digest of the four parts."""
        return _digest([self.config, self.template, self.inputs, self.torchfit])

    def for_subject(self, subject: Subject) -> Fingerprint:
        """This (run-level) fingerprint with ``subject``'s inputs (raises as
        :func:`inputs_digest`)."""
        return Fingerprint(self.config, self.template, inputs_digest(subject), self.torchfit)

    def to_dict(self) -> dict:
        """The ``fingerprint.json`` document."""
        return {
            "fingerprint": self.digest,
            "torchfit": self.torchfit,
            "config": self.config,
            "template": self.template,
            "inputs": self.inputs,
        }

    def changes(self, previous: dict | None) -> str:
        """What differs from a ``fingerprint.json`` document, in words (empty when none)."""
        if previous is None:
            return "no complete outputs"
        if previous.get("fingerprint") == self.digest:
            return ""
        parts = ("torchfit", "config", "template", "inputs")
        changed = [p for p in parts if previous.get(p) != getattr(self, p)]
        names = {"torchfit": "torchfit version", "inputs": "input files"}
        return ", ".join(names.get(p, p) for p in changed) + " changed" if changed else "changed"


def read_fingerprint(folder: Path) -> dict | None:
    """The ``fingerprint.json`` document of a subject folder (None when absent or
    unreadable)."""
    try:
        data = json.loads((Path(folder) / FINGERPRINT_FILE).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def write_fingerprint(folder: Path, fingerprint: Fingerprint) -> None:
    """Write ``fingerprint.json`` (atomically): the subject's outputs are complete."""
    write_json(Path(folder) / FINGERPRINT_FILE, fingerprint.to_dict())
