"""Full-resolution figures people can read: side-by-side panels with titles, a depth colour bar in metres
and a semantic class legend.

A figure is one row of equally sized panels (each at the resolution of the input image, never shrunk),
each under a title bar, followed on the right by a key column: the depth colour bar (turbo, ticks in
metres, the same ``[0, depth_max]`` range as every depth panel of the row) above the class legend (a
swatch and the name of every class that appears in a semantic panel). Text is drawn with OpenCV's
Hershey font scaled with the panel height, so a 256-px and a 1024-px panorama read alike.

All images are float ``(3, H, W)`` RGB tensors in ``[0, 1]`` (write them with :func:`to_uint8_bgr` +
``omnidl.utils.io.atomic_imwrite``).
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from omnidl.classes import CLASS_NAMES

from .colormap import depth_to_color, overlay, palette, semantic_to_color

#: a panel: (title, image (3, H, W) | (1, H, W) | (H, W) in [0, 1])
Panel = tuple[str, Tensor]


def _scale(h: int) -> float:
    """Font scale for a panel ``h`` pixels high (0.45 at 128 px, 1.0 at 512 px, capped at 2)."""
    return float(min(2.0, max(0.45, h / 512)))


def _text_canvas(h: int, w: int, value: float = 1.0) -> np.ndarray:
    return np.full((h, w, 3), int(round(value * 255)), np.uint8)


def _put(canvas: np.ndarray, text: str, x: int, y: int, scale: float, color=(0, 0, 0)) -> None:
    import cv2
    cv2.putText(canvas, text, (int(x), int(y)), cv2.FONT_HERSHEY_SIMPLEX, scale, color,
                max(1, int(round(scale * 1.6))), cv2.LINE_AA)


def _text_size(text: str, scale: float) -> tuple[int, int]:
    import cv2
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, int(round(scale * 1.6))))
    return w, h + base


def _as_rgb(img: Tensor) -> Tensor:
    img = img.detach().float().cpu()
    if img.dim() == 2:
        img = img[None]
    if img.shape[0] == 1:
        img = img.expand(3, -1, -1)
    if img.dim() != 3 or img.shape[0] != 3:
        raise ValueError(f"a panel must be (3, H, W), (1, H, W) or (H, W), got {tuple(img.shape)}")
    return img.clamp(0, 1)


def title_height(h: int) -> int:
    """Height in pixels of the title bar above a panel ``h`` pixels high."""
    return int(math.ceil(_text_size("Ag", _scale(h))[1] * 1.6)) + 4


def titled_row(panels: Sequence[Panel], pad: int = 4, key: Tensor | None = None) -> Tensor:
    """Panels side by side at full resolution, each under its title; ``key`` (e.g. :func:`figure_key`)
    is appended on the right, top-aligned.

    Every panel is resized (nearest) to the size of the first one (normally they already share it).
    Returns ``(3, title_height + H, n * (W + pad) - pad [+ pad + key width])`` in ``[0, 1]``.
    """
    if not panels:
        raise ValueError("titled_row needs at least one panel")
    first = _as_rgb(panels[0][1])
    h, w = first.shape[-2:]
    th = title_height(h)
    s = _scale(h)
    width = len(panels) * (w + pad) - pad + (pad + key.shape[-1] if key is not None else 0)
    height = max(th + h, key.shape[-2] if key is not None else 0)
    canvas = _text_canvas(height, width)
    for j, (title, img) in enumerate(panels):
        x0 = j * (w + pad)
        img = _as_rgb(img)
        if img.shape[-2:] != (h, w):
            img = torch.nn.functional.interpolate(img[None], size=(h, w), mode="nearest")[0]
        canvas[th:th + h, x0:x0 + w] = (img.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        text = str(title)
        while len(text) > 3 and _text_size(text, s)[0] > w - 8:
            text = text[:-4] + "..."
        tw, _ = _text_size(text, s)
        _put(canvas, text, x0 + max(4, (w - tw) // 2), int(th * 0.7), s)
    if key is not None:
        k = (_as_rgb(key).permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        canvas[:k.shape[0], width - k.shape[1]:] = k
    return torch.from_numpy(canvas).permute(2, 0, 1).float() / 255


def nice_ticks(vmin: float, vmax: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values in ``[vmin, vmax]`` (steps of 1, 2 or 5 x 10^k)."""
    span = max(vmax - vmin, 1e-9)
    raw = span / max(n - 1, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 5, 10) if m * mag >= raw)
    first = math.ceil(vmin / step - 1e-9) * step
    return [round(first + i * step, 10) for i in range(int(math.floor((vmax - first) / step + 1e-9)) + 1)]


