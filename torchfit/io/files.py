"""Output files written whole or not at all, and digests of input files.

Every file a run writes goes through :func:`write_atomic`: the bytes go to a temporary file in
the destination's own folder (``.<name>.<random>.tmp``), which is flushed, synced to disk and
then renamed over the destination (``os.replace``, atomic on POSIX within one file system). A
reader, or a rerun after a crash, sees the old file or the new one, never a part of one; a
crash leaves at most a temporary file, which :func:`remove_temporary` clears.

Every failure to write (a read-only or full disk, missing permissions, a vanished folder, a
path through a regular file) raises :class:`~torchfit.errors.OutputError` naming the path and
the system's reason, in one line.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Iterable
from pathlib import Path

from torchfit.errors import DataError, OutputError

__all__ = [
    "TEMPORARY_SUFFIX",
    "make_dirs",
    "write_atomic",
    "copy_atomic",
    "remove_files",
    "remove_temporary",
    "files_digest",
]

#: Suffix of the temporary files of :func:`write_atomic` (their names start with a dot).
TEMPORARY_SUFFIX = ".tmp"

_UMASK = os.umask(0o022)
os.umask(_UMASK)


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def make_dirs(folder: str | Path) -> Path:
    """Create ``folder`` and its parents (no error when it exists).

    Raises:
        OutputError: naming the folder when it cannot be created.
    """
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create folder {folder}: {_reason(exc)}") from None
    return folder


def write_atomic(path: str | Path, data: bytes | str) -> Path:
    """Write ``data`` (``str`` is UTF-8 encoded) to ``path`` atomically; its folder is created.

    Returns:
        ``path``.

    Raises:
        OutputError: naming ``path`` when any step fails (the temporary file is removed).
    """
    path = Path(path)
    make_dirs(path.parent)
    payload = data.encode() if isinstance(data, str) else bytes(data)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(
            prefix=f".{path.name}.", suffix=TEMPORARY_SUFFIX, dir=path.parent
        )
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give what open() would
        os.replace(tmp, path)
    except OSError as exc:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
        raise OutputError(f"cannot write {path}: {_reason(exc)}") from None
    return path


def copy_atomic(source: str | Path, destination: str | Path) -> Path:
    """Copy a (small) file atomically (:func:`write_atomic`).

    Raises:
        DataError: ``source`` cannot be read; OutputError: ``destination`` cannot be written.
    """
    try:
        data = Path(source).read_bytes()
    except OSError as exc:
        raise DataError(f"cannot read {source}: {_reason(exc)}") from None
    return write_atomic(destination, data)


def remove_files(paths: Iterable[str | Path]) -> None:
    """Remove files that exist (missing ones are skipped), in the order given.

    Raises:
        OutputError: naming the file that cannot be removed.
    """
    for p in paths:
        try:
            Path(p).unlink(missing_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot remove {p}: {_reason(exc)}") from None


def remove_temporary(folder: str | Path) -> None:
    """Remove the temporary files a crashed :func:`write_atomic` left in ``folder``."""
    folder = Path(folder)
    if folder.is_dir():
        remove_files(folder.glob(f".*{TEMPORARY_SUFFIX}"))


def files_digest(paths: Iterable[str | Path], root: str | Path | None = None) -> str:
    """SHA-256 (hex) of the names and contents of files, in the order given.

    Args:
        paths: the files.
        root: names are taken relative to this folder (default: the file name alone), so
            that moving a whole folder keeps the digest.

    Raises:
        DataError: naming a file that cannot be read.
    """
    digest = hashlib.sha256()
    for p in paths:
        p = Path(p)
        name = p.relative_to(root).as_posix() if root is not None else p.name
        try:
            content = hashlib.sha256()
            with p.open("rb") as fh:
                while chunk := fh.read(1 << 20):
                    content.update(chunk)
        except OSError as exc:
            raise DataError(f"cannot read {p}: {_reason(exc)}") from None
        digest.update(name.encode() + b"\0" + content.digest())
    return digest.hexdigest()
