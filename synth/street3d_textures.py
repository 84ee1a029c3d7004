"""The procedural textures of ``street3d``: asphalt with lane markings, paving slabs, curbs, facades with
windows and shop fronts, street furniture, car paint and glass.

Grey luminance in about [0.03, 0.9], drawn band-limited at the texel size (``synth.procedural``: noise
octaves finer than two texels left out, every edge a one-texel ramp, patterns too fine for the texel
faded to their mean), at power-of-two sizes (the ray caster's mip maps and repeats). The tiling
textures (road, pavement, curb, walls, metal) use periodic noise, so their repeats have no seams.
``res`` multiplies every texel size (2 at half the DAVIS346 resolution), so both sizes show one street.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from edmcgs.synth.procedural import band, box_sd, fbm, hash01, ramp

ROAD_TILE = 10.24
"""Metres of road texture along and across the street (the road is 9 m wide)."""
ROAD_MARKINGS = {"parking": 1.5, "centre": 4.5, "edge": 8.3}
FACADE_HEIGHT = 20.48
"""Metres of a facade texture from the roof line down: no building is taller."""
"""Lines across the road texture's v (metres from the road's north edge)."""


def _grid(width: int, height: int, texel: float) -> tuple[np.ndarray, np.ndarray]:
    """Metres (u right, v down) of every texel centre, [height, width] each."""
    u = (np.arange(width) + 0.5) * texel
    v = (np.arange(height) + 0.5) * texel
    return np.meshgrid(u, v)


def _cells(u, v, size: float, count: int | None = None):
    """Cell indices of a ``size`` grid (taken modulo ``count`` to repeat with the texture) and the
    offsets from the cell centres."""
    iu, iv = np.floor(u / size), np.floor(v / size)
    du, dv = u - (iu + 0.5) * size, v - (iv + 0.5) * size
    if count is not None:
        iu, iv = iu % count, iv % count
    return iu, iv, du, dv


def _fade(pattern: np.ndarray, period: float, px: float) -> np.ndarray:
    """A pattern of ``period`` shown only where the texel resolves it (>= 3 texels a period), else its
    mean: a pattern finer than the texture would alias in it."""
    keep = float(np.clip((period / px - 3.0) / 2.0, 0.0, 1.0))
    return keep * pattern + (1.0 - keep) * float(pattern.mean())


def _clip(img: np.ndarray) -> np.ndarray:
    return np.clip(img, 0.03, 0.9)


# ------------------------------------------------------------------------------------------- ground

def road(key: int, res: int) -> tuple[np.ndarray, float]:
    """Asphalt (grain, stones, repair patches, sealed cracks, a manhole) with a dashed centre line, an
    edge line and a parking strip with bays; 10.24 m square, 2 cm texels."""
    texel, n = 0.02 * res, 512 // res
    u, v = _grid(n, n, texel)
    px, p = texel, ROAD_TILE
    lo = fbm(u, v, (2.56, 1.28, 0.64), key, px, p)
    hi = fbm(u, v, (0.16, 0.08, 0.04), key + 1, px, p)
    grain = hash01(np.floor(u / texel), np.floor(v / texel), key + 2) - 0.5
    patch = np.clip(4.0 * (fbm(u, v, (2.56, 1.28), key + 3, px, p) - 0.3), 0.0, 1.0)
    crack = np.clip(1.0 - np.abs(fbm(u, v, (1.28, 0.64, 0.32), key + 4, px, p)) / 0.02, 0.0, 1.0) ** 2
    asphalt = 0.2 * (1 + 0.12 * lo + 0.15 * hi + 0.25 * grain) * (1 - 0.22 * patch) * (1 - 0.45 * crack)
    asphalt *= 1 - 0.2 * (band(v, 0.0, 0.25, px) + band(v, 8.75, 9.0, px))  # gutters
    d = np.hypot(u - 7.5, v - 6.8)  # a manhole cover
    cover = 0.27 + 0.05 * np.sin(40 * u) * np.sin(40 * v)
    asphalt += ramp(d - 0.3, px) * (cover - asphalt)
    asphalt *= 1 - 0.6 * ramp(np.abs(d - 0.3) - 0.015, px)
    paint = 0.62 * (0.85 + 0.15 * fbm(u, v, (0.32, 0.16, 0.08), key + 5, px, p))
    dash = ramp(np.abs(u % 5.12 - 2.56) - 1.5, px)  # 3 m dashes, 2.12 m gaps

    def line(v0, half):
        return ramp(np.abs(v - v0) - half, px)

    bays = ramp(np.abs((u + 2.56) % 5.12 - 2.56) - 0.05, px) * band(v, 0.0, ROAD_MARKINGS["parking"], px)
    marks = np.maximum.reduce([line(ROAD_MARKINGS["centre"], 0.06) * dash, line(ROAD_MARKINGS["edge"], 0.06),
                               line(ROAD_MARKINGS["parking"], 0.05), bays])
    return _clip(asphalt + marks * (paint - asphalt)), texel


def pavement(key: int, res: int) -> tuple[np.ndarray, float]:
    """Paving slabs of 64 cm (their own tones, joints, grain, stains, chewing gum); 5.12 m, 1 cm texels."""
    texel, n = 0.01 * res, 512 // res
    u, v = _grid(n, n, texel)
    px, p = texel, 5.12
    iu, iv, du, dv = _cells(u, v, 0.64, 8)
    tone = 0.36 + 0.1 * hash01(iu, iv, key)
    joint = ramp(np.minimum(0.32 - np.abs(du), 0.32 - np.abs(dv)) - 0.005, px)
    grain = fbm(u, v, (0.16, 0.08, 0.04, 0.02), key + 1, px, p)
    stains = fbm(u, v, (1.28, 0.64), key + 2, px, p)
    cu, cv, gu, gv = _cells(u, v, 0.16, 32)
    h = hash01(cu, cv, key + 3)
    gum = (h > 0.9) * ramp(np.hypot(gu - 0.05 * (h - 0.95), gv) - (0.008 + 0.1 * (h - 0.9)), px)
    return _clip(tone * (1 + 0.12 * grain + 0.1 * stains) * (1 - 0.45 * joint) * (1 - 0.55 * gum)), texel


def curb(key: int, res: int) -> tuple[np.ndarray, float]:
    """Granite curb stones of 1.28 m, their worn top edge brighter; 2.56 x 0.16 m, 1 cm texels."""
    texel = 0.01 * res
    u, v = _grid(256 // res, 16 // res, texel)
    iu, _, du, _ = _cells(u, v, 1.28, 2)
    tone = 0.48 + 0.06 * hash01(iu, 0, key)
    grain = fbm(u, v, (0.08, 0.04, 0.02), key + 1, texel, 2.56)
    img = tone * (1 + 0.12 * grain) * (1 - 0.5 * ramp(0.64 - np.abs(du) - 0.004, texel))
    return _clip(img + band(v, 0.0, 0.025, texel) * 0.1), texel


def soil(key: int, res: int) -> tuple[np.ndarray, float]:
    """Dark soil with pebbles (the top of a planter); 1.28 m, 1 cm texels."""
    texel = 0.01 * res
    u, v = _grid(128 // res, 128 // res, texel)
    img = 0.12 * (1 + 0.3 * fbm(u, v, (0.32, 0.08, 0.04, 0.02), key, texel, 1.28))
    cu, cv, gu, gv = _cells(u, v, 0.08, 16)
    h = hash01(cu, cv, key + 1)
    pebble = (h > 0.7) * ramp(np.hypot(gu, gv) - 0.012 - 0.02 * (h - 0.7), texel)
    return _clip(img + pebble * 0.25), texel


# ------------------------------------------------------------------------------------------- buildings

def wall(key: int, res: int) -> tuple[np.ndarray, float]:
    """Plain plaster (a building's side wall): stains and grime; 10.24 m, 4 cm texels."""
    texel, n = 0.04 * res, 256 // res
    u, v = _grid(n, n, texel)
    lo = fbm(u, v, (2.56, 1.28, 0.64), key, texel, 10.24)
    hi = fbm(u, v, (0.32, 0.16, 0.08), key + 1, texel, 10.24)
    return _clip(0.44 * (1 + 0.12 * lo + 0.05 * hi)), texel


@dataclass(frozen=True)
class Facade:
    """One building front: its size (metres), storeys and bays, wall material and tones."""

    width: float
    height: float
    ground: float
    """Height of the ground floor (shops)."""
    storey: float
    """Height of each upper storey."""
    bays: int
    """Windows per storey, evenly spaced."""
    material: str
    """"brick", "plaster" or "stone"."""
    tone: float
    frame: float
    """Luminance of the window frames."""
    sign: float
    """Luminance of the shop sign's background (its letters the opposite)."""
    key: int

    @classmethod
    def draw(cls, rng: np.random.Generator, width: float, key: int) -> Facade:
        """A random building front ``width`` metres wide."""
        storey = float(rng.uniform(2.9, 3.4))
        ground = float(rng.uniform(3.6, 4.4))
        floors = min(int(rng.integers(2, 6)), int((FACADE_HEIGHT - 0.6 - ground) / storey))
        material = str(rng.choice(["brick", "plaster", "stone"]))
        tone = float({"brick": rng.uniform(0.28, 0.4), "plaster": rng.uniform(0.42, 0.62),
                      "stone": rng.uniform(0.38, 0.52)}[material])
        return cls(width=width, height=ground + floors * storey + 0.6, ground=ground, storey=storey,
                   bays=max(2, int(width / rng.uniform(1.8, 2.4))), material=material, tone=tone,
                   frame=float(rng.choice([0.7, 0.14])), sign=float(rng.choice([0.8, 0.12, 0.5])), key=key)


def facade(f: Facade, res: int) -> tuple[np.ndarray, float]:
    """A building front: material, cornices, windows (dark glass, curtains, blinds or lit) with frames,
    sills and mullions, a ground floor of shop windows, doors and a lettered sign. v runs down from
    the roof line; 10.24 x 20.48 m, 4 cm texels."""
    texel = 0.04 * res
    u, v = _grid(256 // res, 512 // res, texel)
    px, key = texel, f.key
    z = f.height - v  # height above the pavement
    lo = fbm(u, v, (2.56, 1.28, 0.64), key, px)
    hi = fbm(u, v, (0.32, 0.16, 0.08), key + 1, px)
    if f.material == "brick":
        row = np.floor(z / 0.075)
        shifted = u + 0.12 * (row % 2)  # running bond
        joints = ramp(np.abs(shifted - 0.24 * np.round(shifted / 0.24)) - 0.005, px)
        wall_lum = f.tone * (0.85 + 0.3 * hash01(np.floor(shifted / 0.24), row, key + 2))
        wall_lum += _fade(joints, 0.24, px) * 0.35 * f.tone
    elif f.material == "stone":
        iu, iv = np.floor(u / 1.2), np.floor(z / 0.6)
        du, dv = u - (iu + 0.5) * 1.2, z - (iv + 0.5) * 0.6
        joints = ramp(np.minimum(0.6 - np.abs(du), 0.3 - np.abs(dv)) - 0.006, px)
        wall_lum = f.tone * (0.9 + 0.2 * hash01(iu, iv, key + 2)) * (1 - 0.4 * joints)
    else:
        wall_lum = f.tone * np.ones_like(u)
        for k in range(1, 8):  # a cornice at each storey line
            zk = f.ground + k * f.storey
            if zk < f.height - 0.6:
                wall_lum = wall_lum * (1 + 0.15 * band(z, zk - 0.08, zk + 0.1, px)
                                       - 0.3 * band(z, zk - 0.16, zk - 0.08, px))
    wall_lum = wall_lum * (1 + 0.12 * lo + 0.05 * hi) * (1 - 0.15 * np.clip(1 - z / 3.0, 0, 1))
    img = wall_lum
    # roof cornice
    img = img + band(z, f.height - 0.35, f.height + 1.0, px) * (1.2 * f.tone - img)
    img = img * (1 - 0.35 * band(z, f.height - 0.45, f.height - 0.35, px))
    # windows of the upper storeys
    floors = round((f.height - 0.6 - f.ground) / f.storey)
    bay = f.width / f.bays
    j = np.clip(np.floor(u / bay), 0, f.bays - 1)
    i = np.floor((z - f.ground) / f.storey)
    upper = (i >= 0) & (i < floors) & (u < f.width)
    ww, wh = 0.5 * min(1.3, 0.55 * bay), 0.8
    du = u - (j + 0.5) * bay
    dz = z - (f.ground + i * f.storey + 0.9 + wh)
    frame = ramp(box_sd(du, dz, ww, wh), px) * upper
    glass_cov = ramp(box_sd(du, dz, ww - 0.07, wh - 0.07), px) * upper
    state = hash01(j, i, key + 3)
    shade = hash01(j, i, key + 4)
    reflect = 0.07 + 0.1 * (dz / wh + 1) * 0.5 + 0.05 * shade + 0.03 * lo
    curtains = 0.42 + 0.1 * shade + _fade(0.06 * np.sin(2 * np.pi * du / 0.16), 0.16, px)
    blinds = 0.45 + 0.1 * shade + _fade(0.08 * np.sin(2 * np.pi * dz / 0.2), 0.2, px)
    glass = np.where(state < 0.55, reflect,
                     np.where(state < 0.75, curtains, np.where(state < 0.9, blinds, 0.7)))
    glass = glass * (1 - 0.4 * band(dz, wh - 0.2, wh, px))  # the reveal's shadow under the lintel
    mullion = ramp(np.abs(du) - 0.025, px) * (ww > 0.5) + ramp(np.abs(dz - 0.35 * wh) - 0.025, px)
    glass = glass + np.clip(mullion, 0, 1) * (f.frame - glass)
    sill = band(dz, -wh - 0.08, -wh + 0.01, px) * ramp(np.abs(du) - ww - 0.06, px) * upper
    img = img + frame * (f.frame - img)
    img = img + glass_cov * (glass - img)
    img = img + sill * (0.65 - img)
    # the ground floor: shop units of a window, a door and a sign
    units = max(1, int(f.width / 4.5))
    unit = f.width / units
    k = np.clip(np.floor(u / unit), 0, units - 1)
    cu = u - (k + 0.5) * unit
    ground = (z < f.ground) & (u < f.width)
    door_at = (hash01(k, 0, key + 5) - 0.5) * (unit - 2.0)
    door = ramp(box_sd(cu - door_at, z - 1.1, 0.5, 1.1), px) * ground
    half_height = (f.ground - 1.5) / 2 - 0.25  # shop windows from 0.5 m to 1.0 m under the ground floor's top
    shop = ramp(box_sd(cu, z - 0.5 - half_height, 0.5 * unit - 0.3, half_height), px)
    shop = shop * ground * (1 - door)
    stuff = np.clip(2.5 * fbm(u, z, (0.64, 0.32, 0.16), key + 6, px), -1, 1)
    shop_lum = 0.1 + 0.08 * stuff + 0.06 * np.clip(1 - np.abs((cu + z) % 1.5 - 0.75) / 0.1, 0, 1)
    sign = ramp(box_sd(cu, z - (f.ground - 0.55), 0.5 * unit - 0.35, 0.3), px) * ground
    letters = _letters(cu, z - (f.ground - 0.55), 0.5 * unit - 0.7, key + 7, px, k)
    sign_lum = f.sign + letters * (0.9 - f.sign if f.sign < 0.5 else 0.1 - f.sign)
    plinth = band(z, -1.0, 0.45, px) * (u < f.width)
    img = img + plinth * (0.6 * f.tone - img)
    img = img + shop * (shop_lum - img)
    img = img + door * (0.1 + 0.05 * ramp(np.abs(cu - door_at) - 0.45, px) - img)
    img = img + sign * (sign_lum - img)
    return _clip(img), texel


def _letters(x, y, half_width, key, px, line=0):
    """Coverage of a line of block letters centred at (0, 0), 0.3 m tall, over |x| < half_width;
    ``line`` (an index, or an array of them) picks other letters."""
    cell = 0.22
    i = np.floor(x / cell)
    lx, ly = x - (i + 0.5) * cell, y
    i = i + 4096 * np.asarray(line)
    h = hash01(i, 0, key)
    stroke = 0.035
    letter = np.maximum.reduce([
        ramp(box_sd(lx + 0.06, ly, stroke, 0.13), px),
        ramp(box_sd(lx, ly - 0.1 * np.sign(h - 0.5), 0.07, stroke), px) * (h > 0.25),
        ramp(box_sd(lx - 0.06, ly, stroke, 0.13), px) * (h > 0.5),
        ramp(box_sd(lx, ly + 0.1, 0.07, stroke), px) * (h < 0.7)])
    return letter * (np.abs(x) < half_width) * (hash01(i, 1, key) > 0.15)


# ------------------------------------------------------------------------------------------- furniture

def metal(key: int, res: int) -> tuple[np.ndarray, float]:
    """Painted metal, brushed vertically, a seam every 1.28 m; 2 cm texels."""
    texel, n = 0.02 * res, 64 // res
    u, v = _grid(n, n, texel)
    img = 0.36 * (1 + 0.08 * fbm(u, v, (0.32, 0.08, 0.04), key, texel, 1.28))
    return _clip(img * (1 - 0.4 * band(v, 0.0, 0.03, texel))), texel


def bollard(key: int, res: int) -> tuple[np.ndarray, float]:
    """A dark bollard with a white reflective band near its top; 2 cm texels."""
    texel, n = 0.02 * res, 64 // res
    u, v = _grid(n, n, texel)
    img = 0.16 * (1 + 0.1 * fbm(u, v, (0.32, 0.08, 0.04), key, texel, 1.28))
    return _clip(img + band(v, 0.1, 0.2, texel) * (0.78 - img)), texel


def bin_texture(key: int, res: int) -> tuple[np.ndarray, float]:
    """A litter bin: dark ribs every 16 cm, a lighter lid band; 2 cm texels."""
    texel, n = 0.02 * res, 64 // res
    u, v = _grid(n, n, texel)
    img = 0.15 * (1 + 0.25 * np.cos(2 * np.pi * u / 0.16) + 0.1 * fbm(u, v, (0.32, 0.08), key, texel, 1.28))
    return _clip(img + band(v, 0.0, 0.08, texel) * (0.32 - img)), texel


def cabinet(key: int, res: int) -> tuple[np.ndarray, float]:
    """A grey street cabinet with stickers and scrawls; 1.28 m, 1 cm texels."""
    texel, n = 0.01 * res, 128 // res
    u, v = _grid(n, n, texel)
    img = 0.52 * (1 + 0.08 * fbm(u, v, (0.32, 0.16, 0.04), key, texel, 1.28))
    scrawl = np.clip(1 - np.abs(fbm(u, v, (0.32, 0.16), key + 1, texel, 1.28)) / 0.03, 0, 1)
    img *= 1 - 0.6 * scrawl * (fbm(u, v, (0.64,), key + 2, texel, 1.28) > 0.1)
    for s in range(5):
        h = hash01(np.arange(5), s, key + 3)
        at_u, at_v = u - 0.2 - 0.9 * h[0], v - 0.2 - 0.9 * h[1]
        sticker = ramp(box_sd(at_u, at_v, 0.04 + 0.08 * h[2], 0.03 + 0.06 * h[3]), texel)
        img = img + sticker * (0.1 + 0.8 * h[4] - img)
    return _clip(img), texel


def poster(key: int, res: int) -> tuple[np.ndarray, float]:
    """An advertising poster: a frame, a gradient, a big disc, bold bars, lettering and a blotchy
    'photograph'; 1.6 x 3.2 m, 1.25 cm texels."""
    texel = 0.0125 * res
    u, v = _grid(128 // res, 256 // res, texel)
    img = 0.3 + 0.35 * v / 3.2
    img = img + ramp(np.hypot(u - 0.9, v - 0.9) - 0.45, texel) * (0.85 - img)
    for k in range(3):
        img = img + ramp(box_sd(u - 0.8, v - 1.55 - 0.16 * k, 0.6 - 0.15 * k, 0.045), texel) * (0.08 - img)
    photo = np.clip(0.45 + 0.5 * fbm(u, v, (0.32, 0.16, 0.08, 0.04), key, texel), 0.05, 0.9)
    img = img + ramp(box_sd(u - 0.8, v - 2.35, 0.6, 0.35), texel) * (photo - img)
    img = img + _letters(u - 0.8, v - 2.9, 0.6, key + 1, texel) * (0.9 - img)
    frame = 1 - ramp(box_sd(u - 0.8, v - 1.6, 0.75, 1.55), texel)
    return _clip(img + frame * (0.2 - img)), texel


def concrete(key: int, res: int) -> tuple[np.ndarray, float]:
    """Cast concrete with pores and a lighter lip on top (planters); 1.6 x 0.8 m, 1.25 cm texels."""
    texel = 0.0125 * res
    u, v = _grid(128 // res, 64 // res, texel)
    img = 0.5 * (1 + 0.1 * fbm(u, v, (0.4, 0.2, 0.1, 0.05), key, texel, 1.6))
    cu, cv, gu, gv = _cells(u, v, 0.05, 32)
    pores = (hash01(cu, cv, key + 1) > 0.8) * ramp(np.hypot(gu, gv) - 0.008, texel)
    return _clip(img * (1 - 0.4 * pores) + band(v, 0.0, 0.05, texel) * 0.08), texel


# ------------------------------------------------------------------------------------------- cars

@dataclass(frozen=True)
class CarModel:
    """A car's shape: a body box and a narrower cabin box on it (metres)."""

    length: float
    width: float
    body: float
    """Height of the body (bonnet and boot)."""
    cabin: float
    """Height of the cabin above the body."""
    cabin_length: float
    cabin_shift: float
    """The cabin's centre behind the body's, metres."""


CAR_MODELS = (CarModel(3.9, 1.75, 0.85, 0.55, 2.1, 0.35), CarModel(4.5, 1.8, 0.8, 0.55, 2.3, 0.2),
              CarModel(4.7, 1.82, 0.82, 0.58, 2.8, 0.45), CarModel(4.9, 1.9, 1.0, 0.9, 3.2, 0.55))
"""Hatchback, saloon, estate, van."""


def car_textures(m: CarModel, key: int, res: int) -> dict[str, tuple[np.ndarray, float]]:
    """The faces of a white car of model ``m`` (the renderer's shade tints it): body side (wheels,
    arches, seams, handles), front (lights, grille, plate), rear, top (paint), cabin side (windows),
    windscreen and rear window."""
    out = {}
    # body side: u along the car, v down from the body's top
    t = m.length / (256 // res)
    u, v = _grid(256 // res, 64 // res, t)
    z = m.body - v
    img = 0.9 - 0.15 * v / m.body
    img *= 1 - 0.5 * ramp(np.abs(z - (m.body - 0.2)) - 0.006, t)
    for s in (0.36, 0.62):
        img *= 1 - 0.6 * ramp(np.abs(u - s * m.length) - 0.006, t) * (z > 0.25)
        img = img + ramp(box_sd(u - s * m.length - 0.2, z - (m.body - 0.3), 0.08, 0.02), t) * (0.3 - img)
    img = img + band(z, -1.0, 0.22, t) * (0.25 - img)
    for w in (0.8, m.length - 0.85):
        r = np.hypot(u - w, z - 0.32)
        img = img + ramp(r - 0.42, t) * (0.1 - img)
        img = img + ramp(r - 0.32, t) * (0.05 - img)
        img = img + ramp(r - 0.19, t) * (0.5 - 0.25 * ramp(np.abs(r - 0.12) - 0.015, t) - img)
    out["side"] = (_clip(img), t)
    # front and rear: u across the car, v down from the body's top
    t = m.width / (128 // res)
    u, v = _grid(128 // res, 64 // res, t)
    z, cu = m.body - v, u - 0.5 * m.width
    base = 0.88 - 0.1 * v / m.body
    bumper = band(z, 0.18, 0.42, t)
    plate = ramp(box_sd(cu, z - 0.34, 0.26, 0.06), t)
    chars = _letters(cu / 0.35, (z - 0.34) / 0.35, 0.6, key, t / 0.35)
    front = base + bumper * (0.3 - base)
    grille = 0.08 + 0.05 * np.cos(2 * np.pi * z / 0.04)
    front = front + ramp(box_sd(cu, z - 0.55, 0.4, 0.08), t) * (grille - front)
    for side in (-1, 1):
        lamp = ramp(np.hypot((cu - side * (0.5 * m.width - 0.3)) / 2.2, z - 0.62) - 0.07, t)
        front = front + lamp * (0.88 - front)
    front = front + plate * (0.85 - 0.7 * chars - front)
    out["front"] = (_clip(front), t)
    rear = base + bumper * (0.3 - base)
    for side in (-1, 1):
        lamp = ramp(box_sd(cu - side * (0.5 * m.width - 0.18), z - 0.65, 0.12, 0.07), t)
        rear = rear + lamp * (0.22 - rear)
    rear = rear + plate * (0.85 - 0.7 * chars - rear)
    out["rear"] = (_clip(rear), t)
    # top: paint, the light off it
    t = m.length / (256 // res)
    u, v = _grid(256 // res, 128 // res, t)
    out["top"] = (_clip(0.92 + 0.04 * fbm(u, v, (1.28, 0.64), key + 1, t)), t)
    # cabin side: two windows and a B pillar, slanted ends
    t = m.cabin_length / (256 // res)
    u, v = _grid(256 // res, 64 // res, t)
    z = m.cabin - v
    slant = 0.45 * m.cabin
    inside = np.maximum.reduce([0.06 - z, z - (m.cabin - 0.07), (0.12 + slant * z / m.cabin) - u,
                                u - (m.cabin_length - 0.12 - slant * z / m.cabin * 0.7)])
    pillar = ramp(np.abs(u - 0.52 * m.cabin_length) - 0.05, t)
    glass = ramp(inside, t) * (1 - pillar)
    img = 0.88 + glass * (0.09 + 0.1 * z / m.cabin - 0.88)
    out["cabin_side"] = (_clip(img), t)
    # windscreen and rear window: glass within a border
    t = m.width / (128 // res)
    u, v = _grid(128 // res, 64 // res, t)
    z, cu = m.cabin - v, u - 0.5 * m.width
    screen = ramp(np.maximum(np.abs(cu) - (0.5 * m.width - 0.1 - 0.08 * z / m.cabin),
                             np.abs(z - 0.5 * m.cabin) - (0.5 * m.cabin - 0.07)), t)
    out["glass"] = (_clip(0.88 + screen * (0.07 + 0.12 * z / m.cabin - 0.88)), t)
    return out
