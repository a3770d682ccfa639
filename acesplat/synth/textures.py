"""Procedural surface textures built from sample photographs, noise, shapes and text.

Every surface gets its own texture covering it exactly once (no tiling of one image), so no two
places in the room look alike: repeated patterns would make scene coordinate regression ambiguous.
Photographs give feature-rich detail; random crops, magnifications, colour transforms, per-tile
variation, posters, shapes and text make each surface distinct. Textures are float32 RGB in [0, 1],
``(h, w, 3)`` with ``rho`` texels per metre; row 0 is the top of the surface as seen from outside.
"""

from __future__ import annotations

import string
from collections.abc import Sequence

import cv2
import numpy as np

from acesplat.synth.photos import Photo

FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)
GLYPHS = string.ascii_uppercase + string.digits


def value_noise(
    rng: np.random.Generator, h: int, w: int, cell: float, octaves: int = 4, gain: float = 0.55
) -> np.ndarray:
    """Multi-octave smooth noise (h, w) with roughly unit spread; ``cell`` is the coarsest feature size in texels."""
    out = np.zeros((h, w), dtype=np.float32)
    amp, total = 1.0, 0.0
    for _ in range(octaves):
        gh, gw = max(2, int(h / max(cell, 1.0)) + 2), max(2, int(w / max(cell, 1.0)) + 2)
        grid = rng.standard_normal((gh, gw)).astype(np.float32)
        out += amp * cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp * amp
        amp *= gain
        cell /= 2.0
        if cell < 1.0:
            break
    return out / np.float32(np.sqrt(total))


def random_color(
    rng: np.random.Generator,
    sat: tuple[float, float],
    val: tuple[float, float],
    hue: tuple[float, float] = (0.0, 180.0),
) -> np.ndarray:
    """An RGB colour (3,) from random hue (OpenCV's 0..180 scale), saturation and value in ranges."""
    hsv = np.array([[[rng.uniform(*hue), rng.uniform(*sat) * 255, rng.uniform(*val) * 255]]], dtype=np.float32)
    return cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB).reshape(3).astype(np.float32) / 255.0


def gray(img: np.ndarray) -> np.ndarray:
    """Luminance (h, w) of an RGB float image."""
    return cv2.cvtColor(np.ascontiguousarray(img, dtype=np.float32), cv2.COLOR_RGB2GRAY)


def recolor(rng: np.random.Generator, img: np.ndarray, gray_source: bool, strength: float = 1.0) -> np.ndarray:
    """A random colour transform of an RGB image (h, w, 3): duotone for gray photos, channel mix otherwise."""
    if gray_source:
        dark = random_color(rng, (0.1, 0.6), (0.05, 0.45))
        light = random_color(rng, (0.05, 0.4), (0.6, 1.0))
        out = (
            cv2.transform(np.ascontiguousarray(img, dtype=np.float32), np.diag(light - dark).astype(np.float32)) + dark
        )
    else:
        mix = np.eye(3, dtype=np.float32) + rng.normal(0.0, 0.15 * strength, (3, 3)).astype(np.float32)
        mix /= mix.sum(axis=1, keepdims=True)
        out = cv2.transform(np.ascontiguousarray(img, dtype=np.float32), mix)
    gain = rng.uniform(0.75, 1.2)
    bias = rng.uniform(-0.08, 0.08)
    contrast = rng.uniform(0.8, 1.3)
    mean = np.array(cv2.mean(out)[:3], dtype=np.float32)
    # (out - mean) * contrast + mean * gain + bias, as one affine map per channel
    out = out * np.float32(contrast) + (mean * np.float32(gain - contrast) + np.float32(bias))
    return np.clip(out, 0.0, 1.0, out=out)


