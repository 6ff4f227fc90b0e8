"""``omnidl predict depth|layout|upright|stabilise INPUT --checkpoint CKPT --out DIR``: omnidl on your own
panoramas. INPUT is an image, a folder of images or a video; the network's input size, camera and model come
from the checkpoint; outputs are at the input's resolution.

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

Cameras (``--camera FILE|PRESET``, :mod:`omnidl.apps.predict.camera`). Without it, the input must show the
model's own camera: the network's input size or that image uniformly resized (a 2:1 panorama for an
equirectangular model); any other size or aspect is refused with both sizes named, never stretched. With it
(any calibration file :func:`omnidl.cameras.load` reads, or a preset such as ``kb_f195``; else a sidecar
``<stem>.camera.yaml``/``.json`` next to the input) the image is re-projected into the model's camera, the
network runs there and every output comes back to the input: depth and semantics per input pixel, points
along the input camera's own rays (non-central included) in metres. Input pixels the model camera does not see
are **masked, never filled in**: ``NaN`` in ``<name>_depth.npy``, 0 in ``<name>_depth.png`` and in
``<name>_semantic.png``, 0 in ``<name>_valid.png`` (255 = both cameras see); the shares are printed and
written in ``<name>_predict.json`` (``camera.coverage``) or the layout JSON.

Outputs never destroy data (:mod:`omnidl.utils.outputs`): images of one folder sharing a stem get their
extension in the name (``a.png`` + ``a.jpg`` -> ``a_png_*`` and ``a_jpg_*``); an output never replaces an input
(``--out`` may be the input folder, but an existing file there, e.g. a ground truth ``x_depth.png``, is never
overwritten, with or without ``--overwrite``); a previous run's outputs are replaced only with
``--overwrite``; the folder is locked while a run writes (``.omnidl.lock``); every file is written atomically.
Everything is checked before the first file is written. ``depth`` also writes ``<name>_predict.json`` (cameras,
coverage, point-cloud size); ``--max-points N`` / ``--voxel SIZE`` bound the clouds
(:mod:`omnidl.apps.predict.points`; default: every valid pixel, as before).

``depth`` and ``layout`` level a non-upright panorama first (``--upright auto``, weight-free, see
:mod:`omnidl.geometry.upright`) and return maps in the input's frame. ``--compile`` compiles their network
with ``torch.compile`` (Inductor, freezing) before the first image and prints the compile time; the outputs
are the same up to float rounding.
"""
from .cli import main

__all__ = ["main"]
