"""Capture importers: one module per format, all returning :class:`presim.capture.scene.Scene`.

Entry point: :func:`import_capture` (format auto-detected). See docs/importers.md.
"""

from presim.capture.importers.registry import FORMATS, detect_format, import_capture, importer

__all__ = ["FORMATS", "detect_format", "import_capture", "importer"]
