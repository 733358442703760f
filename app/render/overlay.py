"""Colours for vertices; the overlay's words; text, legends and contact points drawn onto finished images.

They are drawn with Pillow into the image itself because GGUI's widgets do not
appear in offscreen images, and the software renderer has none; drawn after
rendering, they look the same whichever renderer made the picture.
"""

import functools

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from app.render.camera import Camera

# Distinct, soft colours for telling bodies apart (RGB in [0, 1]).
BODY_PALETTE = np.array([
    [0.91, 0.49, 0.36],  # coral
    [0.36, 0.61, 0.84],  # blue
    [0.52, 0.75, 0.42],  # green
    [0.96, 0.76, 0.33],  # amber
    [0.67, 0.52, 0.82],  # violet
    [0.36, 0.77, 0.75],  # teal
    [0.91, 0.55, 0.71],  # pink
    [0.72, 0.60, 0.45],  # tan
])

# Colour maps as evenly spaced control points from the low end to the high end.
COLORMAPS = {
    # Moreland's cool-warm: blue below, light grey at the middle, red above.
    "coolwarm": np.array([
        [0.230, 0.299, 0.754], [0.554, 0.690, 0.996], [0.865, 0.865, 0.865],
        [0.958, 0.603, 0.482], [0.706, 0.016, 0.150],
    ]),
    # Perceptually uniform dark-blue-to-yellow, for magnitudes such as stress.
    "viridis": np.array([
        [0.267, 0.005, 0.329], [0.229, 0.322, 0.546], [0.128, 0.567, 0.551],
        [0.369, 0.789, 0.383], [0.993, 0.906, 0.144],
    ]),
}

TEXT_COLOR = (255, 255, 255, 255)
PANEL_COLOR = (20, 24, 32, 150)  # translucent dark, readable over any scene
# Contact points: magenta, a colour no body palette entry or colour map comes near, outlined in dark.
CONTACT_COLOR = (255, 0, 255)
CONTACT_OUTLINE = (20, 24, 32)


def body_colors(body_index) -> np.ndarray:
    """Colours (n, 3) in [0, 1]: vertex i gets the palette colour of body body_index[i]."""
    return BODY_PALETTE[np.asarray(body_index) % len(BODY_PALETTE)]


def scalar_colors(values, vmin: float, vmax: float, colormap: str = "coolwarm") -> np.ndarray:
    """Colours (n, 3) in [0, 1] for values (n,), vmin at the low end of the map
    and vmax at the high end; values outside are clamped.

    For volume change J = det(F), use vmin, vmax symmetric about 1 with
    "coolwarm": compressed is blue, unchanged grey, stretched red.
    """
    stops = COLORMAPS[colormap]
    t = np.clip((np.asarray(values, dtype=np.float64) - vmin) / (vmax - vmin), 0.0, 1.0)
    positions = np.linspace(0.0, 1.0, len(stops))
    return np.stack([np.interp(t, positions, stops[:, k]) for k in range(3)], axis=1)


@functools.cache
def _font(size: int) -> ImageFont.FreeTypeFont:
    """Pillow's own font at size pixels (loaded once: an export draws it on every frame)."""
    return ImageFont.load_default(size=size)