def photo_region(rng: np.random.Generator, photo: Photo, h: int, w: int, mag: float) -> np.ndarray:
    """A random crop of ``photo`` resized to (h, w, 3) at ``mag`` texels per photo pixel (more if it is small).

    Materials are also turned by a random multiple of 90 degrees; photos without text may be mirrored.
    The crop is resized before it is turned, so only the small result is copied.
    """
    k = int(rng.integers(4)) if photo.is_material else 0  # pictures stay upright
    mirror = rng.random() < 0.5 and not photo.has_text
    th, tw = (w, h) if k % 2 else (h, w)  # size before turning
    img = photo.image
    ph, pw = img.shape[:2]
    mag = max(mag, th / ph, tw / pw)
    ch, cw = min(ph, max(1, round(th / mag))), min(pw, max(1, round(tw / mag)))
    y0 = int(rng.integers(0, ph - ch + 1))
    x0 = int(rng.integers(0, pw - cw + 1))
    interp = cv2.INTER_AREA if mag < 1.0 else cv2.INTER_LINEAR
    out = cv2.resize(img[y0 : y0 + ch, x0 : x0 + cw], (tw, th), interpolation=interp)
    if k:
        out = np.rot90(out, k)
    if mirror:
        out = out[:, ::-1]
    return np.ascontiguousarray(out)


def _pick(
    rng: np.random.Generator,
    photos: Sequence[Photo],
    material: bool | None = None,
    min_side: int = 0,
    min_brightness: float = 0.0,
) -> Photo | None:
    if not photos:
        return None
    pool = [
        p
        for p in photos
        if (material is None or p.is_material == material)
        and min(p.image.shape[:2]) >= min_side
        and p.brightness >= min_brightness
    ] or list(photos)
    return pool[int(rng.integers(len(pool)))]


def _procedural_fill(rng: np.random.Generator, h: int, w: int, rho: float) -> np.ndarray:
    """Colourful noise patches: the stand-in for a photograph when none is installed."""
    a, b = random_color(rng, (0.3, 0.9), (0.2, 0.6)), random_color(rng, (0.1, 0.7), (0.6, 1.0))
    n = value_noise(rng, h, w, cell=rng.uniform(0.05, 0.3) * rho, octaves=6, gain=0.7)
    m = np.clip(0.5 + 0.35 * n, 0.0, 1.0)[..., None]
    return (a + m * (b - a)).astype(np.float32)


def fill(
    rng: np.random.Generator,
    photos: Sequence[Photo],
    h: int,
    w: int,
    rho: float,
    material: bool | None,
    mag_m: tuple[float, float],
    min_brightness: float = 0.0,
) -> np.ndarray:
    """A recoloured photo crop (or procedural fill) of (h, w, 3); ``mag_m`` is the photo pixel size range in metres."""
    photo = _pick(rng, photos, material, min_brightness=min_brightness)
    if photo is None:
        return _procedural_fill(rng, h, w, rho)
    mag = rho * rng.uniform(*mag_m)
    return recolor(rng, photo_region(rng, photo, h, w, mag), photo.gray_source)


def _grain(rng: np.random.Generator, img: np.ndarray, rho: float, amount: float) -> np.ndarray:
    """Low-frequency blotches plus fine grain: detail at close range where magnified photos go soft."""
    h, w = img.shape[:2]
    low = value_noise(rng, h, w, cell=rng.uniform(0.4, 1.2) * rho, octaves=3)
    fine = value_noise(rng, h, w, cell=max(2.0, 0.02 * rho), octaves=2)
    return np.clip(img * (1.0 + amount * (0.6 * low + 0.4 * fine))[..., None], 0.0, 1.0)


def _to_u8(img: np.ndarray) -> np.ndarray:
    return np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _contrast_color(rng: np.random.Generator, under: np.ndarray) -> tuple[int, int, int]:
    bright = float(under.mean()) > 110
    c = random_color(rng, (0.0, 1.0), (0.0, 0.3) if bright else (0.75, 1.0))
    return tuple(int(v * 255) for v in c)


