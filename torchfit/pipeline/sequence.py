"""A motion sequence's folder (:func:`load_sequence`) and its frames' silhouettes
(:class:`SequenceSegmenter`): background subtraction against ``background/``, the sequence's
own ``masks/`` (one per frame, from a segmenter of your own) or a chroma key, as
``segmentation.method`` says (:class:`torchfit.config.SilhouetteSource`).

The layout::

    <sequence>/
      camera.yaml
      background/*.png     # the empty scene (not needed with masks/, nor for a chroma key
                           # whose colour the config gives)
      frames/000000.png …  # or a video file (tools/track.py --video)
      masks/000000.png …   # optional: one silhouette per frame, in the frames' order
                           # (8-bit, > 127 is the person, camera.yaml's image size)
      truth.json           # optional: {"fps": F, "joints_world": [{joint: [x, y, z]}, …]}
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import torch

from torchfit.camera import Camera
from torchfit.config.schema import SilhouetteSource
from torchfit.errors import DataError, SegmentationError
from torchfit.image import fit_background, segment
from torchfit.image.background import least_background_frames
from torchfit.image.chroma import key_colour, screen_frame
from torchfit.image.segment import SegmentationResult, finish_silhouettes
from torchfit.image.shadow import bridged
from torchfit.io.camera import load_camera
from torchfit.io.dataset import resolve_method
from torchfit.io.images import list_images, load_frames, read_mask, read_silhouette
from torchfit.io.validate import is_position
from torchfit.io.video import read_video, video_frame_count
from torchfit.measurements import JOINT_NAMES
from torchfit.pipeline.prepare import chroma_silhouettes

__all__ = ["Sequence", "load_sequence", "SequenceSegmenter"]


@dataclass
class Sequence:
    """A sequence folder (its frames as images, or a video file).

    Attributes:
        method: where its silhouettes come from: ``background``, ``masks`` or
            ``chroma_key`` (``segmentation.method`` resolved for this folder).
        masks: with ``masks``, one mask file per frame to track.
    """

    name: str
    camera: Camera
    background: list[Path]
    frames: list[Path]
    fps: float
    truth: list[dict] | None
    video: Path | None = None
    video_frames: int = 0
    method: str = "background"
    masks: list[Path] = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        """The number of frames to track."""
        return self.video_frames if self.video is not None else len(self.frames)

    def images(self) -> Iterator[torch.Tensor]:
        """The frames in order, each (1, 3, H, W) RGB in [0, 1]."""
        if self.video is None:
            for path in self.frames:
                yield load_frames([path], self.camera.image_size)[0]
            return
        yield from read_video(self.video, self.camera.image_size, self.video_frames)


def _load_truth(path: Path, count: int | None) -> tuple[list[dict] | None, float]:
    """A sequence's ``truth.json``: its true joints per frame (None without ``joints_world``)
    and its frame rate (25 without ``fps``), checked before any frame is tracked.

    Args:
        path: the file.
        count: the frames to be tracked, that the truth must cover (None: not known, a video).

    Raises:
        DataError: naming the file and the key: not JSON, an ``fps`` that is not a positive
        number, a ``joints_world`` that is not a list of frames with every evaluated joint
        as ``[x, y, z]``, or fewer truth frames than frames to track.
    """
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: cannot read the truth: {exc}") from None
    if not isinstance(doc, dict):
        raise DataError(f"{path}: expected a JSON object, got {type(doc).__name__}")
    fps = doc.get("fps", 25.0)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not 0 < fps < math.inf:
        raise DataError(f"{path}: key 'fps' expects a positive number, got {fps!r}")
    truth = doc.get("joints_world")
    if truth is None:
        return None, float(fps)
    if not isinstance(truth, list):
        raise DataError(
            f"{path}: key 'joints_world' expects a list of frames, got {type(truth).__name__}"
        )
    if count is not None and len(truth) < count:
        raise DataError(f"{path}: {len(truth)} truth frames for {count} frames to track")
    names = [n for n in JOINT_NAMES if n != "head_top"]
    for k, frame in enumerate(truth[:count]):
        bad = [n for n in names if not (isinstance(frame, dict) and is_position(frame.get(n)))]
        if bad:
            raise DataError(
                f"{path}: joints_world[{k}] expects [x, y, z] in metres for each of "
                f"{', '.join(bad)}"
            )
    return truth, float(fps)


def _check_numbering(frames: list[Path]) -> None:
    """Frames named by their number (``000000.png`` ...) must number every frame: a gap would
    pair each later frame with the truth of another and the tracker's prediction with a
    motion twice as fast.

    Raises:
        DataError: naming the first missing number (or one out of the names' order).
    """
    if not frames or not all(p.stem.isdigit() for p in frames):
        return
    first = int(frames[0].stem)
    for k, path in enumerate(frames):
        if int(path.stem) != first + k:
            raise DataError(
                f"{path.parent}: frame {first + k:06d} is missing (the frames are numbered "
                f"from {frames[0].name}; {path.name} follows {frames[k - 1].name})"
            )


def load_sequence(
    folder: str | Path,
    max_frames: int | None = None,
    video: str | Path | None = None,
    method: str = "auto",
) -> Sequence:
    """Read a sequence folder's layout (images and masks are read while tracking).

    Args:
        folder: the sequence folder.
        max_frames: track only the first frames.
        video: a video file to read the frames from instead of ``frames/``.
        method: ``segmentation.method``: ``auto`` takes ``masks/`` where the folder has it.

    Raises:
        DataError: a part is missing (``background/`` for background subtraction, ``masks/``
        with ``masks``, the frames), frames named by number with one missing, the masks do
        not number the frames or the first is not the camera's size, the video cannot be
        read, or an unknown ``method``.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DataError(f"sequence folder not found: {folder}")
    method = resolve_method(folder, method)
    camera = load_camera(folder / "camera.yaml")
    background = list_images(folder / "background") if (folder / "background").is_dir() else []
    frames = [] if video is not None else list_images(folder / "frames")
    if video is None and not frames:
        raise DataError(f"{folder}: needs frames/*.png (or a video)")
    if method == "background" and not background:
        raise DataError(
            f"{folder}: needs background/*.png for background subtraction (or masks/ with "
            "segmentation.method: masks or auto)"
        )
    _check_numbering(frames)
    count = len(frames)
    if video is not None:
        count = video_frame_count(video)
    masks = list_images(folder / "masks") if method == "masks" else []
    if method == "masks":
        if len(masks) != count:
            raise DataError(
                f"{folder / 'masks'}: {len(masks)} masks for {count} frames (one per frame, in "
                "the frames' order)"
            )
        read_mask(masks[0], camera.image_size)
    if max_frames is not None:
        frames, masks, count = frames[:max_frames], masks[:max_frames], min(count, max_frames)
    truth, fps = None, 25.0
    if (folder / "truth.json").is_file():
        truth, fps = _load_truth(folder / "truth.json", None if video is not None else count)
    path = Path(video) if video is not None else None
    return Sequence(
        folder.name, camera, background, frames, fps, truth, path, count if path else 0, method,
        masks,
    )  # fmt: skip


class SequenceSegmenter:
    """One sequence's frames to silhouettes, by its ``method``: the key colour and empty screen
    are made once here, the background model once on the first frame (:meth:`prepare`: where
    the frames are read, so that the reader processes of many sequences make theirs side by
    side), both from ``background/``, read only for those; then :meth:`silhouettes` gives the
    frames' (H, W) bool silhouettes in order. It is sent to the frame reader's process as it is.

    Raises (on creation):
        ConfigError: a chroma key with no key colour and no background frames;
        SegmentationError: no screen in a chroma key's background frames; fewer background
            frames than ``min_background_frames``.
    """

    def __init__(
        self, sequence: Sequence, options: SilhouetteSource, bridge_min: float = 0.0
    ) -> None:
        self.sequence, self.options, self.bridge_min = sequence, options, bridge_min
        self.model = self.key = self.screen = None
        if sequence.method == "masks":
            return
        if sequence.method == "background":
            least = least_background_frames(options)
            if len(sequence.background) < least:
                raise SegmentationError(
                    f"{sequence.name}: {len(sequence.background)} background frames, expected "
                    f"at least {least} (segmentation.min_background_frames)"
                )
            return  # the model is made on the first frame (prepare)
        size = sequence.camera.image_size
        empty = load_frames(sequence.background, size)[0] if sequence.background else None
        self.key = key_colour(options.chroma_key, empty)
        self.screen = None if empty is None else screen_frame(empty, options.chroma_key)

    def prepare(self) -> SequenceSegmenter:
        """Make the background model (with background subtraction), if not made yet: reads
        ``background/`` (about 0.3 s at 720x576). :meth:`segmented` calls it first."""
        seq = self.sequence
        if seq.method == "background" and self.model is None:
            empty = load_frames(seq.background, seq.camera.image_size)[0]
            self.model = fit_background(empty, self.options)
        return self

    def silhouettes(self) -> Iterator[torch.Tensor]:
        """The frames' silhouettes, (H, W) bool each, in order (``masks/`` are read, not the
        frames, with ``masks``)."""
        for mask, _ in self.segmented():
            yield mask

    def segmented(self) -> Iterator[tuple[torch.Tensor, torch.Tensor | None]]:
        """Per frame in order, its silhouette and a second one or None, each (H, W) bool.

        The second is made by background subtraction where the shadow test removed pixels
        that lie between the body above them and a part of the person cut off below them in
        their column (:func:`torchfit.image.shadow.bridged`), at least ``bridge_min`` of the
        silhouette's area: the frame's silhouette made again with those pixels given back,
        as ``shadow_bridge`` makes it (:func:`torchfit.image.finish_silhouettes`; the tests
        are not run again). Light trousers before a light wall are an attenuated copy of it,
        and the first silhouette then ends at the hips; a shadow on the floor between the
        feet is bridged too, so which one a frame is is for the tracker to tell (from where
        it expects the body). 0 makes no second silhouette.
        """
        seq = self.prepare().sequence
        if seq.method == "masks":
            for path in seq.masks[: seq.num_frames]:
                yield torch.from_numpy(read_silhouette(path, seq.camera.image_size)), None
            return
        for image in seq.images():
            if seq.method == "chroma_key":
                yield chroma_silhouettes(image, self.options, self.screen, self.key)[0, 0], None
                continue
            result = segment(image, self.model, self.options)
            yield result.masks[0, 0], self._bridged(result)

    def _bridged(self, result: SegmentationResult) -> torch.Tensor | None:
        """The second silhouette of :meth:`segmented` (None where there is none)."""
        opts = self.options
        if not (self.bridge_min > 0 and opts.shadow_test) or opts.shadow_bridge:
            return None
        removed = result.shadow
        least = self.bridge_min * float(result.masks.sum())
        if float(removed.sum()) < least:  # what the bridge gives back is some of these
            return None
        kept = (result.distance > opts.threshold) & ~removed
        gained = removed & bridged(kept, opts.open_kernel)
        if float(gained.sum()) < least:
            return None
        # what segment() with shadow_bridge gives, without testing the image again
        return finish_silhouettes(result.tested, self.model, kept | gained, opts)[0, 0]
