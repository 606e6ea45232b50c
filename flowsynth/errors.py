"""Exception hierarchy. Every error the library raises on purpose derives from FlowsynthError."""

__all__ = ["AssetError", "ConfigError", "ExportError", "FlowsynthError", "ShapeError", "StorageError"]


class FlowsynthError(Exception):
    """Base class of every flowsynth error."""


class ConfigError(FlowsynthError, ValueError):
    """A configuration value or API argument is invalid; the message says which and how to fix it."""


class AssetError(FlowsynthError, ValueError):
    """A mesh or texture cannot be used (missing file, no faces, non-finite vertices)."""


class ShapeError(FlowsynthError, ValueError):
    """A tensor or array has the wrong shape or dtype."""


class ExportError(FlowsynthError, OSError):
    """Writing or reading an exported dataset failed (unwritable folder, conflicting manifest)."""


class StorageError(ExportError):
    """The file system refused a read or write (disk full, permission denied, a file vanished).

    Not bad input: the same command can succeed once the cause is fixed. ``errno`` holds the OS error
    number when there was one. The CLI exits with status 3.
    """

    def __init__(self, message: str, errno: int | None = None) -> None:
        super().__init__(message)
        self.errno = errno
