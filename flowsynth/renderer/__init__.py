"""Rendering: ``render`` / ``render_plan`` run a plan's stages on one device (``pipeline``: one primary cast per frame,
then ``flowsynth.truth``), ``render_batch`` B scenes at once (``batch``), the RGB image (``shading``), the final pass
(``finalpass``); ``pipeline`` and ``shading`` are exported as modules for benchmarks that time their parts."""

from flowsynth.renderer import pipeline, shading
from flowsynth.renderer.batch import BATCH_KEYS, batch_tables, check_batch_plan, render_batch, render_batch_plan
from flowsynth.renderer.finalpass import draw_final
from flowsynth.renderer.pipeline import gbuffer_outputs, render, render_plan

__all__ = ["BATCH_KEYS", "batch_tables", "check_batch_plan", "draw_final", "gbuffer_outputs", "pipeline", "render",
           "render_batch", "render_batch_plan", "render_plan", "shading"]
