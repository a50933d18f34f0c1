"""Procedural textures (numpy + OpenCV drawing) for the simulated scenes.

Every generator takes a ``numpy.random.Generator`` and returns ``uint8 (h, w, 3)`` RGB arrays, so a scene is
reproducible from its seed. The patterns imitate printed packaging: colour fields, stripes, checks, gradients,
blobs, borders and rows of text, so that the faces of an object differ and a network can tell them apart.
"""

from __future__ import annotations

import colorsys

import cv2
import numpy as np

# MuJoCo stores the six faces of a cube texture in OpenGL cube-map order: +x, -x, +y, -y, +z, -z.
CUBE_FACES = ("+x", "-x", "+y", "-y", "+z", "-z")

_WORDS = (
    "QUEST", "ISLAND", "EMPIRE", "CASTLE", "ROVER", "HARBOR", "TOWER", "FOREST", "ORBIT", "DRAGON",
    "MARKET", "VOYAGE", "CIPHER", "SUMMIT", "GALAXY", "KINGDOM", "RIVER", "TRAIL", "PIXEL", "ATLAS",
)


def random_colour(rng: np.random.Generator, saturation=(0.4, 1.0), value=(0.35, 1.0)) -> np.ndarray:
    """A random RGB colour, ``float (3,)`` in [0, 255]: uniform hue, saturation and value in the ranges."""
    h = rng.uniform()
    s = rng.uniform(*saturation)
    v = rng.uniform(*value)
    return np.array(colorsys.hsv_to_rgb(h, s, v)) * 255.0


def _contrasting(rng: np.random.Generator, base: np.ndarray) -> np.ndarray:
    """A colour far from ``base`` in brightness, so printed marks stand out."""
    lum = base.mean()
    if lum > 128:
        return random_colour(rng, (0.3, 1.0), (0.05, 0.35))
    return random_colour(rng, (0.0, 0.5), (0.8, 1.0))


def _periodic_noise(rng: np.random.Generator, h: int, w: int, cells: int) -> np.ndarray:
    """Smooth noise in [0, 1] that tiles in both directions: a random grid upsampled with wrap-around."""
    grid = rng.uniform(size=(cells, cells)).astype(np.float32)
    big = np.tile(grid, (3, 3))
    up = cv2.resize(big, (3 * w, 3 * h), interpolation=cv2.INTER_CUBIC)
    return np.clip(up[h : 2 * h, w : 2 * w], 0.0, 1.0)


