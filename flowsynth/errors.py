"""Exception hierarchy. Every error the library raises on purpose derives from FlowsynthError."""

__all__ = ["AssetError", "ConfigError", "DependencyError", "ExportError", "FlowsynthError", "ForkError", "ShapeError",
           "StorageError"]


class FlowsynthError(Exception):
    """Base class of every flowsynth error."""


class ConfigError(FlowsynthError, ValueError):
    """A configuration value or API argument is invalid; the message says which and how to fix it."""


class ForkError(FlowsynthError, RuntimeError):
    """This process was forked from one that had initialised CUDA, where Warp cannot run (CUDA does not survive
    ``fork()``); the message says how to start workers instead (``fs.datasets.loader``, forkserver or spawn)."""


class DependencyError(FlowsynthError, ImportError):
    """An optional package that a function needs is not installed; the message says what to install.
    The CLI exits with status 2."""


class AssetError(FlowsynthError, ValueError):
    """A mesh or texture cannot be used (missing file, no faces, non-finite vertices)."""


class ShapeError(FlowsynthError, ValueError):
    """A tensor or array has the wrong shape or dtype."""


class ExportError(FlowsynthError):
    """Writing or reading an exported dataset failed (a folder that holds something else, a conflicting manifest,
    a file that is not what its layout says). The CLI exits with status 2.

    Not an ``OSError``: most export errors are bad input, not the operating system's. What the file system refused
    is a :class:`StorageError`, which is both.
    """


class StorageError(ExportError, OSError):
    """The file system refused a read or write (disk full, permission denied, a file vanished).

    Not bad input: the same command can succeed once the cause is fixed. ``errno`` holds the OS error
    number when there was one. An ``OSError`` as well as an ExportError, so ``except OSError`` still catches it.
    The CLI exits with status 3.
    """

    def __init__(self, message: str, errno: int | None = None) -> None:
        super().__init__(message)
        self.errno = errno
