"""H.264 MP4 that plays in a browser (yuv420p, even frame size, ``+faststart``), through imageio-ffmpeg
(preferred: it ships an ffmpeg binary) or PyAV. Install one with ``pip install "omnidl[video]"``."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

INSTALL_HINT = ('H.264 video needs imageio-ffmpeg or PyAV: pip install "omnidl[video]" (or pip install '
                'imageio-ffmpeg); the PNG frames are written either way')


def backend() -> str | None:
    """``"imageio-ffmpeg"``, ``"pyav"`` or None when neither is installed."""
    try:
        import imageio_ffmpeg  # noqa: F401
        return "imageio-ffmpeg"
    except ImportError:
        pass
    try:
        import av  # noqa: F401
        return "pyav"
    except ImportError:
        return None


def _even(frame: np.ndarray) -> np.ndarray:
    h, w = frame.shape[:2]
    return np.ascontiguousarray(frame[: h - h % 2, : w - w % 2])


class H264Writer:
    """``with H264Writer(path, fps) as w: w.write(rgb_uint8 (H, W, 3))``; the file appears atomically on close.

    Raises ``RuntimeError`` (with the install hint) when no backend is installed."""

    def __init__(self, path: str | Path, fps: float = 10.0) -> None:
        self.path = Path(path)
        self.fps = float(fps)
        self.kind = backend()
        if self.kind is None:
            raise RuntimeError(INSTALL_HINT)
        self.tmp = self.path.with_name(f".{self.path.stem}.tmp{os.getpid()}.mp4")
        self.size: tuple[int, int] | None = None
        self._gen = self._container = self._stream = None
        self.frames = 0

    def _open(self, h: int, w: int) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.size = (h, w)
        if self.kind == "imageio-ffmpeg":
            import imageio_ffmpeg
            self._gen = imageio_ffmpeg.write_frames(str(self.tmp), (w, h), fps=self.fps, codec="libx264",
                                                    pix_fmt_out="yuv420p", macro_block_size=2, quality=7,
                                                    output_params=["-movflags", "+faststart"])
            self._gen.send(None)
        else:
            import av
            self._container = av.open(str(self.tmp), mode="w", options={"movflags": "+faststart"})
            self._stream = self._container.add_stream("libx264", rate=int(round(self.fps)))
            self._stream.width, self._stream.height, self._stream.pix_fmt = w, h, "yuv420p"

    def write(self, rgb: np.ndarray) -> None:
        """One ``(H, W, 3)`` uint8 RGB frame (every frame the size of the first; odd sizes are cropped by 1)."""
        frame = _even(np.asarray(rgb, dtype=np.uint8))
        if self.size is None:
            self._open(*frame.shape[:2])
        if frame.shape[:2] != self.size:
            raise ValueError(f"video frame is {frame.shape[1]}x{frame.shape[0]}, the video is "
                             f"{self.size[1]}x{self.size[0]}")
        if self._gen is not None:
            self._gen.send(frame)
        else:
            import av
            for pkt in self._stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                self._container.mux(pkt)
        self.frames += 1

    def close(self) -> Path | None:
        """Finish the file; returns its path (None when no frame was written)."""
        if self._gen is not None:
            self._gen.close()
        if self._container is not None:
            for pkt in self._stream.encode():
                self._container.mux(pkt)
            self._container.close()
        if self.frames == 0:
            return None
        os.replace(self.tmp, self.path)
        return self.path

    def __enter__(self) -> "H264Writer":
        return self

    def __exit__(self, exc_type, *_) -> None:
        if exc_type is None:
            self.close()
            return
        try:                                              # an error: finish the encoder, keep no partial file
            if self._gen is not None:
                self._gen.close()
            if self._container is not None:
                self._container.close()
        finally:
            if self.tmp.exists():
                self.tmp.unlink()
