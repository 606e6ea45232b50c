"""Atomic file writes: a crash never leaves a partial file under the final name.

Every writer in :mod:`flowsynth.io` writes to a hidden temporary file in the destination directory,
fsyncs it, then renames it over the final name with :func:`os.replace` (atomic on POSIX and Windows
when both names are on the same file system, which the shared directory guarantees).

Temporary names start with ``.`` and keep the final extension, ``.{stem}.tmp-{8 hex}{suffix}``
(``depth_0003.exr`` -> ``.depth_0003.tmp-1a2b3c4d.exr``), so globbing ``*.exr`` for samples ignores
them and libraries that pick a format from the extension (OpenEXR, Pillow) still see the right one.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Iterator
from pathlib import Path

from flowsynth.errors import ExportError, StorageError

__all__ = ["atomic_path", "atomic_write_bytes"]

_MAX_NAME_TRIES = 16  # collisions of 32 random bits are rare; give up after this many


def _create_temp(path: Path) -> Path:
    """Create an empty, uniquely named temporary sibling of ``path`` and return its path."""
    for _ in range(_MAX_NAME_TRIES):
        tmp = path.with_name(f".{path.stem}.tmp-{secrets.token_hex(4)}{path.suffix}")
        try:
            # 0o666 filtered by the umask gives the permissions a plain open() would give;
            # tempfile.mkstemp would leave 0o600 on the final file.
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:
            continue
        except OSError as exc:
            raise StorageError(
                f"cannot write {path}: the directory {path.parent} is missing or not writable ({exc})", exc.errno
            ) from exc
        os.close(fd)
        return tmp
    raise ExportError(f"cannot write {path}: could not create a unique temporary file next to it")


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(directory: Path) -> None:
    """Persist the rename itself; not supported on every platform, so failures are ignored."""
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path to write; on normal exit it is fsynced and renamed to ``path``.

    For libraries that write by file name (OpenEXR, Pillow). The temporary file already exists
    (empty) when yielded; the library may overwrite or replace it. If the body raises, the temporary
    file is removed and the exception propagates; ``path`` is left untouched.

    Args:
        path: final destination. Its directory must exist.

    Raises:
        StorageError: the directory is missing or not writable, the disk is full, or the rename fails;
            names ``path`` (an ExportError; the CLI exits with status 3).

    Example:
        >>> with atomic_path("out/depth.exr") as tmp:  # doctest: +SKIP
        ...     exr_file.write(str(tmp))
    """
    final = Path(path)
    tmp = _create_temp(final)
    try:
        yield tmp
        _fsync_file(tmp)
        os.replace(tmp, final)
    except BaseException as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        if isinstance(exc, OSError) and not isinstance(exc, ExportError):
            raise StorageError(f"cannot write {final}: {exc.strerror or exc}", exc.errno) from exc
        raise
    _fsync_dir(final.parent)


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temporary sibling, fsync, :func:`os.replace`).

    Raises:
        StorageError: the directory is missing or not writable, or the disk is full; names ``path``.
    """
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