def stripes(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Bands of 2-4 colours at a random angle and period (periodic along the texture's edges)."""
    cols = np.stack([random_colour(rng) for _ in range(rng.integers(2, 5))])
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    # numpy integers (not python ints): they set the dtype of ``phase`` below.
    fx: int | np.integer
    fy: int | np.integer
    fx, fy = rng.integers(0, 6), rng.integers(0, 6)
    if fx == 0 and fy == 0:
        fx = 3
    phase = (fx * x / w + fy * y / h) * len(cols)
    idx = np.floor(phase).astype(int) % len(cols)
    return cols[idx].astype(np.uint8)


def checks(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A two-colour checkerboard with a random number of squares per side."""
    a, b = random_colour(rng), random_colour(rng)
    n = int(rng.integers(2, 9))
    y, x = np.mgrid[0:h, 0:w]
    mask = ((x * n // w) + (y * n // h)) % 2 == 0
    return np.where(mask[..., None], a, b).astype(np.uint8)


def gradient(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A linear blend between two colours along a random direction."""
    a, b = random_colour(rng), random_colour(rng)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    ang = rng.uniform(0, 2 * np.pi)
    s = np.cos(ang) * x / max(w - 1, 1) + np.sin(ang) * y / max(h - 1, 1)
    s = (s - s.min()) / max(float(np.ptp(s)), 1e-6)
    return (a * (1 - s[..., None]) + b * s[..., None]).astype(np.uint8)


def blobs(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Smooth colour noise thresholded into 2-3 colour regions, like a camouflage print."""
    cols = [random_colour(rng) for _ in range(3)]
    n = _periodic_noise(rng, h, w, int(rng.integers(3, 7)))
    img = np.empty((h, w, 3), np.float32)
    img[:] = cols[0]
    img[n > 0.45] = cols[1]
    img[n > 0.65] = cols[2]
    return img.astype(np.uint8)


def dots(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Polka dots on a flat ground, on a regular lattice (so the pattern tiles)."""
    ground, ink = random_colour(rng), random_colour(rng)
    img = np.empty((h, w, 3), np.uint8)
    img[:] = ground
    n = int(rng.integers(3, 8))
    r = max(1, int(min(h, w) / n * rng.uniform(0.15, 0.35)))
    for i in range(n):
        for j in range(n):
            off = 0.5 if i % 2 else 0.0
            cx = int((j + 0.5 + off) * w / n) % w
            cy = int((i + 0.5) * h / n)
            cv2.circle(img, (cx, cy), r, ink.tolist(), -1, cv2.LINE_AA)
    return img


PATTERNS = (stripes, checks, gradient, blobs, dots)


def pattern(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """One of the patterns above, chosen at random."""
    return PATTERNS[int(rng.integers(len(PATTERNS)))](rng, h, w)


def text_marks(
    img: np.ndarray, rng: np.random.Generator, box: tuple[int, int, int, int], colour=None
) -> None:
    """Draw rows of text-like marks (random words, or bars of letter width) inside ``box = (x0, y0, x1, y1)``.

    Draws in place on ``img`` (h, w, 3) uint8.
    """
    x0, y0, x1, y1 = box
    colour = _contrasting(rng, img[y0:y1, x0:x1].reshape(-1, 3).mean(0)) if colour is None else colour
    bh, bw = y1 - y0, x1 - x0
    if bh < 4 or bw < 8:
        return
    if rng.uniform() < 0.5:
        # Real letters: a word or two scaled to the box.
        text = " ".join(rng.choice(_WORDS, size=int(rng.integers(1, 3))))
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_DUPLEX, 1.0, 2)
        scale = min(bw / tw, bh / (th * 1.4))
        thick = max(1, int(round(2 * scale)))
        (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_DUPLEX, scale, thick)
        org = (x0 + (bw - tw) // 2, y0 + (bh + th) // 2)
        cv2.putText(img, text, org, cv2.FONT_HERSHEY_DUPLEX, scale, colour.tolist(), thick, cv2.LINE_AA)
        return
    # Lines of small blocks, the look of fine print at a distance.
    rows = int(rng.integers(2, 6))
    row_h = bh / rows
    for r in range(rows):
        y = int(y0 + r * row_h + 0.2 * row_h)
        yh = int(y0 + (r + 1) * row_h - 0.2 * row_h)
        x = x0
        end = x1 - (rng.uniform(0, 0.4) * bw if r == rows - 1 else 0)
        while x < end:
            ww = int(rng.integers(max(2, bw // 40), max(3, bw // 8)))
            cv2.rectangle(img, (x, y), (min(int(end), x + ww), max(y, yh)), colour.tolist(), -1)
            x += ww + max(1, bw // 50)


def printed_face(rng: np.random.Generator, h: int, w: int, kind: str) -> np.ndarray:
    """One face of a printed box, drawn at its physical aspect ratio (``h, w`` in texels).

    Args:
        kind: "lid" (title band, artwork and border), "bottom" (light ground, fine print, barcode) or
            "side" (pattern band with a title word).
    """
    if kind == "lid":
        img = pattern(rng, h, w)
        border = max(2, min(h, w) // 14)
        cv2.rectangle(img, (0, 0), (w - 1, h - 1), random_colour(rng).tolist(), border)
        # Title band across the upper part, artwork disc below it, fine print in a corner.
        band = (border, border, w - border, border + h // 4)
        img[band[1] : band[3], band[0] : band[2]] = random_colour(rng, (0.6, 1.0), (0.15, 0.5))
        text_marks(img, rng, (band[0] + w // 20, band[1] + 2, band[2] - w // 20, band[3] - 2))
        cx = int(w * rng.uniform(0.25, 0.75))
        cy = int(h * rng.uniform(0.55, 0.7))
        rad = int(min(h, w) * rng.uniform(0.12, 0.22))
        cv2.circle(img, (cx, cy), rad, random_colour(rng).tolist(), -1, cv2.LINE_AA)
        pts = rng.uniform([cx - 2 * rad, cy - rad], [cx + 2 * rad, cy + rad], size=(3, 2)).astype(np.int32)
        cv2.fillPoly(img, [pts], random_colour(rng).tolist(), cv2.LINE_AA)
        text_marks(img, rng, (w - w // 4, h - h // 6, w - border - 1, h - border - 1))
        return img
    if kind == "bottom":
        img = np.empty((h, w, 3), np.uint8)
        img[:] = random_colour(rng, (0.0, 0.25), (0.75, 1.0))
        for i in range(int(rng.integers(3, 6))):
            y0 = int(h * (0.08 + 0.16 * i))
            text_marks(img, rng, (w // 12, y0, int(w * rng.uniform(0.5, 0.9)), y0 + h // 9))
        # Barcode in the lower right corner.
        bx, by = int(w * 0.62), int(h * 0.7)
        x = bx
        while x < w - w // 14:
            bw = int(rng.integers(1, 4))
            if rng.uniform() < 0.6:
                cv2.rectangle(img, (x, by), (x + bw - 1, h - h // 12), (10, 10, 10), -1)
            x += bw
        return img
    if kind == "side":
        img = pattern(rng, h, w)
        stripe = random_colour(rng)
        s0 = int(h * rng.uniform(0.1, 0.3))
        img[s0 : h - s0] = stripe
        text_marks(img, rng, (w // 10, s0, w - w // 10, h - s0))
        return img
    raise ValueError(f"printed_face: unknown kind {kind!r} (expected 'lid', 'bottom' or 'side')")


def box_faces(rng: np.random.Generator, dims: tuple[float, float, float], res: int = 128) -> np.ndarray:
    """The six faces of a printed box as a MuJoCo cube texture, ``uint8 (6, res, res, 3)``.

    Each face is drawn at the aspect ratio it has on a box with full extents ``dims = (dx, dy, dz)`` (the +z
    face is the lid, -z the bottom, the others sides) and resized to the square texture MuJoCo stretches
    over it. Faces are in MuJoCo's cube order :data:`CUBE_FACES`.
    """
    dx, dy, dz = dims
    # (face, its two in-plane extents as (horizontal, vertical) in the texture, kind)
    spec = [
        ((dy, dz), "side"),  # +x
        ((dy, dz), "side"),  # -x
        ((dx, dz), "side"),  # +y
        ((dx, dz), "side"),  # -y
        ((dx, dy), "lid"),  # +z
        ((dx, dy), "bottom"),  # -z
    ]
    out = np.empty((6, res, res, 3), np.uint8)
    for i, ((eh, ev), kind) in enumerate(spec):
        # Draw with ~res texels along the longer extent and the true aspect, then stretch to a square.
        scale = 2 * res / max(eh, ev)
        w = max(8, int(round(eh * scale)))
        h = max(8, int(round(ev * scale)))
        face = printed_face(rng, h, w, kind)
        out[i] = cv2.resize(face, (res, res), interpolation=cv2.INTER_AREA)
    return out


def table_texture(rng: np.random.Generator, res: int = 256) -> np.ndarray:
    """A tileable table top, ``(res, res, 3)``: wood grain, cloth check, speckled laminate or blotchy mat."""
    kind = int(rng.integers(4))
    y, x = np.mgrid[0:res, 0:res].astype(np.float32) / res
    a = random_colour(rng, (0.1, 0.6), (0.3, 0.9))
    b = random_colour(rng, (0.1, 0.6), (0.3, 0.9))
    if kind == 0:  # wood: wavy periodic grain along x
        warp = _periodic_noise(rng, res, res, 4)
        s = 0.5 + 0.5 * np.sin(2 * np.pi * (int(rng.integers(6, 16)) * y + 1.5 * warp))
        img = a * s[..., None] + (0.6 * a) * (1 - s[..., None])
    elif kind == 1:  # gingham-like cloth check
        n = int(rng.integers(4, 12))
        sx = (np.floor(x * n) % 2)[..., None]
        sy = (np.floor(y * n) % 2)[..., None]
        img = 255 - (255 - a) * (0.2 + 0.4 * sx + 0.4 * sy)
    elif kind == 2:  # speckled laminate
        speckle = _periodic_noise(rng, res, res, 32)
        img = a * (0.8 + 0.4 * speckle[..., None])
    else:  # blotchy mat
        blotch = _periodic_noise(rng, res, res, 6)[..., None]
        img = a * blotch + b * (1 - blotch)
    noise = rng.normal(0, 6, size=(res, res, 1))
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def wrap_texture(rng: np.random.Generator, h: int = 128, w: int = 256) -> np.ndarray:
    """A label that wraps around a round object (periodic in u): pattern, band and a printed word."""
    img = pattern(rng, h, w)
    if rng.uniform() < 0.7:
        b0 = int(h * rng.uniform(0.3, 0.5))
        b1 = b0 + int(h * rng.uniform(0.15, 0.3))
        img[b0:b1] = random_colour(rng)
        # Text on one side only, so the print also tells front from back.
        x0 = int(w * rng.uniform(0.05, 0.3))
        text_marks(img, rng, (x0, b0 + 1, x0 + w // 3, b1 - 1))
    return img


def cup_texture(rng: np.random.Generator, h: int = 128, w: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Texture for :func:`s3k.sim.meshes.cup_profile`: rows with v < 0.25 hold the plain inside colour, the
    rest the outside print (flipped so that it reads upright: texture row 0 is v = 0, the bottom).

    Returns:
        ``(texture (h, w, 3) uint8, inside_colour (3,) float)``.
    """
    inside = random_colour(rng, (0.0, 0.3), (0.7, 1.0)) if rng.uniform() < 0.6 else random_colour(rng)
    q = h // 4
    img = np.empty((h, w, 3), np.uint8)
    img[:q] = inside
    img[q:] = wrap_texture(rng, h - q, w)[::-1]
    return img, inside
