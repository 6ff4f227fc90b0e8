"""``omnidl predict depth|layout|upright|stabilise INPUT --checkpoint CKPT --out DIR``: omnidl on your own
panoramas. INPUT is an image, a folder of images or a video; the network's input size, camera and model come
from the checkpoint; any input resolution works (outputs are at the input's resolution).

Per image ``<name>`` in ``DIR``:

* ``depth``: ``<name>_depth.npy`` (float32 metres), ``<name>_depth.png`` + ``<name>_depth.json`` (16-bit,
  ``depth_m = png * scale``), ``<name>_semantic.png`` (class ids) + ``<name>_semantic_color.png``,
  ``<name>.ply`` (coloured, gravity-aligned y-up frame), ``<name>_figure.png`` (full-size panels with titles,
  a depth colour bar in metres and a class legend), ``<name>_upright.json``;
* ``layout``: ``<name>_layout.json`` (layout frame, input-frame corners, tilt), ``<name>_layout.obj`` (y-up),
  ``<name>_wireframe.png`` (wireframe over the input), ``<name>_figure.png``;
* ``upright`` (no checkpoint needed): ``<name>_upright.png``, ``<name>_upright.json``, ``<name>_figure.png``;
* ``stabilise`` (the whole sequence): ``rotations.json``/``.csv``, ``stabilised/``, ``before_after/``,
  ``angles.png``, ``before_after.mp4`` (H.264).

``depth`` and ``layout`` level a non-upright panorama first (``--upright auto``, weight-free, see
:mod:`omnidl.geometry.upright`) and return maps in the input's frame. ``--compile`` compiles their network
with ``torch.compile`` (Inductor, freezing) before the first image and prints the compile time; the outputs
are the same up to float rounding.
"""
from .cli import main

__all__ = ["main"]
