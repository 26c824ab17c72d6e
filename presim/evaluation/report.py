"""Pictures of a leave-one-out evaluation: one strip per target and method, and a Markdown report.

A strip is four panels side by side, at the target's resolution (or ``panel_width``)::

    real | rendered (delivered, filled) | |error| heat map | holes (before fill)

- ``|error|``: mean absolute difference over R, G, B in grey levels, colour-mapped (inferno) from 0 to
  ``err_max`` (default 64 levels; larger errors saturate); the colour bar under the panel states
  the scale. Pixels outside the target's validity mask are grey.
- holes: the pixels no view covered (``RGBD.valid`` is False; the renderer filled them) in
  magenta, over the rendered image's luminance at 30 %.

Below the panels one line gives the target, the method and its metrics. Strips are written with
OpenCV only (~0.1 s per 640x480 strip), atomically. :func:`write_report` writes ``report.md``:
the results table, then the five worst targets by the ranking method's delivered PSNR, each with
the strips of every method, then the other targets in capture order.

Example::

    strip = eval_strip(real, out.color, out.valid, caption="frame-000005 default: 24.1 dB")
    write_png("frame-000005_default.png", strip)
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import cv2
import numpy as np

from presim.io_utils import atomic_write_text, write_png

__all__ = ["ERR_MAX", "HOLE_RGB", "PANELS", "WORST_N", "eval_strip", "strip_layout", "strip_name",
           "ranking_method", "write_report"]

ERR_MAX = 64.0
"""Grey levels at which the error heat map saturates (a quarter of the range: typical view-synthesis
errors are 5-30 levels, so the map keeps contrast where it matters)."""
HOLE_RGB = (255, 0, 255)
"""Colour of the hole pixels in the holes panel."""
PANELS = ("real", "rendered", "|error|", "holes (before fill)")
WORST_N = 5
"""Targets shown first in report.md."""
_INVALID_RGB = (128, 128, 128)


def strip_layout(height: int, width: int) -> tuple[int, int]:
    """(caption band height above the panels, band height below them) in pixels for panels of
    ``height`` x ``width``."""
    top = max(14, round(width * 0.035))
    return top, 2 * top


def _text(img: np.ndarray, text: str, org: tuple[int, int], band_h: int, max_w: int | None = None) -> None:
    """White text with its baseline at ``org``, sized to the band and shrunk to fit ``max_w`` pixels."""
    scale = band_h / 40.0
    if max_w is not None:
        w = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0]
        scale *= min(1.0, max_w / max(w, 1))
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


def _heat(err: np.ndarray, err_max: float) -> np.ndarray:
    """RGB inferno colours of ``err`` (float, grey levels) scaled 0..err_max."""
    u8 = np.clip(err * (255.0 / err_max), 0, 255).astype(np.uint8)
    return cv2.cvtColor(cv2.applyColorMap(u8, cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)


def eval_strip(real: np.ndarray, rendered: np.ndarray, valid: np.ndarray, caption: str = "",
               real_valid: np.ndarray | None = None, err_max: float = ERR_MAX,
               panel_width: int | None = None) -> np.ndarray:
    """The strip of one rendered target (see module docstring).

    Args:
        real, rendered: uint8 (H, W, 3) RGB: the target's real image and the delivered render.
        valid: bool (H, W), True where a view covered the pixel (``RGBD.valid``); False = hole.
        caption: one line written below the panels.
        real_valid: bool (H, W) pixels where the real image has data (None = all).
        err_max: grey levels at which the heat map saturates.
        panel_width: width of each panel in pixels (None = W); the height keeps the aspect ratio.
    Returns:
        uint8 (top + h + bottom, 4 w, 3) RGB with ``(top, bottom) = strip_layout(h, w)``.
    """
    H, W = valid.shape
    if real.shape != (H, W, 3) or rendered.shape != (H, W, 3):
        raise ValueError(f"eval_strip: real {real.shape} and rendered {rendered.shape} must be ({H}, {W}, 3)")
    if not err_max > 0:
        raise ValueError(f"eval_strip: err_max must be > 0, got {err_max}")
    err = np.abs(rendered.astype(np.float32) - real.astype(np.float32)).mean(axis=2)
    heat = _heat(err, err_max)
    if real_valid is not None:
        heat[~real_valid] = _INVALID_RGB
    shade = (cv2.cvtColor(rendered, cv2.COLOR_RGB2GRAY).astype(np.float32) * 0.3).astype(np.uint8)
    holes = np.repeat(shade[..., None], 3, axis=2)
    holes[~valid] = HOLE_RGB
    panels = [real, rendered, heat, holes]
    w = W if panel_width is None else int(panel_width)
    if w < 1:
        raise ValueError(f"eval_strip: panel_width must be >= 1, got {panel_width}")
    h = H if w == W else max(1, round(H * w / W))
    if (h, w) != (H, W):
        # Area averaging for images; nearest for the hole colours (a hole stays magenta, not pink).
        panels = [cv2.resize(p, (w, h), interpolation=cv2.INTER_NEAREST if i == 3 else cv2.INTER_AREA)
                  for i, p in enumerate(panels)]
    top, bottom = strip_layout(h, w)
    out = np.zeros((top + h + bottom, 4 * w, 3), np.uint8)
    base = max(3, top // 4)  # text baseline above the bottom of its band
    for i, (p, title) in enumerate(zip(panels, PANELS)):
        out[top:top + h, i * w:(i + 1) * w] = p
        _text(out, title, (i * w + 4, top - base), top, max_w=w - 8)
    # First band below the panels: the colour bar of the heat map, 0 .. err_max grey levels, with
    # its labels left and right of it.
    lab = max(8, w // 5)
    x0, x1 = 2 * w + lab, 3 * w - lab
    y0, bar_h = top + h + top // 4, max(2, top // 2)
    ramp = np.linspace(0, err_max, max(1, x1 - x0), dtype=np.float32)[None, :]
    out[y0:y0 + bar_h, x0:x1] = _heat(np.repeat(ramp, bar_h, axis=0), err_max)
    _text(out, "0", (x0 - lab + 2, 2 * top + h - base), top, max_w=lab - 4)
    _text(out, f"{err_max:g}+", (x1 + 3, 2 * top + h - base), top, max_w=lab - 4)
    _text(out, "grey levels", (3 * w + 4, 2 * top + h - base), top, max_w=w - 8)
    if caption:  # second band: one line across the strip
        _text(out, caption, (4, 3 * top + h - base), top, max_w=4 * w - 8)
    return out


def strip_name(target_id: str, method: str) -> str:
    """File name of a strip: ``<target>_<method>.png`` with unsafe characters replaced by ``_``."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", f"{target_id}_{method}") + ".png"