def decorate(rng: np.random.Generator, canvas: np.ndarray, rho: float, count: int) -> None:
    """Draw ``count`` random anti-aliased shapes, strokes and text labels onto a uint8 canvas in place."""
    h, w = canvas.shape[:2]
    for _ in range(count):
        kind = rng.choice(["text", "text", "text", "circle", "rect", "line", "poly"])
        size = rng.uniform(0.02, 0.12) * rho
        x, y = int(rng.integers(0, w)), int(rng.integers(0, h))
        under = canvas[min(y, h - 1), min(x, w - 1)]
        color = _contrast_color(rng, under)
        thick = max(1, int(round(rng.uniform(0.004, 0.02) * rho)))
        if kind == "text":
            text = "".join(rng.choice(list(GLYPHS), size=int(rng.integers(2, 9))))
            font = FONTS[int(rng.integers(len(FONTS)))]
            scale = max(0.3, size / 22.0)
            cv2.putText(canvas, text, (x, y), font, scale, color, max(1, int(scale * 1.5)), cv2.LINE_AA)
        elif kind == "circle":
            cv2.circle(canvas, (x, y), max(2, int(size / 2)), color, -1 if rng.random() < 0.5 else thick, cv2.LINE_AA)
        elif kind == "rect":
            x2, y2 = x + int(size * rng.uniform(0.5, 2)), y + int(size * rng.uniform(0.5, 2))
            cv2.rectangle(canvas, (x, y), (x2, y2), color, -1 if rng.random() < 0.5 else thick, cv2.LINE_AA)
        elif kind == "line":
            ang = rng.uniform(0, np.pi)
            L = size * rng.uniform(1, 4)
            p2 = (int(x + L * np.cos(ang)), int(y + L * np.sin(ang)))
            cv2.line(canvas, (x, y), p2, color, thick, cv2.LINE_AA)
        else:
            n = int(rng.integers(3, 7))
            ang = np.sort(rng.uniform(0, 2 * np.pi, n))
            rad = size * rng.uniform(0.3, 1.0, n)
            pts = np.stack([x + rad * np.cos(ang), y + rad * np.sin(ang)], axis=1).astype(np.int32)
            cv2.fillPoly(canvas, [pts], color, cv2.LINE_AA)


def _paste(dst: np.ndarray, src: np.ndarray, x0: int, y0: int) -> None:
    h, w = dst.shape[:2]
    sh, sw = src.shape[:2]
    xa, ya, xb, yb = max(0, x0), max(0, y0), min(w, x0 + sw), min(h, y0 + sh)
    if xa < xb and ya < yb:
        dst[ya:yb, xa:xb] = src[ya - y0 : yb - y0, xa - x0 : xb - x0]


def _frame(rng: np.random.Generator, h: int, w: int, rho: float, pic: np.ndarray) -> np.ndarray:
    """A picture with a border (a poster, a framed print or a rug)."""
    b = max(1, int(round(rng.uniform(0.01, 0.05) * rho)))
    color = random_color(rng, (0.0, 0.8), (0.05, 0.95))
    out = np.empty((h, w, 3), dtype=np.float32)
    out[:] = color
    if h > 2 * b and w > 2 * b:
        out[b : h - b, b : w - b] = pic[b : h - b, b : w - b]
    return out


def _strips(
    rng: np.random.Generator, photos: Sequence[Photo], h: int, w: int, rho: float, tint: np.ndarray
) -> np.ndarray:
    """Wallpaper-like vertical strips, each from its own photo, orientation and offset, under one tint.

    One magnified photo cannot cover a whole wall at a fine scale without repeating; strips of
    different crops can, and look like panels of paper or boards.
    """
    out = np.empty((h, w, 3), dtype=np.float32)
    x = 0
    while x < w:
        sw = min(w - x, max(4, int(rng.uniform(0.45, 0.9) * rho)))
        photo = _pick(rng, photos, True, min_side=400)
        if photo is None:
            g = 0.5 + 0.25 * value_noise(rng, h, sw, cell=rng.uniform(0.02, 0.1) * rho, octaves=5, gain=0.7)
        else:
            g = gray(photo_region(rng, photo, h, sw, rho * rng.uniform(0.0025, 0.006)))
            g = (g - g.mean()) / (g.std() + 1e-3) * 0.18 + 0.5
        out[:, x : x + sw] = (tint * (0.55 + 0.9 * np.clip(g, 0, 1)[..., None])) * np.float32(rng.uniform(0.94, 1.06))
        x += sw
    return out


