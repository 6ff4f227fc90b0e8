"""What ``omnidl predict`` reads: one image, a folder of images (sorted by name) or a video (every frame).

Each item is ``(name, image)`` with ``image (3, H, W)`` float RGB in [0, 1] at the file's own resolution
(:func:`iter_items` adds the file each item comes from). ``name`` is the file's stem, unless two files of a
folder share it (``a.png`` + ``a.jpg``, or ``A.png`` + ``a.png``, which a case-insensitive file system cannot
tell apart): then each gets its extension, ``a_png`` and ``a_jpg`` (:func:`omnidl.utils.outputs.unique_stems`,
deterministic), so their outputs never overwrite each other. Video frames are ``<stem>_<index:06d>``.
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


def read_image(path: str | Path) -> torch.Tensor:
    """An image file -> ``(3, H, W)`` RGB in [0, 1] (8- or 16-bit, grey or colour; alpha dropped; EXIF
    orientation applied; a file name of any bytes): the datasets' reading policy,
    :func:`omnidl.data.readers.read_rgb`. An unreadable file is a ``ValueError`` naming it."""
    from omnidl.data.readers import read_rgb
    try:
        return read_rgb(path, field="INPUT")
    except OSError as e:                  # UnreadableFileError: missing, undecodable, over OpenCV's pixel limit
        raise ValueError(str(e)) from e


def list_images(folder: str | Path) -> list[Path]:
    """Image files of ``folder`` sorted by name (sub-folders are not searched)."""
    files = sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise FileNotFoundError(f"INPUT folder {folder} holds no images ({', '.join(IMAGE_EXTENSIONS)})")
    return files


def item_names(paths: list[Path]) -> list[str]:
    """Output names of a folder's images: :func:`omnidl.utils.outputs.unique_stems` (see the module docstring)."""
    from omnidl.utils.outputs import unique_stems
    return unique_stems(paths)


def iter_items(path: str | Path, limit: int = 0) -> Iterator[tuple[str, torch.Tensor | None, Path]]:
    """``(name, image, source file)`` for every input item; ``image`` is None (with a warning) for an
    unreadable file of a folder, so one bad file does not stop a batch. A video's frames share its file."""
    kind = kind_of(path)
    p = Path(path)
    n = 0
    if kind == "image":
        yield p.stem, read_image(p), p
        return
    if kind == "folder":
        files = list_images(p)
        if limit:
            files = files[:limit]
        for f, name in zip(files, item_names(files)):
            try:
                yield name, read_image(f), f
            except ValueError as e:
                warnings.warn(f"{e}; skipped", stacklevel=2)
                yield name, None, f
        return
    from omnidl.data.readers import iter_video_frames
    try:
        for frame in iter_video_frames(p, limit):
            yield f"{p.stem}_{n:06d}", frame, p
            n += 1
    except OSError as e:                  # UnreadableFileError: OpenCV cannot open it
        raise ValueError(f"INPUT {p}: {e}") from e
    if n == 0:
        raise ValueError(f"INPUT {p}: the video has no readable frame")


def planned_items(path: str | Path, limit: int = 0) -> list[tuple[str, Path]] | None:
    """``(name, file)`` of every item of an image or a folder without reading them (None for a video, whose
    frame count is known only once read)."""
    kind = kind_of(path)
    p = Path(path)
    if kind == "image":
        return [(p.stem, p)]
    if kind == "folder":
        files = list_images(p)
        files = files[:limit] if limit else files
        return list(zip(item_names(files), files))
    return None


def iter_inputs(path: str | Path, limit: int = 0) -> Iterator[tuple[str, torch.Tensor | None]]:
    """``(name, image)`` of :func:`iter_items`."""
    for name, image, _ in iter_items(path, limit):
        yield name, image


def video_fps(path: str | Path, default: float = 10.0) -> float:
    """Frame rate of a video file (``default`` for folders or when unknown)."""
    if kind_of(path) != "video":
        return default
    import cv2

    from omnidl.data.readers import cv2_path
    with cv2_path(path) as name:
        cap = cv2.VideoCapture(name)
        fps = cap.get(cv2.CAP_PROP_FPS) if cap.isOpened() else 0
        cap.release()
    return float(fps) if fps and fps > 0 and np.isfinite(fps) else default
