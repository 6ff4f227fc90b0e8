"""What ``omnidl predict`` reads: one image, a folder of images (sorted by name) or a video (every frame).

Each item is ``(name, image)`` with ``image (3, H, W)`` float RGB in [0, 1] at the file's own resolution.
"""
from __future__ import annotations

from collections.abc import Iterator
import warnings
from pathlib import Path

import numpy as np
import torch

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")


def kind_of(path: str | Path) -> str:
    """``"image"``, ``"folder"`` or ``"video"``; a clear error for anything else."""
    p = Path(path)
    if p.is_dir():
        return "folder"
    if not p.exists():
        raise FileNotFoundError(f"INPUT {p}: no such file or folder")
    suf = p.suffix.lower()
    if suf in IMAGE_EXTENSIONS:
        return "image"
    if suf in VIDEO_EXTENSIONS:
        return "video"
    raise ValueError(f"INPUT {p}: unknown extension {suf!r}; expected an image ({', '.join(IMAGE_EXTENSIONS)}), "
                     f"a video ({', '.join(VIDEO_EXTENSIONS)}) or a folder of images")


def _bgr_to_tensor(bgr: np.ndarray) -> torch.Tensor:
    if bgr.ndim == 2:
        bgr = np.repeat(bgr[..., None], 3, 2)
    if bgr.dtype == np.uint16:
        arr = bgr[..., :3][..., ::-1].astype(np.float32) / 65535.0
    else:
        arr = bgr[..., :3][..., ::-1].astype(np.float32) / 255.0
    return torch.from_numpy(np.ascontiguousarray(arr)).permute(2, 0, 1)


def read_image(path: str | Path) -> torch.Tensor:
    """An image file -> ``(3, H, W)`` RGB in [0, 1] (8- or 16-bit, grey or colour; alpha dropped)."""
    import cv2
    bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if bgr is None:
        raise ValueError(f"{path}: not a readable image")
    return _bgr_to_tensor(bgr)


def list_images(folder: str | Path) -> list[Path]:
    """Image files of ``folder`` sorted by name (sub-folders are not searched)."""
    files = sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise FileNotFoundError(f"INPUT folder {folder} holds no images ({', '.join(IMAGE_EXTENSIONS)})")
    return files


def iter_inputs(path: str | Path, limit: int = 0) -> Iterator[tuple[str, torch.Tensor | None]]:
    """``(name, image)`` for every input item; ``image`` is None (with a warning) for an unreadable file of a
    folder, so one bad file does not stop a batch."""
    kind = kind_of(path)
    p = Path(path)
    n = 0
    if kind == "image":
        yield p.stem, read_image(p)
        return
    if kind == "folder":
        for f in list_images(p):
            if limit and n >= limit:
                return
            n += 1
            try:
                yield f.stem, read_image(f)
            except ValueError as e:
                warnings.warn(f"{e}; skipped", stacklevel=2)
                yield f.stem, None
        return
    import cv2
    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise ValueError(f"INPUT {p}: OpenCV cannot open this video")
    try:
        while not limit or n < limit:
            ok, frame = cap.read()
            if not ok:
                break
            yield f"{p.stem}_{n:06d}", _bgr_to_tensor(frame)
            n += 1
    finally:
        cap.release()
    if n == 0:
        raise ValueError(f"INPUT {p}: the video has no readable frame")


def video_fps(path: str | Path, default: float = 10.0) -> float:
    """Frame rate of a video file (``default`` for folders or when unknown)."""
    if kind_of(path) != "video":
        return default
    import cv2
    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS) if cap.isOpened() else 0
    cap.release()
    return float(fps) if fps and fps > 0 and np.isfinite(fps) else default