def _caption_font(image_height: int) -> ImageFont.FreeTypeFont:
    return _font(max(11, image_height // 32))


def blended(image: np.ndarray, layer: Image.Image) -> np.ndarray:
    """A copy of image (H, W, 3) uint8 with the translucent RGBA layer of its size laid over it.
    Only the part of the layer drawn on is blended: over a whole 640 x 480 frame, blending took
    more time than the drawing."""
    canvas = Image.fromarray(image)
    box = layer.getbbox()
    if box is not None:
        drawn = Image.alpha_composite(canvas.crop(box).convert("RGBA"), layer.crop(box))
        canvas.paste(drawn.convert("RGB"), box[:2])
    return np.asarray(canvas)


def _corner_origin(corner: str, box_size, image_size, margin: int):
    """Top-left pixel of a box of box_size (w, h) placed in a corner of the image."""
    vertical, horizontal = corner.split("-")
    x = margin if horizontal == "left" else image_size[0] - box_size[0] - margin
    y = margin if vertical == "top" else image_size[1] - box_size[1] - margin
    return x, y


def draw_text_overlay(image: np.ndarray, lines: list[str], corner: str = "top-left") -> np.ndarray:
    """A copy of image (H, W, 3) uint8 with lines of text on a translucent panel.

    corner: "top-left", "top-right", "bottom-left" or "bottom-right".
    """
    layer = Image.new("RGBA", (image.shape[1], image.shape[0]), (0, 0, 0, 0))
    draw = ImageDraw.Draw(layer)
    font = _caption_font(layer.height)
    line_height = round(font.size * 1.35)
    padding = font.size // 2
    text_width = max((draw.textlength(line, font=font) for line in lines), default=0)
    box = (round(text_width) + 2 * padding, line_height * len(lines) + 2 * padding)
    x, y = _corner_origin(corner, box, layer.size, margin=padding)
    draw.rounded_rectangle([x, y, x + box[0], y + box[1]], radius=padding, fill=PANEL_COLOR)
    for row, line in enumerate(lines):
        draw.text((x + padding, y + padding + row * line_height), line, font=font, fill=TEXT_COLOR)
    return blended(image, layer)


LISTED = 4    # bodies named one by one in the volume line; a pile's 20 ran off the 640-pixel panel


def volume_line(bodies: list[tuple[str, str, float]]) -> str:
    """Each body's volume / rest volume by method, every method and name said once, e.g.
    "volume / rest volume: linear 1.82 | corotational 1.00" (epcot --compare), or
    "volume / rest volume: linear soft 1.31 | corotational stiff 1.00"; more than LISTED bodies
    under a method, each method's range: "volume / rest volume of 20 bodies: corotational 0.98 to 1.01".

    bodies: (name, method, volume ratio) of each body of the simulation. Where every method
    holds the same bodies (--compare, or all bodies under one method), the names are given
    once, before the numbers, and only where there are several."""
    by_method = {}
    for name, method, ratio in bodies:
        by_method.setdefault(method, []).append((name, ratio))
    names = [[name for name, _ in group] for group in by_method.values()]
    shared = all(n == names[0] for n in names)
    if max(len(n) for n in names) > LISTED:        # a pile: each method's range, which fits on the panel
        head = f" of {len(names[0])} bodies" if shared else ""
        parts = [f"{method} " + ("" if shared else f"{len(group)} bodies ") +
                 f"{min(r for _, r in group):.2f} to {max(r for _, r in group):.2f}"
                 for method, group in by_method.items()]
        return f"volume / rest volume{head}: " + " | ".join(parts)
    head = f" of {', '.join(names[0])}" if shared and len(names[0]) > 1 else ""
    parts = [f"{method} " + ", ".join(f"{ratio:.2f}" if shared else f"{name} {ratio:.2f}" for name, ratio in group)
             for method, group in by_method.items()]
    return f"volume / rest volume{head}: " + " | ".join(parts)


def draw_labels(image: np.ndarray, labels: list[tuple[str, float]]) -> np.ndarray:
    """A copy of image (H, W, 3) uint8 with each (text, x) of labels on a panel at the
    top of the image, centred at column x."""
    layer = Image.new("RGBA", (image.shape[1], image.shape[0]), (0, 0, 0, 0))
    draw = ImageDraw.Draw(layer)
    font = _font(max(12, layer.height // 20))
    padding = font.size // 3
    for text, centre in labels:
        left, top, right, bottom = draw.textbbox((0, 0), text, font=font)
        box_w, box_h = right - left + 2 * padding, bottom - top + 2 * padding
        x, y = round(centre - box_w / 2), padding
        draw.rounded_rectangle([x, y, x + box_w, y + box_h], radius=padding, fill=PANEL_COLOR)
        draw.text((x + padding - left, y + padding - top), text, font=font, fill=TEXT_COLOR)
    return blended(image, layer)


def draw_legend(image: np.ndarray, title: str, vmin: float, vmax: float,
                colormap: str = "coolwarm", corner: str = "bottom-right") -> np.ndarray:
    """A copy of image (H, W, 3) uint8 with a colour bar: title above, the map
    from vmin (left) to vmax (right), and the two end values and the middle below."""
    layer = Image.new("RGBA", (image.shape[1], image.shape[0]), (0, 0, 0, 0))
    draw = ImageDraw.Draw(layer)
    font = _caption_font(layer.height)
    padding = font.size // 2
    bar_width, bar_height = max(120, layer.width // 4), font.size
    line_height = round(font.size * 1.35)
    box = (bar_width + 2 * padding, 2 * line_height + bar_height + 2 * padding)
    x, y = _corner_origin(corner, box, layer.size, margin=padding)
    draw.rounded_rectangle([x, y, x + box[0], y + box[1]], radius=padding, fill=PANEL_COLOR)
    draw.text((x + padding, y + padding), title, font=font, fill=TEXT_COLOR)

    bar_top = y + padding + line_height
    ramp = scalar_colors(np.linspace(vmin, vmax, bar_width), vmin, vmax, colormap)
    ramp = (np.round(ramp * 255).astype(np.uint8)[None, :, :]).repeat(bar_height, axis=0)
    layer.paste(Image.fromarray(ramp).convert("RGBA"), (x + padding, bar_top))

    label_y = bar_top + bar_height + padding // 2
    labels = [(f"{vmin:g}", "la"), (f"{(vmin + vmax) / 2:g}", "ma"), (f"{vmax:g}", "ra")]
    for (text, anchor), fraction in zip(labels, (0.0, 0.5, 1.0)):
        draw.text((x + padding + fraction * bar_width, label_y), text, font=font,
                  fill=TEXT_COLOR, anchor=anchor)
    return blended(image, layer)


def draw_points(image: np.ndarray, points, camera: Camera) -> np.ndarray:
    """A copy of image (H, W, 3) uint8 with a dot where the camera sees each of points (n, 3),
    world metres: a CONTACT_COLOR disc a few pixels wide with a thin dark outline (dots that
    overlap merge into one outlined patch). Drawn over everything, with no depth test: a
    contact point lies between two surfaces, so nearly always behind one of them."""
    canvas = Image.fromarray(image)
    draw = ImageDraw.Draw(canvas)
    radius = max(2, round(canvas.height / 160))
    pixels, ahead = camera.to_pixels(points, canvas.width, canvas.height)
    # Only the dots that reach into the picture (Pillow takes coordinates as C integers).
    margin = radius + 1
    shown = ahead & (pixels >= -margin).all(axis=1) & (pixels <= np.add(canvas.size, margin)).all(axis=1)
    # Pillow's integer coordinates are pixel centres; repeated dots are drawn once.
    centres = np.unique(np.round(pixels[shown] - 0.5).astype(np.int64), axis=0)
    for grow, color in ((1, CONTACT_OUTLINE), (0, CONTACT_COLOR)):
        r = radius + grow
        for x, y in centres.tolist():
            draw.ellipse([x - r, y - r, x + r, y + r], fill=color)
    return np.asarray(canvas)
