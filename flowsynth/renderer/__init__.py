"""Rendering: ``render`` / ``render_plan`` run the stages a plan asks for on one device (``pipeline``: one primary cast
per frame, then the ground truth of ``flowsynth.truth``), the RGB image (``shading``) and the final pass's camera
effects (``finalpass``); ``pipeline`` and ``shading`` are exported as modules for benchmarks that time their parts."""

from flowsynth.renderer import pipeline, shading
from flowsynth.renderer.finalpass import draw_final
from flowsynth.renderer.pipeline import gbuffer_outputs, render, render_plan

__all__ = ["draw_final", "gbuffer_outputs", "pipeline", "render", "render_plan", "shading"]
