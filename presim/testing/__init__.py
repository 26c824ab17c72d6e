"""Test fixtures with known answers, used by tests/ and benchmarks/ only (never by the product).

Modules: :mod:`~presim.testing.rect_scene` (textured rectangles ray cast exactly: the synthetic
room of the view-synthesis tests and benchmarks), :mod:`~presim.testing.two_planes` (two-plane
RGB-D scene for depth refinement and evaluation), :mod:`~presim.testing.toy_scene` (box room with a
pillar for the simulator), :mod:`~presim.testing.steps` (synthetic step-loop output for the sinks),
:mod:`~presim.testing.browser` (headless-Chromium screenshots of the web viewer).

This sub-package may import anything in ``presim``; nothing in the product imports it
(``tests/test_layering.py`` checks both).
"""
