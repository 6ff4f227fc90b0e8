"""The perspective views of the view chain, cut from panoramas, as a training set (issue 50, view re-projection).

:class:`PanoramaViews` wraps a panorama dataset (any map-style dataset of sample dicts with ``image`` and ``depth``
on a known camera: the built-in synthetic rooms by default, Stanford2D3DS, a ``_target_``; central or non-central)
and yields the views of :func:`omnidl.geometry.views.view_layout` -- the same views, cut by the same code
(:func:`~omnidl.geometry.views.view_warp`, kept per view and sampled as :func:`~omnidl.geometry.views.cut_views`
samples it), that the zero-shot chain :func:`~omnidl.geometry.views.depth_through_views` runs a network on:

* **one sample per view**: sample ``i`` is view ``i % V`` of panorama ``i // V`` (``V`` views the camera sees: 12
  ``tangent``, 6 ``cube`` for a full panorama), so an epoch shows every view of every panorama once; the training
  sampler shuffles them. Consecutive views share a panorama (an in-memory LRU of ``cache_panoramas``); a shuffled
  order loads a panorama up to ``V`` times per epoch -- give the synthetic source a ``cache_dir``.
* **image**: the chain's cut (bilinear; a non-central camera sampled at ``assumed_range``, as the chain does).
* **depth**: the view's **z-depth** ``z = r * cos`` (:func:`~omnidl.geometry.views.view_cos`: the cosine of the view
  pixel's ray to the view axis; the chain reads a view's depth back as ``z / cos``), ``r`` the range from the
  centre of the 3D point the input pixel **nearest** to the view pixel's sample point sees (``|o + depth * d|``;
  the input's depth for a central camera). Nearest: a depth never mixes foreground and background at an edge
  (a bilinear blend of two surfaces is a surface that is not there).
* **semantic**: nearest (``0`` = unknown), when the panorama has one; **valid**: the view pixel is seen by the
  camera and its nearest input pixel has a depth ``> 0`` (``depth = 0`` and ``semantic = 0`` elsewhere).

Sample dict (``S`` = view side): ``image (3, S, S) float32`` in ``[0, 1]``, ``depth (1, S, S) float32`` (z-depth,
metres, 0 = invalid), ``valid (S, S) bool``, ``semantic (S, S) int64`` (if the source has one), ``rotation (3, 3)
float32`` ``R_input_view`` (a view-frame direction ``d`` is ``R @ d`` in the input camera's frame), ``meta``
(panorama and view index, layout, split, the view's pinhole camera config).
"""
from __future__ import annotations

from collections import OrderedDict
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor
from torch.utils.data import Dataset

from omnidl.cameras.base import Camera
from omnidl.cameras.equirectangular import Equirectangular
from omnidl.cameras.resolve import resolve_camera
from omnidl.geometry.views import View, view_cos, view_layout, view_warp, visible_views
from omnidl.geometry.warp import WarpGrid, sample_grid

from .fisheye import SPLITS, build_panoramas
from .readers import image_to_float


