"""A folder of the user's own panoramas (no labels): ``python evaluate.py ... data=folder data.root=DIR``."""
from __future__ import annotations

from pathlib import Path

from .paired import PairedPanoramas, PanoramaFiles

EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


class ImageFolder(PairedPanoramas):
    """Every image file directly in ``root`` (or below it with ``recursive=True``), sorted by path, resized to
    ``width x height`` (the network's input size; None keeps each file's size, then use batch size 1).
    Samples are ``{"image", "meta"}``."""

    def __init__(self, root: str, height: int | None = 256, width: int | None = 512, recursive: bool = False,
                 extensions: tuple[str, ...] = EXTENSIONS):
        root_p = Path(root).expanduser()
        if not root_p.is_dir():
            raise FileNotFoundError(f"image folder {root_p} does not exist (set data.root=<folder of panoramas>)")
        exts = {e.lower() for e in extensions}
        files = sorted(p for p in (root_p.rglob("*") if recursive else root_p.iterdir())
                       if p.is_file() and p.suffix.lower() in exts)
        if not files:
            raise FileNotFoundError(f"image folder {root_p} holds no images with extensions {sorted(exts)}"
                                    f"{'' if recursive else ' (recursive=false)'}")
        samples = [PanoramaFiles(name=p.relative_to(root_p).with_suffix("").as_posix(), image=p)  # x/y: evaluation makes it file-safe
                   for p in files]
        super().__init__(samples, height, width, None, None, f"image folder {root_p}")
