"""A PNG contact sheet of a synthetic recording: APS frames through it, a held-out frame beside the novel
view at its time (when the recording has novel views), and the events of a window before it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from edmcgs.atomic import atomic_output
from edmcgs.errors import RecordingError
from edmcgs.sensor.files.recording import Recording
from edmcgs.sensor.frames import Frames

EVENT_WINDOW_US = 20_000


def _grey(image: np.ndarray) -> Image.Image:
    return Image.fromarray(image[..., 0] if image.shape[-1] == 1 else image).convert("RGB")


def event_image(rec: Recording, t0_us: int, t1_us: int) -> Image.Image:
    """The events of [t0, t1): on dark grey, ON red and OFF blue, brighter where more fired."""
    ev = rec.events.time_slice(t0_us, t1_us)
    img = np.full((rec.height, rec.width, 3), 30, np.float64)
    for sign, colour in ((1, (255, 60, 40)), (-1, (60, 120, 255))):
        keep = ev.p == sign
        counts = np.zeros((rec.height, rec.width))
        np.add.at(counts, (ev.y[keep].astype(np.int64), ev.x[keep].astype(np.int64)), 1.0)
        alpha = np.clip(counts / 3.0, 0.0, 1.0)[..., None]
        img = img * (1 - alpha) + alpha * np.array(colour, np.float64)
    return Image.fromarray(img.astype(np.uint8))


def contact_sheet(rec: Recording, path: str | Path, *, columns: int = 4) -> Path:
    """Write the sheet to ``path`` (atomically): a row of ``columns`` frames spread over the recording,
    then a held-out frame, the novel view at its time and the events of the 20 ms before it."""
    frames = [f for f in (rec.anchors, rec.held_out) if f is not None and len(f)]
    t = np.concatenate([f.t_us for f in frames])
    images = np.concatenate([f.images for f in frames])[np.argsort(t)]
    t = np.sort(t)
    picks = np.linspace(0, len(t) - 1, columns).round().astype(int)
    top = [(_grey(images[i]), f"APS t = {(t[i] - t[0]) / 1e6:.2f} s") for i in picks]
    held = rec.held_out if rec.held_out is not None and len(rec.held_out) else Frames(t, images)
    i = len(held) // 2
    th = int(held.t_us[i])
    bottom = [(_grey(held.images[i]), f"held-out t = {(th - t[0]) / 1e6:.2f} s")]
    if rec.novel_views is not None and len(rec.novel_views):
        j = int(np.argmin(np.abs(rec.novel_views.t_us - th)))
        bottom.append((_grey(rec.novel_views.images[j]), "novel view, same time"))
    events = event_image(rec, th - EVENT_WINDOW_US, th)
    bottom.append((events, f"events, {EVENT_WINDOW_US // 1000} ms before"))
    scale = max(1, round(346 / rec.width))
    w, h, label = rec.width * scale, rec.height * scale, 14
    sheet = Image.new("RGB", (columns * w, 2 * (h + label)), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for row, panels in enumerate((top, bottom)):
        for col, (image, text) in enumerate(panels):
            x, y = col * w, row * (h + label)
            sheet.paste(image.resize((w, h), Image.NEAREST), (x, y + label))
            draw.text((x + 3, y + 1), text, fill=(0, 0, 0))
    path = Path(path)
    with atomic_output(path, RecordingError) as tmp:
        sheet.save(tmp, format="PNG")
    return path
