"""Exception hierarchy. Every error the library raises on purpose derives from FlowsynthError."""

__all__ = ["AssetError", "ConfigError", "ExportError", "FlowsynthError", "ShapeError"]


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