def ranking_method(methods: list[str] | tuple[str, ...]) -> str:
    """The method that ranks targets: ``default`` when evaluated, else the first one."""
    if not methods:
        raise ValueError("ranking_method: no evaluated method")
    return "default" if "default" in methods else methods[0]


def _fmt(x: float, pattern: str) -> str:
    return "n/a" if x is None or not math.isfinite(x) else format(x, pattern)


def _target_table(per: dict[str, dict[str, float]]) -> list[str]:
    lines = ["| method | PSNR dB | PSNR covered dB | PSNR holes dB | SSIM | hole % |", "|---|---|---|---|---|---|"]
    for name, m in per.items():
        lines.append(f"| {name} | {_fmt(m['psnr_db'], '.2f')} | {_fmt(m['psnr_covered_db'], '.2f')} | "
                     f"{_fmt(m['psnr_hole_db'], '.2f')} | {_fmt(m['ssim'], '.4f')} | {_fmt(100 * m['hole_frac'], '.2f')} |")
    return lines


def write_report(path: str | Path, table: str, target_ids: list[str],
                 per_target: dict[str, list[dict[str, float]]], protocol: str = "") -> Path:
    """Write ``report.md`` (atomically) next to the strips of :func:`strip_name`.

    Args:
        path: the report file (strips are linked relative to its folder).
        table: the Markdown table of the per-method means (``format_table``).
        target_ids: the evaluated targets in capture order.
        per_target: method -> one metrics dict per target (same order as ``target_ids``).
        protocol: one line describing the run (scene, stride, targets).
    Returns:
        ``path``.
    """
    path = Path(path)
    methods = list(per_target)
    rank = ranking_method(methods)
    psnr = [per_target[rank][i]["psnr_db"] for i in range(len(target_ids))]
    # NaN (never expected for the delivered image) ranks last.
    order = sorted(range(len(target_ids)), key=lambda i: (not math.isfinite(psnr[i]), psnr[i]))
    worst = order[:WORST_N]
    rest = [i for i in range(len(target_ids)) if i not in worst]
    lines = ["# View-synthesis evaluation", ""]
    if protocol:
        lines += [protocol, ""]
    lines += [table, "",
              f"Strips: {' | '.join(PANELS)}. The error is the mean absolute difference over R, G, B, "
              f"0 to {ERR_MAX:g} grey levels (colour bar; larger errors saturate). Holes: pixels no view "
              f"covered (magenta), filled in the delivered image. `PSNR holes` is computed on those pixels "
              f"alone (n/a: none).", ""]

    def section(i: int) -> list[str]:
        tid = target_ids[i]
        out = [f"### {tid}: {rank} {_fmt(psnr[i], '.2f')} dB", ""]
        out += _target_table({m: per_target[m][i] for m in methods}) + [""]
        out += [f"![{tid} {m}]({strip_name(tid, m)})" for m in methods] + [""]
        return out

    lines += [f"## The {len(worst)} worst targets (by `{rank}` PSNR)", ""]
    for i in worst:
        lines += section(i)
    if rest:
        lines += ["## Other targets (capture order)", ""]
        for i in rest:
            lines += section(i)
    atomic_write_text(path, "\n".join(lines))
    return path

