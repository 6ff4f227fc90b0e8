"""OCamCalib ``calib_results.txt`` (adapter to :func:`omnidl.cameras.scaramuzza.read_ocamcalib`; writer).

Layout (the toolbox's ``export_data``): five data lines with ``#`` comments above each — ``N a0 .. a{N-1}``
(``pol``), ``M b0 .. b{M-1}`` (``invpol``), ``xc yc`` (row, column of the centre), ``c d e``, ``height width``.
Pixel convention: the reader follows the centre comment (see :mod:`omnidl.cameras.scaramuzza`); the writer
writes 0-based (C) centres, ``xc = cy - 0.5``, ``yc = cx - 0.5``, and says so in the comment.
"""
from __future__ import annotations

from pathlib import Path

from ...utils.io import atomic_write_bytes
from ..base import Camera
from ._common import family_of, make, unsupported

FORMAT = "ocamcalib"
HEADER = ("#polynomial coefficients for the DIRECT mapping function (ocam_model.ss in MATLAB). "
          "These are used by cam2world")


def read(path: str | Path, one_based: bool | None = None) -> Camera:
    """The :class:`~omnidl.cameras.Scaramuzza` camera of a ``calib_results.txt``."""
    from ..scaramuzza import read_ocamcalib
    kwargs = {} if one_based is None else {"one_based": one_based}
    return make("scaramuzza", f"OCamCalib file {str(path)!r}", **read_ocamcalib(path, **kwargs))


def dumps(camera: Camera, path: str | Path) -> bytes:
    """The bytes :func:`write` writes (``path`` only picks the layout by its suffix)."""
    if family_of(camera) != "scaramuzza":
        raise unsupported(FORMAT, camera, ("scaramuzza",))
    c = camera

    def poly(p: tuple[float, ...]) -> str:
        return " ".join([str(len(p))] + [repr(float(v)) for v in p])

    lines = [HEADER, "", poly(c.pol), "",
             "#polynomial coefficients for the inverse mapping function (ocam_model.invpol in MATLAB). "
             "These are used by world2cam", "", poly(c.invpol), "",
             '#center: "row" and "column", starting from 0 (C convention)', "",
             f"{float(c.cy) - 0.5!r} {float(c.cx) - 0.5!r}", "",
             '#affine parameters "c", "d", "e"', "", f"{float(c.c)!r} {float(c.d)!r} {float(c.e)!r}", "",
             '#image size: "height" and "width"', "", f"{int(c.height)} {int(c.width)}"]
    return ("\n".join(lines) + "\n").encode()


def write(camera: Camera, path: str | Path) -> None:
    """Write a ``scaramuzza`` camera as ``calib_results.txt`` (0-based centre, stated in its comment)."""
    atomic_write_bytes(path, dumps(camera, path))



def looks_like(text: str) -> bool:
    return "ocam_model" in text or "DIRECT mapping function" in text or "#polynomial coefficients" in text