def depth_colorbar(height: int, vmax: float, vmin: float = 0.0, label: str = "depth (m)") -> Tensor:
    """A vertical turbo colour bar for depths ``[vmin, vmax]`` metres (far at the top), with ticks in
    metres and ``label`` above it: ``(3, h, w)`` in [0, 1], ``w`` fitted to the text, ``h = height`` unless
    that is too short to read (tiny panels)."""
    s = _scale(height) * 0.85
    th = title_height(height)
    height = max(height, th + 4 * _text_size("0", s)[1] + 8)       # room for a readable bar on tiny panels
    bar_w = max(12, int(round(24 * s)))
    ticks = nice_ticks(vmin, vmax)
    tick_txt = [f"{t:g}" for t in ticks]
    tw = max(_text_size(t, s)[0] for t in tick_txt)
    w = max(bar_w + 12 + tw + 6, _text_size(label, s)[0] + 8)
    canvas = _text_canvas(height, w)
    _put(canvas, label, 4, int(th * 0.7), s)
    top, bottom = th + _text_size("0", s)[1] // 2 + 2, height - _text_size("0", s)[1] // 2 - 4
    n = max(bottom - top, 2)
    vals = torch.linspace(vmax, vmin, n)[:, None].expand(n, bar_w)
    col = depth_to_color(vals.clamp_min(1e-6) if vmin <= 0 else vals, vmax=vmax, vmin=vmin)
    canvas[top:top + n, 4:4 + bar_w] = (col.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    for t, txt in zip(ticks, tick_txt):
        y = top + int(round((vmax - t) / max(vmax - vmin, 1e-9) * (n - 1)))
        canvas[y, 4 + bar_w:4 + bar_w + 6] = 0
        _put(canvas, txt, 4 + bar_w + 9, y + _text_size(txt, s)[1] // 3, s)
    return torch.from_numpy(canvas).permute(2, 0, 1).float() / 255


def class_legend(class_ids: Sequence[int], height: int, names: Sequence[str] = CLASS_NAMES,
                 label: str = "classes") -> Tensor:
    """A legend of ``class_ids`` (a swatch of the :func:`palette` colour and the class name each), in as
    many columns as ``height`` pixels need: ``(3, h, w)`` in [0, 1] (``h = height``, or one swatch row more
    when that is too short)."""
    ids = sorted({int(c) for c in class_ids})
    s = _scale(height) * 0.85
    th = title_height(height)
    row = _text_size("Ag", s)[1] + 6
    height = max(height, th + row + 4)                                # at least one row of swatches
    per_col = max(1, (height - th) // row)
    pal = palette(max(ids) + 1 if ids else None)
    labels = [names[c] if 0 <= c < len(names) else f"class {c}" for c in ids]
    sw = row - 4
    col_w = sw + 8 + max([_text_size(t, s)[0] for t in labels] + [0]) + 10
    ncol = max(1, math.ceil(len(ids) / per_col))
    w = max(ncol * col_w + 4, _text_size(label, s)[0] + 8)
    canvas = _text_canvas(height, w)
    _put(canvas, label, 4, int(th * 0.7), s)
    for k, (c, text) in enumerate(zip(ids, labels)):
        x = 4 + (k // per_col) * col_w
        y = th + (k % per_col) * row
        rgb = (pal[c].numpy() * 255).round().astype(np.uint8)
        canvas[y + 2:y + 2 + sw, x:x + sw] = rgb
        canvas[y + 2:y + 2 + sw, x:x + 1] = canvas[y + 2:y + 2 + sw, x + sw - 1:x + sw] = 80
        canvas[y + 2, x:x + sw] = canvas[y + 1 + sw, x:x + sw] = 80
        _put(canvas, text, x + sw + 8, y + sw, s)
    return torch.from_numpy(canvas).permute(2, 0, 1).float() / 255


def figure_key(height: int, depth_max: float | None = None, class_ids: Sequence[int] | None = None,
               depth_min: float = 0.0) -> Tensor | None:
    """The key column of a figure: the depth colour bar (when ``depth_max``) above the class legend (when
    ``class_ids``); ``(3, h >= height, w)`` or None when there is nothing to explain."""
    parts = []
    n = int(depth_max is not None) + int(bool(class_ids))
    if n == 0:
        return None
    hh = height // n
    if depth_max is not None:
        parts.append(depth_colorbar(hh if class_ids else height, depth_max, depth_min))
    if class_ids:
        parts.append(class_legend(class_ids, height - (hh if depth_max is not None else 0)))
    w = max(p.shape[-1] for p in parts)
    out = torch.ones(3, max(height, sum(p.shape[-2] for p in parts)), w)
    y = 0
    for p in parts:
        out[:, y:y + p.shape[-2], :p.shape[-1]] = p
        y += p.shape[-2]
    return out


def _labels(sem: Tensor) -> Tensor:
    sem = sem.detach().cpu()
    if sem.is_floating_point() and sem.dim() == 3:
        return sem.argmax(0)
    return sem.reshape(sem.shape[-2:]).long()


def prediction_figure(image: Tensor, depth: Tensor | None = None, semantic: Tensor | None = None,
                      gt_depth: Tensor | None = None, gt_semantic: Tensor | None = None,
                      extra: Sequence[Panel] = (), depth_max: float | None = None, alpha: float = 0.6,
                      titles: dict[str, str] | None = None) -> Tensor:
    """The standard figure of one sample, at the resolution of ``image``:
    ``input | depth | depth GT | semantic | semantic GT | *extra`` + colour bar + legend.

    Args:
        image: ``(3, H, W)`` RGB in [0, 1].
        depth, gt_depth: ``(H', W')`` or ``(1, H', W')`` metres (resized to ``H x W`` with nearest).
        semantic, gt_semantic: ``(C, H', W')`` logits or ``(H', W')`` class ids (drawn over the image).
        extra: more ``(title, image)`` panels (e.g. a layout wireframe overlay).
        depth_max: top of the colour scale; default the 99th percentile of the GT (else predicted) depth.
        titles: replace the default panel titles (keys ``input depth gt_depth semantic gt_semantic``).

    Returns:
        ``(3, h, w)`` in [0, 1].
    """
    t = {"input": "input", "depth": "predicted depth", "gt_depth": "ground-truth depth",
         "semantic": "predicted semantics", "gt_semantic": "ground-truth semantics", **(titles or {})}
    img = _as_rgb(image)
    H, W = img.shape[-2:]

    def fit(x: Tensor, mode: str) -> Tensor:
        x = x.detach().float().cpu().reshape(-1, *x.shape[-2:])
        if x.shape[-2:] != (H, W):
            x = torch.nn.functional.interpolate(x[None], size=(H, W), mode=mode)[0]
        return x

    ref = gt_depth if gt_depth is not None else depth
    if depth_max is None and ref is not None:
        d = ref.detach().float().cpu()
        valid = torch.isfinite(d) & (d > 0)
        depth_max = float(torch.quantile(d[valid], 0.99)) if valid.any() else 1.0
    panels: list[Panel] = [(t["input"], img)]
    for key, d in (("depth", depth), ("gt_depth", gt_depth)):
        if d is not None:
            panels.append((t[key], depth_to_color(fit(d, "nearest")[0], vmax=depth_max)))
    ids: set[int] = set()
    for key, sem in (("semantic", semantic), ("gt_semantic", gt_semantic)):
        if sem is not None:
            lab = _labels(sem)
            lab = fit(lab[None].float(), "nearest")[0].long()
            ids.update(torch.unique(lab).tolist())
            panels.append((t[key], overlay(img, semantic_to_color(lab), alpha)))
    panels += list(extra)
    has_depth = depth is not None or gt_depth is not None
    key = figure_key(title_height(H) + H, depth_max if has_depth else None, sorted(ids) if ids else None)
    return titled_row(panels, key=key)