class PanoramaViews(Dataset):
    """Perspective views of panoramas with z-depth targets (module doc).

    Args:
        panoramas: the panorama source: a dataset object or a config mapping (:func:`omnidl.data.fisheye.
            build_panoramas`: ``{"type": "synthetic", ...}`` (default), ``{"type": "stanford2d3ds", ...}`` or a
            ``_target_``).
        camera: the panoramas' camera (any :func:`omnidl.cameras.resolve_camera` spec); default the source's own
            ``camera`` attribute (the synthetic datasets have one), else an equirectangular camera of the image
            size (which must then be twice as wide as high).
        layout, size, fov: the views (:func:`omnidl.geometry.views.view_layout`); ``size`` a multiple of 32 for
            FreDSNet.
        split: ``train``/``val``/``test`` (passed to a config-built source).
        assumed_range: metres at which a non-central camera is cut (as the chain; unused for central ones).
        length: number of samples (default: every view of every panorama).
        cache_panoramas: panoramas kept in memory.
    """

    def __init__(self, panoramas: Any = None, camera: Any = None, layout: str = "tangent", size: int = 96,
                 fov: float | None = None, split: str = "train", assumed_range: float = 3.0,
                 length: int | None = None, cache_panoramas: int = 2) -> None:
        if split not in SPLITS:
            raise ValueError(f"PanoramaViews: split must be one of {sorted(SPLITS)}, got {split!r}")
        self.panoramas = build_panoramas(panoramas, split)
        self.split, self.layout, self.assumed_range = split, layout, float(assumed_range)
        self.all_views = view_layout(layout, int(size), fov)
        self._camera_spec = camera if camera is not None else getattr(self.panoramas, "camera", None)
        self._cameras: dict[tuple[int, int], tuple[Camera, list[View], list[int]]] = {}
        self._rays: dict[tuple[int, int], tuple[Tensor, Tensor]] = {}
        self._grids: dict[tuple[int, int, int], WarpGrid] = {}
        if self._camera_spec is not None:
            cam = resolve_camera(self._camera_spec)
            self.views_per_panorama = len(self._setup(cam.width, cam.height)[1])
        else:
            self.views_per_panorama = len(self.all_views)   # an equirectangular panorama sees all of them
        n = len(self.panoramas) * self.views_per_panorama
        self.length = n if length is None else int(length)
        if not 0 < self.length <= n:
            raise ValueError(f"PanoramaViews: length={length}: the panorama source has {len(self.panoramas)} "
                             f"panoramas x {self.views_per_panorama} views = {n} views")
        self._cache: OrderedDict[int, dict] = OrderedDict()
        self._cache_size = int(cache_panoramas)
        self._cos = [view_cos(v, torch.float32) for v in self.all_views]

    def __len__(self) -> int:
        return self.length

    def _setup(self, width: int, height: int) -> tuple[Camera, list[View], list[int]]:
        """The camera at the panorama's size, the views it sees and their indices in :attr:`all_views`."""
        key = (int(width), int(height))
        if key not in self._cameras:
            if self._camera_spec is None:
                if width != 2 * height:
                    raise ValueError(f"PanoramaViews: a {width}x{height} image with no camera given; an "
                                     "equirectangular panorama must be twice as wide as high (or pass camera=)")
                cam = Equirectangular(width=int(width), height=int(height))
            else:
                cam = resolve_camera(self._camera_spec, int(width), int(height))
            seen = visible_views(cam, self.all_views)
            idx = [i for i, v in enumerate(self.all_views) if any(v is s for s in seen)]
            self._cameras[key] = (cam, seen, idx)
        return self._cameras[key]

    def _panorama(self, k: int) -> dict:
        if k in self._cache:
            self._cache.move_to_end(k)
            return self._cache[k]
        pano = self.panoramas[k]
        for key in ("image", "depth"):
            if key not in pano:
                raise KeyError(f"PanoramaViews: panorama {k} of {type(self.panoramas).__name__} has no {key!r} "
                               f"(keys: {sorted(pano)})")
        if self._cache_size > 0:
            self._cache[k] = pano
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return pano

    def _points(self, camera: Camera, depth: Tensor) -> Tensor:
        """``(3, H, W)``: the 3D point each input pixel sees (``o + depth * d``, camera frame)."""
        key = (camera.width, camera.height)
        if key not in self._rays:
            rays = camera.unproject_grid(dtype=torch.float32)
            self._rays[key] = (rays.origin, rays.direction)
        o, d = self._rays[key]
        return (o + depth[0, ..., None] * d).permute(2, 0, 1)

    def __getitem__(self, index: int) -> dict:
        if not 0 <= index < self.length:
            raise IndexError(f"index {index} out of range for a dataset of length {self.length}")
        k, j = divmod(int(index), self.views_per_panorama)
        pano = self._panorama(k)
        h, w = pano["image"].shape[-2:]
        cam, views, idx = self._setup(w, h)
        if len(views) != self.views_per_panorama:
            raise ValueError(f"PanoramaViews: panorama {k} ({w}x{h}) sees {len(views)} views, the dataset was "
                             f"sized for {self.views_per_panorama}; give every panorama the same camera")
        view, vi = views[j], idx[j]
        gkey = (w, h, vi)
        if gkey not in self._grids:
            self._grids[gkey] = view_warp(cam, view, self.assumed_range)
        grid = self._grids[gkey]
        img = image_to_float(pano["image"], f"panorama {k}").float()
        image, seen = sample_grid(img.reshape(1, -1, h, w), grid, "bilinear")    # the chain's cut (cut_views)
        image, seen = image[0], seen[0, 0]
        depth = pano["depth"].float().reshape(1, h, w)
        has = (depth > 0) & torch.isfinite(depth)
        depth = torch.where(has, depth, torch.zeros_like(depth))
        stack = torch.cat([self._points(cam, depth), has.float()])[None]          # (1, 4, H, W)
        near, ok_near = sample_grid(stack, grid, "nearest")
        r = near[0, :3].norm(dim=0)                                               # range from the centre
        valid = seen & ok_near[0, 0] & (near[0, 3] > 0.5) & (r > 0)
        z = torch.where(valid, r * self._cos[vi], torch.zeros_like(r))
        out = {"image": torch.where(seen, image, torch.zeros_like(image)).clamp(0, 1),
               "depth": z[None].float(), "valid": valid}
        if "semantic" in pano:
            sem, _ = sample_grid(pano["semantic"].reshape(1, 1, h, w).long(), grid, "nearest")
            out["semantic"] = torch.where(valid, sem[0, 0], torch.zeros_like(sem[0, 0]))
        S = view.camera.width
        out["rotation"] = view.rotation.float()
        meta = {"panorama": int(k), "view": int(vi), "layout": self.layout, "split": self.split, "size": int(S),
                "view_camera": view.camera.to_config()}
        if isinstance(pano.get("meta"), Mapping):
            meta["panorama_meta"] = {kk: vv for kk, vv in pano["meta"].items() if isinstance(vv, (str, int, float))}
        out["meta"] = meta
        return out


__all__ = ["PanoramaViews"]
