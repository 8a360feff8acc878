"""Captions in the image: a title, a one-line caption and a legend, in a white
band above a rendered figure, so a PNG explains itself wherever it ends up."""

from __future__ import annotations

import numpy as np

from ._scene import FRUSTUM_COLOR, level_colors

# Legend entry for faces coloured by batch level (render ``color_levels``).
LEVELS = "levels"
# The swatch of the refining camera's frustum lines.
FRUSTUM_SWATCH = tuple(int(255 * c) for c in FRUSTUM_COLOR[:3])


def _font(size: int):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: one bitmap size
        return ImageFont.load_default()


def _wrap(draw, text: str, font, width: int) -> list[str]:
    lines, line = [], ""
    for word in text.split():
        trial = f"{line} {word}".strip()
        if line and draw.textlength(trial, font=font) > width:
            lines.append(line)
            line = word
        else:
            line = trial
    return lines + [line] if line else lines


def annotate(rgb, title: str, caption: str, legend=()) -> np.ndarray:
    """Return ``rgb`` (``uint8[H, W, 3]``) below a band holding ``title``,
    ``caption`` (wrapped to the width) and ``legend`` entries.

    Args:
        legend: entries ``(colour, label)`` with an RGB triple (0-255) drawn as a
            swatch, or ``(LEVELS, label)`` drawn as the batch-level colour ramp
            from fine (blue) to coarse (red).

    Returns:
        ``uint8[H + band, W, 3]``.
    """
    from PIL import Image, ImageDraw

    rgb = np.asarray(rgb, np.uint8)
    H, W = rgb.shape[:2]
    big, small = _font(max(12, W // 36)), _font(max(10, W // 56))
    pad = max(4, W // 100)
    probe = ImageDraw.Draw(Image.new("RGB", (W, 10)))
    lines = _wrap(probe, caption, small, W - 2 * pad)
    line_h = int(small.size * 1.3) if hasattr(small, "size") else 14
    title_h = int(big.size * 1.4) if hasattr(big, "size") else 16
    band = pad + title_h + line_h * len(lines) + (line_h + pad if legend else 0) + pad
    image = Image.new("RGB", (W, H + band), (255, 255, 255))
    image.paste(Image.fromarray(rgb), (0, band))
    draw = ImageDraw.Draw(image)
    y = pad
    draw.text((pad, y), title, fill=(0, 0, 0), font=big)
    y += title_h
    for line in lines:
        draw.text((pad, y), line, fill=(40, 40, 40), font=small)
        y += line_h
    x, box = pad, max(8, line_h - 4)
    for colour, label in legend:
        if colour == LEVELS:
            ramp = (level_colors(np.linspace(0, 1, 4 * box), 1)[:, :3] * 255).astype(np.uint8)
            for i, c in enumerate(ramp):
                draw.line([(x + i, y + 1), (x + i, y + box)], fill=tuple(int(v) for v in c))
            x += 4 * box + pad // 2
        else:
            draw.rectangle([x, y + 1, x + box, y + box], fill=tuple(colour), outline=(0, 0, 0))
            x += box + pad // 2
        draw.text((x, y), label, fill=(40, 40, 40), font=small)
        x += int(draw.textlength(label, font=small)) + 2 * pad
    return np.asarray(image)
