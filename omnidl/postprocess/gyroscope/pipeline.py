"""HoLiNet -> MPP -> PVG: the visual gyroscope of thesis Ch. 6 and :func:`stabilise` over a sequence.

For each frame (equirectangular RGB), with ``R = R_ref_cur`` (see the package docstring):

1. *Tilt*: the up vectors of the frame and of the reference from the horizon heat maps
   (:func:`~omnidl.geometry.horizon.fit_horizon` on HoLiNet's sigmoid outputs, or any ``horizon_fn``), as rotations
   ``T = tilt_rotation(up)`` that make each image upright.
2. *Yaw* (MPP): ``R = T_ref.T R_y(yaw) T_cur``, yaw found by :func:`mpp_yaw` about the reference's vertical.
3. *Refinement* (PVG): all three angles by :func:`pvg_refine`, starting from step 2.

The photometric steps run on grey images resized to ``2 work_height x work_height``. A frame that is
black/flat, has the wrong size or makes a solver return non-finite values gets a record with
``status = "no_estimate"`` and a ``reason``; the sequence goes on.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from omnidl.geometry.horizon import HorizonFitOptions, fit_horizon
from omnidl.geometry.panorama import rotate_panorama
from omnidl.geometry.rotations import matrix_to_euler, tilt_rotation, up_vector
from omnidl.utils.threads import limit_threads

from .icosahedron import icosahedron_vertices
from .mpp import mpp_samples, mpp_vertex_field, mpp_yaw
from .pvg import pvg_reference_values, pvg_refine

HorizonFn = Callable[[Tensor], tuple[Tensor, Tensor]]


@dataclass
class GyroscopeOptions:
    """Parameters of the pipeline (thesis values where it gives them)."""

    work_height: int = 128             # photometric steps on 2h x h grey images
    model_height: int = 128            # HoLiNet input 2h x h (reference code: 256 x 128)
    use_mpp: bool = True
    mpp_level: int = 3                 # n = 3 (thesis)
    lambda_g: float = 0.325            # thesis
    mpp_tries: int = 4
    mpp_max_iter: int = 30
    use_pvg: bool = True
    pvg_level: int = 5                 # n = 5 (thesis)
    pvg_blur: Sequence[float] = (4.0, 1.5, 0.5)
    pvg_max_iter: int = 20
    min_std: float = 1e-3              # grey-level std below this = black/flat frame: no estimate
    horizon: dict = field(default_factory=dict)  # HorizonFitOptions overrides
    # intra-op threads of the photometric steps and the horizon fit (thousands of small ops): "auto" = the
    # process setting while the CPUs are not oversubscribed, else 1 (a fork/join per op collapses on a busy
    # machine; omnidl.utils.threads.auto_threads); an int caps it; None = the process setting
    photometric_threads: int | str | None = "auto"


def model_horizon_fn(model: torch.nn.Module, height: int = 128, threads: int | str | None = "auto") -> HorizonFn:
    """Wrap a HoLiNet-like model (outputs ``"horizon"``, ``"vp"`` logits) into a ``horizon_fn``.

    ``threads``: intra-op threads of the forward (see :func:`omnidl.utils.threads.limit_threads`): ``"auto"``
    keeps the process setting unless the CPUs are oversubscribed, then runs on one thread (a small network
    is thousands of short ops: measured 12x more CPU time on 2 threads than on 1 under load)."""
    def fn(images: Tensor) -> tuple[Tensor, Tensor]:
        p = next(model.parameters())
        x = images.to(dtype=p.dtype, device=p.device)
        if tuple(x.shape[-2:]) != (height, 2 * height):  # at the same size the resampling is the identity
            x = F.interpolate(x, size=(height, 2 * height), mode="bilinear", align_corners=False, antialias=True)
        was = model.training
        model.eval()
        with torch.no_grad(), limit_threads(threads):
            out = model(x)
        model.train(was)
        return torch.sigmoid(out["horizon"]).float(), torch.sigmoid(out["vp"]).float()
    return fn


def _resize(images: Tensor, height: int) -> Tensor:
    if images.shape[-2] == height:
        return images
    return F.interpolate(images, size=(height, 2 * height), mode="bilinear", align_corners=False, antialias=True)


def pipelining_pays(network_s: float, rest_s: float, threads_now: int, threads: int) -> bool:
    """Whether :meth:`Gyroscope.track`'s pipeline beats running frames one after the other, from one frame's
    ``network_s`` and ``rest_s`` (seconds, timed on ``threads_now`` intra-op threads): pipelined, each side gets
    ``threads`` threads, so the network is assumed ``threads_now / threads`` times slower and a frame costs
    ``max(network, rest)``; unpipelined it costs ``network + rest``."""
    slower = max(1, int(threads_now)) / max(1, int(threads))
    return max(network_s * slower, rest_s) < network_s + rest_s


class Gyroscope:
    """Estimate ``R_ref_cur`` of frames w.r.t. one reference panorama.

    Args:
        horizon_fn: ``images (B, 3, H, W) -> (horizon, vp)`` probability maps ``(B, 1, h, w)``; e.g.
            :func:`model_horizon_fn` of a trained HoLiNet. ``None`` assumes every frame is upright
            (tilt 0) and lets MPP + PVG do all the work (only sensible for small tilts).
        options: :class:`GyroscopeOptions`.
    """

    def __init__(self, horizon_fn: HorizonFn | None = None, options: GyroscopeOptions | None = None) -> None:
        self.horizon_fn = horizon_fn
        self.o = options or GyroscopeOptions()
        self.hopts = HorizonFitOptions(**self.o.horizon)
        self.reference: Tensor | None = None

    # -- steps ---------------------------------------------------------------------------------
    def up_vectors(self, images: Tensor) -> tuple[Tensor, Tensor]:
        """``(B, 3)`` up vectors (camera frame) and ``(B,)`` validity of ``images (B, 3, H, W)``."""
        return self._fit(images, self._maps(images))

    def _maps(self, images: Tensor) -> tuple[Tensor, Tensor] | None:
        """The horizon maps of ``images`` (``None`` without a ``horizon_fn``)."""
        return None if self.horizon_fn is None else self.horizon_fn(images)

    def _fit(self, images: Tensor, maps: tuple[Tensor, Tensor] | None) -> tuple[Tensor, Tensor]:
        """:meth:`up_vectors` from the maps of :meth:`_maps`."""
        B = images.shape[0]
        if maps is None:
            return up_vector(images).expand(B, 3).clone(), torch.ones(B, dtype=torch.bool, device=images.device)
        with limit_threads(self.o.photometric_threads):
            res = fit_horizon(*maps, self.hopts)
        # on the frames' device (the horizon network may run elsewhere): the rotations below meet the frames there
        return res["up"].to(images.device, images.dtype), res["valid"].to(images.device)

    def set_reference(self, image: Tensor) -> None:
        """Fix the reference panorama ``(3, H, W)`` (or ``(1, 3, H, W)``): its tilt and MPP samples."""
        if image is None:
            raise ValueError("gyroscope: a reference image is required (got None)")
        if image.ndim == 3:
            image = image.unsqueeze(0)
        _check_frame(image[0])
        if _flat(image[0], self.o.min_std):
            raise ValueError("gyroscope: the reference image is black/flat; choose another reference frame")
        self.reference = image.float()
        self.ref_work = _resize(self.reference, self.o.work_height)
        up, ok = self.up_vectors(self.reference)
        if not bool(ok[0]):
            raise ValueError("gyroscope: no horizon found in the reference image; choose another reference")
        self.ref_up = up[0]
        self.T_ref = tilt_rotation(self.ref_up)
        self.ref_mpp = mpp_samples(self.ref_work, self.o.mpp_level)[1] if self.o.use_mpp else None
        # per-reference parts of the solvers, prepared once (their fast paths then never read the reference)
        vertices = icosahedron_vertices(self.o.mpp_level, device=self.ref_work.device)
        self.ref_mpp_field = mpp_vertex_field(vertices, self.ref_mpp, self.o.lambda_g) if self.o.use_mpp else None
        self.ref_pvg = pvg_reference_values(self.ref_work, self.o.pvg_level, self.o.pvg_blur) \
            if self.o.use_pvg else None

    def estimate(self, images: Tensor) -> dict[str, Tensor]:
        """Orientations of ``images (B, 3, H, W)`` (same size as the reference).

        Returns ``{"rotation": (B, 3, 3) R_ref_cur, "roll", "pitch", "yaw": (B,) radians, "up": (B, 3),
        "horizon_valid": (B,) bool, "mpp_cost", "pvg_cost": (B,)}``.
        """
        return self._photometric(*self._tilt(images))

    def track(self, frames: Iterable[Tensor], threads: int = 1, pipeline: bool | str = "auto"
              ) -> Iterator[dict[str, Tensor]]:
        """:meth:`estimate` of each of ``frames`` (``(B, 3, H, W)`` each, in order), pipelined where that is faster.

        Pipelined, the horizon network of frame ``k + 1`` (``horizon_fn``, in one worker thread) runs while this
        thread does the rest of frame ``k`` (horizon fit, MPP, PVG), each with ``threads`` intra-op threads; on a
        machine with ``2 threads`` free CPUs the throughput is then one frame per ``max(network, rest)``
        instead of their sum (the latency of a frame is unchanged), and each result is :meth:`estimate`'s for
        that frame run with ``threads`` intra-op threads. Unpipelined, each frame is :meth:`estimate` on the
        process's threads.

        Args:
            threads: intra-op threads of each side of the pipeline.
            pipeline: ``True``, ``False``, or ``"auto"``: the first frame runs unpipelined and is timed, and
                the later ones are pipelined when :func:`pipelining_pays` for its network and rest times (a
                network that needs all the cores, such as HoLiNet-ResNet-50-Equi, runs faster unpipelined).

        While pipelined the process runs with ``threads`` intra-op threads (torch's setting is global) until the
        generator is exhausted or closed; an exception of a frame is raised when its result is reached.
        """
        from concurrent.futures import ThreadPoolExecutor
        if pipeline not in (True, False, "auto"):
            raise ValueError(f"gyroscope: track(pipeline=...) must be True, False or 'auto', got {pipeline!r}")
        if self.reference is None:
            raise RuntimeError("gyroscope: call set_reference(image) before track()")
        it = iter(frames)
        first = next(it, None)
        if first is None:
            return
        if pipeline == "auto":
            t0 = time.perf_counter()
            tilt = self._tilt(first)
            t1 = time.perf_counter()
            yield self._photometric(*tilt)
            pipeline = pipelining_pays(t1 - t0, time.perf_counter() - t1, torch.get_num_threads(), threads)
            first = next(it, None)
            if first is None:
                return
        if not pipeline:
            yield self.estimate(first)
            for frame in it:
                yield self.estimate(frame)
            return
        before = torch.get_num_threads()
        torch.set_num_threads(int(threads))
        pool = ThreadPoolExecutor(1, initializer=torch.set_num_threads, initargs=(int(threads),))
        try:
            pending = pool.submit(self._tilt, first)
            for frame in it:
                tilt = pending.result()
                pending = pool.submit(self._tilt, frame)
                yield self._photometric(*tilt)
            yield self._photometric(*pending.result())
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
            torch.set_num_threads(before)

    def _tilt(self, images: Tensor) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor] | None]:
        """The network part of :meth:`estimate`: ``(images, work images, horizon maps)``."""
        if self.reference is None:
            raise RuntimeError("gyroscope: call set_reference(image) before estimate()")
        images = images.float()
        return images, _resize(images, self.o.work_height), self._maps(images)

    def _photometric(self, images: Tensor, work: Tensor, maps: tuple[Tensor, Tensor] | None) -> dict[str, Tensor]:
        """The rest of :meth:`estimate` after :meth:`_tilt`: the horizon fit (step 1), MPP and PVG (steps 2-3)."""
        up, ok = self._fit(images, maps)
        T_cur = tilt_rotation(up)
        R = self.T_ref.transpose(-1, -2) @ T_cur
        axis = self.T_ref[1, :]  # T_ref.T @ y: the reference's vertical
        B = images.shape[0]
        mpp_cost = torch.full((B,), float("nan"), device=images.device)
        pvg_cost = torch.full((B,), float("nan"), device=images.device)
        with limit_threads(self.o.photometric_threads):
            if self.o.use_mpp:
                r = mpp_yaw(work, self.ref_work, R, axis, level=self.o.mpp_level, lambda_g=self.o.lambda_g,
                            tries=self.o.mpp_tries, max_iter=self.o.mpp_max_iter, reference_samples=self.ref_mpp,
                            reference_field=self.ref_mpp_field)
                R, mpp_cost = r.rotation, r.cost
            if self.o.use_pvg:
                r = pvg_refine(work, self.ref_work, R, level=self.o.pvg_level, blur_px=self.o.pvg_blur,
                               max_iter=self.o.pvg_max_iter, reference_values=self.ref_pvg)
                R, pvg_cost = r.rotation, r.cost
        roll, pitch, yaw = matrix_to_euler(R)
        return {"rotation": R, "roll": roll, "pitch": pitch, "yaw": yaw, "up": up, "horizon_valid": ok,
                "mpp_cost": mpp_cost, "pvg_cost": pvg_cost}


def _check_frame(img: Tensor) -> None:
    if img.ndim != 3 or img.shape[0] != 3 or img.shape[-1] != 2 * img.shape[-2]:
        raise ValueError(f"expected an RGB equirectangular panorama (3, H, 2H), got shape {tuple(img.shape)}")


def _flat(img: Tensor, min_std: float) -> bool:
    return not bool(torch.isfinite(img).all()) or float(img.float().std()) < min_std


@dataclass
class FrameEstimate:
    """One frame's record (angles in degrees, ``rotation`` = ``R_ref_cur`` as nested lists)."""

    index: int
    name: str
    status: str                        # "ok" | "no_estimate"
    reason: str = ""
    roll: float = float("nan")
    pitch: float = float("nan")
    yaw: float = float("nan")
    rotation: list | None = None
    horizon_valid: bool = False
    mpp_cost: float = float("nan")
    pvg_cost: float = float("nan")

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def stabilise(frames: Iterable[Tensor], reference: Tensor, horizon_fn: HorizonFn | None = None,
              options: GyroscopeOptions | None = None, names: Sequence[str] | None = None, batch_size: int = 4,
              on_frame: Callable[[FrameEstimate, Tensor, Tensor | None], None] | None = None,
              progress: bool = False) -> list[FrameEstimate]:
    """Estimate the rotation of every frame w.r.t. ``reference`` and stabilise it.

    Args:
        frames: iterable of ``(3, H, W)`` RGB tensors in ``[0, 1]``.
        reference: ``(3, H, W)`` reference panorama (required: ``None`` raises ``ValueError``).
        horizon_fn: tilt source (see :class:`Gyroscope`); ``None`` = frames assumed upright.
        names: per-frame names for the records (default ``frame_000000`` ...).
        on_frame: ``callback(record, frame, stabilised or None)`` called in order (writers, viewers).
    Returns:
        one :class:`FrameEstimate` per frame; the stabilised frame is
        ``rotate_panorama(frame, R.T)`` with ``R = record.rotation``.
    """
    if reference is None:
        raise ValueError("stabilise: a reference image is required (got None)")
    gyro = Gyroscope(horizon_fn, options)
    gyro.set_reference(reference)
    H, W = reference.shape[-2:]
    records: list[FrameEstimate] = []
    pending: list[tuple[int, str, Tensor]] = []
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(desc="stabilise", unit="frame")

    def flush() -> None:
        if not pending:
            return
        batch = torch.stack([f for _, _, f in pending]).float()
        try:
            est = gyro.estimate(batch)
            err = None
        except Exception as e:  # a solver failure must not stop the sequence
            est, err = None, f"{type(e).__name__}: {e}"
        for k, (i, name, frame) in enumerate(pending):
            if est is None or not bool(torch.isfinite(est["rotation"][k]).all()):
                rec = FrameEstimate(i, name, "no_estimate", err or "non-finite rotation")
                stab = None
            else:
                R = est["rotation"][k]
                rec = FrameEstimate(i, name, "ok", "", *(math.degrees(float(est[a][k])) for a in ("roll", "pitch", "yaw")),
                                    rotation=R.tolist(), horizon_valid=bool(est["horizon_valid"][k]),
                                    mpp_cost=float(est["mpp_cost"][k]), pvg_cost=float(est["pvg_cost"][k]))
                stab, _ = rotate_panorama(frame.float(), R.T, cache=False)
            _emit(rec, frame, stab)
        pending.clear()

    def _emit(rec: FrameEstimate, frame: Tensor, stab: Tensor | None) -> None:
        records.append(rec)
        if on_frame is not None:
            on_frame(rec, frame, stab)
        if bar is not None:
            bar.update(1)

    for i, frame in enumerate(frames):
        name = names[i] if names is not None and i < len(names) else f"frame_{i:06d}"
        if frame is None:
            flush()
            _emit(FrameEstimate(i, name, "no_estimate", "frame could not be read"), torch.zeros(3, H, W), None)
            continue
        if frame.ndim != 3 or frame.shape[0] != 3 or tuple(frame.shape[-2:]) != (H, W):
            flush()
            _emit(FrameEstimate(i, name, "no_estimate", f"frame shape {tuple(frame.shape)} differs from the "
                                f"reference (3, {H}, {W})"), frame, None)
            continue
        if _flat(frame, gyro.o.min_std):
            flush()
            _emit(FrameEstimate(i, name, "no_estimate", "black/flat frame (no texture to align)"), frame, None)
            continue
        pending.append((i, name, frame))
        if len(pending) >= batch_size:
            flush()
    flush()
    if bar is not None:
        bar.close()
    return records
