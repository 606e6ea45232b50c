"""Export to disk: ``export_dataset`` writes samples in any registered layout with worker processes or Ray actors,
crash-safe and resumable (``exporter``: staging, journal, manifest), each unit of work made by one ``writer``;
``estimate`` sizes a run before it starts (``flowsynth export --dry-run``)."""

from flowsynth.export.exporter import ENGINES, JOURNAL, MANIFEST, Sizes, estimate, export_dataset

__all__ = ["ENGINES", "JOURNAL", "MANIFEST", "Sizes", "estimate", "export_dataset"]


def __getattr__(name: str):
    # ``export``, the function's former name (a function named like its module), still works with a
    # DeprecationWarning, and is bound nowhere (``flowsynth.export`` is always this folder).
    if name == "export":
        import warnings

        warnings.warn("flowsynth.export.export is deprecated; use flowsynth.export.export_dataset (the same "
                      "function)", DeprecationWarning, stacklevel=2)
        return export_dataset
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