def wall_texture(rng: np.random.Generator, photos: Sequence[Photo], h: int, w: int, rho: float) -> np.ndarray:
    """A wall: paper strips or painted plaster, optional wainscot, skirting board, posters, marks and text."""
    base = random_color(rng, (0.03, 0.3), (0.55, 0.9))
    if rng.random() < 0.65:
        img = _strips(rng, photos, h, w, rho, base)
    else:
        img = np.empty((h, w, 3), dtype=np.float32)
        img[:] = base
        plaster = gray(fill(rng, photos, h, w, rho, True, (0.004, 0.012)))[..., None]
        img = img * (0.75 + 0.5 * plaster)
    if rng.random() < 0.45:
        wh = int(rng.uniform(0.7, 1.1) * rho)
        if wh < h - 2:
            panel = _strips(rng, photos, wh, w, rho, random_color(rng, (0.15, 0.6), (0.3, 0.7), hue=(5, 30)))
            img[h - wh :] = panel
            img[h - wh : h - wh + max(1, int(0.02 * rho))] *= 0.6
    img = _grain(rng, np.clip(img, 0, 1), rho, rng.uniform(0.08, 0.2))
    sk = max(2, int(rng.uniform(0.06, 0.12) * rho))
    img[h - sk :] = random_color(rng, (0.0, 0.4), (0.2, 0.9)) * (
        0.9 + 0.1 * value_noise(rng, sk, w, cell=0.1 * rho)[..., None]
    )
    area = h * w / rho**2
    for _ in range(int(rng.integers(2, 4 + int(area / 3)))):
        pw, ph = int(rng.uniform(0.3, 1.2) * rho), int(rng.uniform(0.3, 0.9) * rho)
        pw, ph = max(4, min(pw, w - 2)), max(4, min(ph, h - 2))
        x0 = int(rng.integers(0, max(1, w - pw)))
        y0 = int(np.clip(rng.uniform(0.2, 0.7) * h - ph / 2, 0, max(0, h - ph)))
        pic = fill(rng, photos, ph, pw, rho, None, (0.0015, 0.006))
        _paste(img, _frame(rng, ph, pw, rho, pic), x0, y0)
    canvas = _to_u8(img)
    decorate(rng, canvas, rho, int(rng.uniform(3, 6) * max(1.0, area)))
    return canvas.astype(np.float32) / 255.0


