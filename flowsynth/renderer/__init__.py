"""Rendering: ``render_batch`` renders B scenes at once (``batch``: ``batch_outputs``, every batched key), ``render``
is its batch of one plus the per-scene stages (``pipeline``), the RGB image (``shading``), the final pass
(``finalpass``); ``pipeline`` and ``shading`` are exported as modules for benchmarks that time their parts."""

from flowsynth.renderer import pipeline, shading
from flowsynth.renderer.batch import (BATCH_KEYS, batch_outputs, batch_tables, check_batch_plan, gbuffer_outputs,
                                      render_batch, render_batch_plan)
from flowsynth.renderer.finalpass import draw_final
from flowsynth.renderer.pipeline import render, render_plan

__all__ = ["BATCH_KEYS", "batch_outputs", "batch_tables", "check_batch_plan", "draw_final", "gbuffer_outputs",
           "pipeline", "render", "render_batch", "render_batch_plan", "render_plan", "shading"]