def floor_texture(rng: np.random.Generator, photos: Sequence[Photo], h: int, w: int, rho: float) -> np.ndarray:
    """Tiles or planks, each cut from its own (disjoint) cell of a material photograph, plus a rug and marks."""
    if rng.random() < 0.5:
        tw = th = int(max(4, rng.uniform(0.25, 0.7) * rho))
        stagger = 0.0
    else:
        th = int(max(3, rng.uniform(0.12, 0.25) * rho))
        tw = int(max(6, rng.uniform(0.8, 1.6) * rho))
        stagger = rng.uniform(0.25, 0.5)
    rows, cols = -(-h // th), -(-w // tw) + 1
    # One source cell per tile, never shared: overlapping crops would repeat texture across the floor.
    material = fill(rng, photos, rows * th, cols * tw, rho, True, (0.002, 0.006), min_brightness=0.25)
    tint = (
        random_color(rng, (0.1, 0.6), (0.35, 0.8), hue=(5, 30))
        if rng.random() < 0.7
        else random_color(rng, (0.0, 0.15), (0.3, 0.8))
    )
    material = 0.35 * material + 0.65 * (1.3 * gray(material)[..., None] * tint)
    material *= np.float32(rng.uniform(0.35, 0.6) / max(float(np.mean(cv2.mean(material)[:3])), 0.05))  # not black
    cells = iter(rng.permutation(rows * cols))
    img = np.empty((h, w, 3), dtype=np.float32)
    for row, y in enumerate(range(0, h, th)):
        shift = int((row * stagger % 1.0) * tw)
        for x in range(-shift, w, tw):
            cell = int(next(cells))
            cy, cx = (cell // cols) * th, (cell % cols) * tw
            tile = material[cy : cy + th, cx : cx + tw] * np.float32(rng.uniform(0.8, 1.15))
            tile = tile * (1.0 + rng.normal(0, 0.04, 3)).astype(np.float32)
            _paste(img, tile, x, y)
    canvas = _to_u8(_grain(rng, np.clip(img, 0, 1), rho, rng.uniform(0.08, 0.2)))
    grout = tuple(int(v * 255) for v in random_color(rng, (0.0, 0.3), (0.1, 0.5)))
    gt = max(1, int(round(0.008 * rho)))
    for row, y in enumerate(range(0, h, th)):
        cv2.line(canvas, (0, y), (w, y), grout, gt, cv2.LINE_AA)
        shift = int((row * stagger % 1.0) * tw)
        for x in range(-shift, w, tw):
            cv2.line(canvas, (x, y), (x, y + th), grout, gt, cv2.LINE_AA)
    img = canvas.astype(np.float32) / 255.0
    if rng.random() < 0.7:
        rw, rh = int(rng.uniform(0.35, 0.6) * w), int(rng.uniform(0.35, 0.6) * h)
        pic = fill(rng, photos, rh, rw, rho, None, (0.003, 0.01))
        _paste(img, _frame(rng, rh, rw, rho, pic), int(rng.integers(0, w - rw + 1)), int(rng.integers(0, h - rh + 1)))
    canvas = _to_u8(img)
    decorate(rng, canvas, rho, int(rng.integers(3, 7) * max(1.0, h * w / rho**2 / 3)))
    return canvas.astype(np.float32) / 255.0


def ceiling_texture(rng: np.random.Generator, photos: Sequence[Photo], h: int, w: int, rho: float) -> np.ndarray:
    """Light ceiling panels, each slightly different, with a faint material and a few fixtures."""
    base = random_color(rng, (0.0, 0.25), (0.7, 0.95))
    img = np.empty((h, w, 3), dtype=np.float32)
    img[:] = base
    faint = fill(rng, photos, h, w, rho, True, (0.003, 0.01))
    img = img * (0.8 + 0.4 * gray(faint)[..., None])
    p = int(max(4, rng.uniform(0.5, 1.0) * rho))
    for y in range(0, h, p):
        for x in range(0, w, p):
            img[y : y + p, x : x + p] *= np.float32(rng.uniform(0.9, 1.08))
    canvas = _to_u8(_grain(rng, np.clip(img, 0, 1), rho, 0.12))
    line = tuple(int(v * 255) for v in random_color(rng, (0.0, 0.3), (0.2, 0.6)))
    for y in range(0, h, p):
        cv2.line(canvas, (0, y), (w, y), line, max(1, int(0.01 * rho)), cv2.LINE_AA)
    for x in range(0, w, p):
        cv2.line(canvas, (x, 0), (x, h), line, max(1, int(0.01 * rho)), cv2.LINE_AA)
    decorate(rng, canvas, rho, int(rng.integers(3, 8) * max(1.0, h * w / rho**2 / 4)))
    return canvas.astype(np.float32) / 255.0


def object_texture(rng: np.random.Generator, photos: Sequence[Photo], h: int, w: int, rho: float) -> np.ndarray:
    """One face of an object: a recoloured photo crop, sometimes striped, labelled and marked."""
    img = fill(rng, photos, h, w, rho, None, (0.001, 0.004))
    img = _grain(rng, img, rho, rng.uniform(0.05, 0.2))
    if rng.random() < 0.35:
        period = max(2, int(rng.uniform(0.04, 0.2) * rho))
        c = random_color(rng, (0.2, 1.0), (0.2, 1.0))
        stripes = ((np.arange(h)[:, None] // period) % 2 == 0).astype(np.float32) * rng.uniform(0.3, 0.7)
        img = img * (1 - stripes[..., None]) + c * stripes[..., None]
    canvas = _to_u8(img)
    decorate(rng, canvas, rho, int(rng.integers(1, 5) * max(1.0, h * w / rho**2 / 0.5)))
    return canvas.astype(np.float32) / 255.0
