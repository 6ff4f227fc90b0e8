"""``torch.ops.omnidl.surface_shade``: the synthetic renderer's per-pixel surface pass.

From the ray-cast hits of every pixel - the hit point and ray direction ``(3, P)`` (component-major), whether the ray
hit anything, the box it hit (``-1``: none) and the room hit (``kind`` CEILING / WALL / FLOOR, the wall and the
metres along it) - and the scene's tables, the op finds each pixel's surface and returns its colour, labels and
normal. Surfaces are numbered walls ``0..n-1``, floor ``n``, ceiling ``n+1`` (also for pixels without a hit),
wall openings ``n+2..n+1+K`` (the last opening of the wall that contains a wall pixel without a box), boxes
``n+2+K..``. Per pixel:

* ``semantic``, ``instance``: the surface's labels, 0 without a hit;
* the world normal: the structural surface's, or the box face's (the local axis of largest ``|x| / half size``),
  negated where it points along the ray, 0 without a hit; returned in the camera frame (``rotation^T n``,
  ``rotation`` camera-to-world);
* ``image``: the albedo ``c1 (1 - w) + c2 w`` of the surface's material, ``w`` its procedural texture
  (:func:`texture_mix`) at the surface coordinates (metres along the wall and height; ``x, y`` on the floor and
  ceiling; ``[0, 1]`` panel coordinates on a PANEL opening; the face's two other local axes on a box), times the
  light ``ambient + sum_l power_l max(n.(l - p) / |l - p|, 0) / (1 + |l - p|^2 / 4) * shadow[l, p]`` rolled off as
  ``1.25 g / (1 + g / 4)``, unless the material is emissive; clamped to ``[0, 1]``; 0 without a hit.

Registered with ``torch.library`` (schema, fake kernel; no autograd: labels and a procedural image are not
differentiable). Kernels, by device only:

* CPU: the native C kernel (``csrc/surface_shade.c``: one pass per pixel, the PyTorch implementation's float32
  operations in the same order) for float32 operands; other dtypes, and a machine where the kernel cannot be built,
  the PyTorch implementation.
* any other device: the PyTorch implementation (:func:`torch_surface_shade`: gathers over whole images, a mask per
  opening, a pass per texture kind).

The two agree exactly on every label, surface and texture cell; the image and the camera-frame normal to float32
rounding (the three-term products with the lights and with ``rotation^T`` are matrix products, which a BLAS may sum
in another order).
"""
from __future__ import annotations

import ctypes
from typing import NamedTuple

import torch
from torch import Tensor

from . import _native

#: the room hit's kinds (``kind``): no hit, ceiling, wall, floor
NONE, CEILING, WALL, FLOOR = 0, 1, 2, 3
#: the procedural textures (a material's ``texture``); a kind above PANEL is drawn as PLANKS
PLAIN, STRIPES, CHECKER, NOISE, PLANKS, PANEL = range(6)

LIBRARY = "surface_shade"
_P, _I, _I64 = _native.POINTER, _native.INT, _native.INT64
_SIGNATURES = {
    "omnidl_surface_shade": (_I, [_I64, _P, _P, _P, _P, _P, _P, _P, _I64, _I64, _P, _P, _P, _P, _I64, _P, _P, _P,
                                  _P, _P, _P, _P, _P, _I, _P, _P, ctypes.c_float, _P, _P, _P, _P, _P, _I]),
}


def native_library() -> ctypes.CDLL | None:
    """The CPU kernel's library (built on first use), or ``None`` where it cannot be built."""
    return _native.load(LIBRARY, ["surface_shade.c"], _SIGNATURES)


class SurfaceTables(NamedTuple):
    """The scene's operands of :func:`surface_shade`, in the op's order (after the per-pixel ones)."""
    n_walls: int
    openings: Tensor       # (K, 6) float rows s0, s1, z0, z1, s1 - s0, z1 - z0 of each wall opening
    opening_wall: Tensor   # (K,) int64 wall of each opening
    opening_panel: Tensor  # (K,) bool: the opening's texture is PANEL (its own [0, 1] coordinates)
    boxes: Tensor          # (B, 8) float rows x, y, z, half sizes x, y, z, cos yaw, sin yaw
    semantic: Tensor       # (S,) int64 per surface, S = n_walls + 2 + K + B
    instance: Tensor       # (S,) int64 per surface
    material: Tensor       # (S,) int64 per surface: a row of the material tables
    normal: Tensor         # (n_walls + 2 + K, 3) float inward normal of each structural surface
    colour: Tensor         # (M, 6) float colour 1 | colour 2 per material
    texture: Tensor        # (M,) int64 texture kind per material
    scale: Tensor          # (M,) float texture scale per material (metres; at least 1e-3 is used)
    emissive: Tensor       # (M,) bool per material
    lights: Tensor         # (L, 4) float rows x, y, z, power of the point lights
    ambient: float


# ---- the op ------------------------------------------------------------------------------------------------------

@torch.library.custom_op("omnidl::surface_shade", mutates_args=())
def surface_shade(point: Tensor, direction: Tensor, hit: Tensor, box_id: Tensor, kind: Tensor, wall: Tensor,
                  wall_s: Tensor, n_walls: int, openings: Tensor, opening_wall: Tensor, opening_panel: Tensor,
                  boxes: Tensor, semantic: Tensor, instance: Tensor, material: Tensor, normal: Tensor,
                  colour: Tensor, texture: Tensor, scale: Tensor, emissive: Tensor, lights: Tensor, ambient: float,
                  rotation: Tensor, shadow: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(image (3, P), semantic (P,), instance (P,), normal_cam (3, P))`` of the pixels ``point``, ``direction
    (3, P)``, ``hit (P,)`` bool, ``box_id (P,)``, ``kind``, ``wall (P,)`` int64, ``wall_s (P,)`` in a scene of
    :class:`SurfaceTables`, ``rotation (3, 3)`` camera-to-world, ``shadow (L, P)`` the light factors (``None``: 1);
    see the module docstring (this body: devices without a kernel)."""
    return torch_surface_shade(point, direction, hit, box_id, kind, wall, wall_s, n_walls, openings, opening_wall,
                               opening_panel, boxes, semantic, instance, material, normal, colour, texture, scale,
                               emissive, lights, ambient, rotation, shadow)


@surface_shade.register_fake
def _fake(point, direction, hit, box_id, kind, wall, wall_s, n_walls, openings, opening_wall, opening_panel, boxes,
          semantic, instance, material, normal, colour, texture, scale, emissive, lights, ambient, rotation,
          shadow=None):
    check_arguments(point, direction, hit, box_id, kind, wall, wall_s, n_walls, openings, opening_wall,
                    opening_panel, boxes, semantic, instance, material, normal, colour, texture, scale, emissive,
                    lights, rotation, shadow)
    P = hit.shape[0]
    return (point.new_empty(3, P), box_id.new_empty(P), box_id.new_empty(P), point.new_empty(3, P))


def check_arguments(point, direction, hit, box_id, kind, wall, wall_s, n_walls, openings, opening_wall,
                    opening_panel, boxes, semantic, instance, material, normal, colour, texture, scale, emissive,
                    lights, rotation, shadow) -> None:
    """Raise a ``ValueError`` naming the operand whose shape, dtype or device does not fit the others."""
    P, K, B, M, L = hit.shape[0] if hit.dim() == 1 else -1, len(openings), len(boxes), len(colour), len(lights)
    S = n_walls + 2 + K + B
    dtype = point.dtype
    if not dtype.is_floating_point:
        raise ValueError(f"surface_shade: point must be a floating-point tensor, got {dtype}")
    i64, b8 = torch.int64, torch.bool
    for name, t, want, shape in (
            ("point", point, dtype, (3, P)), ("direction", direction, dtype, (3, P)), ("hit", hit, b8, (P,)),
            ("box_id", box_id, i64, (P,)), ("kind", kind, i64, (P,)), ("wall", wall, i64, (P,)),
            ("wall_s", wall_s, dtype, (P,)), ("openings", openings, dtype, (K, 6)),
            ("opening_wall", opening_wall, i64, (K,)), ("opening_panel", opening_panel, b8, (K,)),
            ("boxes", boxes, dtype, (B, 8)), ("semantic", semantic, i64, (S,)), ("instance", instance, i64, (S,)),
            ("material", material, i64, (S,)), ("normal", normal, dtype, (n_walls + 2 + K, 3)),
            ("colour", colour, dtype, (M, 6)), ("texture", texture, i64, (M,)), ("scale", scale, dtype, (M,)),
            ("emissive", emissive, b8, (M,)), ("lights", lights, dtype, (L, 4)), ("rotation", rotation, dtype, (3, 3)),
            ("shadow", shadow, dtype, (L, P))):
        if t is None:
            continue
        if t.dtype != want or tuple(t.shape) != shape or t.device != point.device:
            raise ValueError(f"surface_shade: {name} must be a {want} tensor of shape {shape} on {point.device} "
                             f"(point's dtype and device), got {t.dtype} on {t.device} with shape {tuple(t.shape)}")


def _check_material(material: Tensor, M: int) -> None:
    if material.numel() and not (0 <= int(material.min()) and int(material.max()) < M):
        raise ValueError(f"surface_shade: material holds an index outside [0, {M}) (the colour table's rows)")


def _index_error(n_boxes: int, n_walls: int) -> ValueError:
    return ValueError(f"surface_shade: box_id holds a box index of {n_boxes} or more, or a wall pixel without a box "
                      f"has a wall outside [0, {n_walls})")


# ---- the PyTorch implementation (any device, any floating dtype) -------------------------------------------------

def _hash(i: Tensor, j: Tensor) -> Tensor:
    """Deterministic pseudo-random value in ``[0, 1)`` per integer lattice cell (int64 tensors)."""
    h = (i * 73856093) ^ (j * 19349663)
    h = (h ^ (h >> 13)) * 1274126177
    return torch.remainder(h, 1021).to(torch.float32) / 1021.0


def _hash_table(i: Tensor, j: Tensor) -> Tensor:
    """:func:`_hash` of many points through a table over the box of their ``(i, j)`` cells when that box is
    small (textures repeat few cells over many pixels): the same values, a gather instead of 9 int64 ops."""
    if i.numel() < 4096:
        return _hash(i, j)
    i0, i1, j0, j1 = int(i.min()), int(i.max()), int(j.min()), int(j.max())
    ni, nj = i1 - i0 + 1, j1 - j0 + 1
    if ni * nj > i.numel() // 8:
        return _hash(i, j)
    ci = torch.arange(i0, i1 + 1, device=i.device)[:, None].expand(ni, nj).reshape(-1)
    cj = torch.arange(j0, j1 + 1, device=i.device)[None].expand(ni, nj).reshape(-1)
    return _hash(ci, cj).index_select(0, (i - i0) * nj + (j - j0))


def texture_mix(texture: Tensor, scale: Tensor, su: Tensor, sv: Tensor, kinds: list[int] | None = None) -> Tensor:
    """Blend weight in ``[0, 1]`` between colour1 (0) and colour2 (1) per point.

    ``texture``, ``scale``: per point material fields ``(P,)``; ``su``, ``sv``: surface coordinates
    in metres (horizontal along the surface, and vertical / second axis; ``[0, 1]`` box coordinates
    for ``PANEL``). Each texture kind is evaluated only on its own points (``kinds``: those present, when known).
    """
    w = torch.zeros_like(su)
    for kind in (torch.unique(texture).tolist() if kinds is None else kinds):
        if kind == PLAIN:
            continue
        idx = (texture == kind).nonzero()[:, 0]
        u, v, s = su.index_select(0, idx), sv.index_select(0, idx), scale.index_select(0, idx).clamp_min(1e-3)
        if kind == PANEL:
            val = ((u < 0.08) | (u > 0.92) | (v < 0.06) | (v > 0.94) | ((v > 0.48) & (v < 0.52))).to(su.dtype)
        else:
            iu = torch.floor(u / s).to(torch.int64)
            iv = torch.floor(v / s).to(torch.int64)
            if kind == STRIPES:
                val = torch.remainder(iu, 2).to(su.dtype)
            elif kind == CHECKER:
                val = torch.remainder(iu + iv, 2).to(su.dtype)
            elif kind == NOISE:
                val = _hash_table(iu, iv).to(su.dtype)
            else:  # PLANKS: rows of staggered planks 4 x scale long with dark seams
                off = _hash_table(iv, iv + 7).to(su.dtype) * 4 * s
                x = (u + off) / (4 * s)
                col = torch.floor(x)
                seam = (v / s - iv.to(su.dtype) < 0.05) | (x - col < 0.012)
                val = 0.6 * _hash_table(iv, col.to(torch.int64)).to(su.dtype)
                val = torch.where(seam, torch.ones_like(val), val)
        w.index_copy_(0, idx, val)
    return w


def box_faces(points: Tensor, boxes: Tensor, box_id: Tensor) -> tuple[Tensor, Tensor]:
    """Outward world normals ``(K, 3)`` of box hits and their face coordinates ``(K, 2)``: ``points (K, 3)`` on
    the boxes ``box_id (K,)`` (rows of the ``(B, 8)`` table of :class:`SurfaceTables`)."""
    b = boxes.index_select(0, box_id)
    c, s = b[:, 6], b[:, 7]
    px, py = points[:, 0] - b[:, 0], points[:, 1] - b[:, 1]
    local = torch.stack([c * px + s * py, -s * px + c * py, points[:, 2] - b[:, 2]], -1)
    ratio = local.abs() / b[:, 3:6].clamp_min(1e-9)
    axis = ratio.argmax(-1)
    sign = torch.sign(local.gather(1, axis[:, None])[:, 0])
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    n_local = torch.zeros_like(local)
    n_local.scatter_(1, axis[:, None], sign[:, None])
    normal = torch.stack([c * n_local[:, 0] - s * n_local[:, 1], s * n_local[:, 0] + c * n_local[:, 1],
                          n_local[:, 2]], -1)
    # texture coordinates on the face: the two local axes other than the normal axis
    uv = torch.where((axis == 2)[:, None], local[:, :2],
                     torch.where((axis == 0)[:, None], local[:, 1:], local[:, 0::2]))
    return normal, uv


def torch_surface_shade(point: Tensor, direction: Tensor, hit: Tensor, box_id: Tensor, kind: Tensor, wall: Tensor,
                        wall_s: Tensor, n_walls: int, openings: Tensor, opening_wall: Tensor, opening_panel: Tensor,
                        boxes: Tensor, semantic: Tensor, instance: Tensor, material: Tensor, normal: Tensor,
                        colour: Tensor, texture: Tensor, scale: Tensor, emissive: Tensor, lights: Tensor,
                        ambient: float, rotation: Tensor, shadow: Tensor | None = None
                        ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The op in PyTorch operations over whole images (any device, any floating dtype)."""
    check_arguments(point, direction, hit, box_id, kind, wall, wall_s, n_walls, openings, opening_wall,
                    opening_panel, boxes, semantic, instance, material, normal, colour, texture, scale, emissive,
                    lights, rotation, shadow)
    n, n_dec, n_boxes = n_walls, len(openings), len(boxes)
    _check_material(material, len(colour))
    is_box = box_id >= 0
    is_wall = kind == WALL
    on_wall = is_wall & ~is_box
    if bool((box_id >= n_boxes).any() | (on_wall & ((wall < 0) | (wall >= n))).any()):
        raise _index_error(n_boxes, n)
    # surface id per pixel
    surf = torch.where(is_wall, wall, torch.where(kind == FLOOR, n, n + 1))
    tex_u = torch.where(is_wall, wall_s, point[0])
    tex_v = torch.where(is_wall, point[2], point[1])
    if n_dec:
        widx = on_wall.nonzero()[:, 0]
        # index_select / index_copy_: the same gathers and scatters as x[idx], several times faster
        w_wall, w_s, w_z = wall.index_select(0, widx), wall_s.index_select(0, widx), point[2].index_select(0, widx)
        w_surf = surf.index_select(0, widx)
        w_u, w_v = tex_u.index_select(0, widx), tex_v.index_select(0, widx)
        for k, (wl, (s0, s1, z0, z1, ds, dz), panel) in enumerate(zip(opening_wall.tolist(), openings.tolist(),
                                                                         opening_panel.tolist())):
            m = (w_wall == wl) & (w_s >= s0) & (w_s <= s1) & (w_z >= z0) & (w_z <= z1)
            w_surf = torch.where(m, n + 2 + k, w_surf)
            if panel:
                w_u = torch.where(m, (w_s - s0) / ds, w_u)
                w_v = torch.where(m, (w_z - z0) / dz, w_v)
        surf.index_copy_(0, widx, w_surf)
        tex_u.index_copy_(0, widx, w_u)
        tex_v.index_copy_(0, widx, w_v)
    nrm = normal.T.index_select(1, surf)                                       # (3, P)
    bidx = is_box.nonzero()[:, 0]
    if bidx.numel():
        bi = box_id.index_select(0, bidx)
        nb, uvb = box_faces(point.index_select(1, bidx).T, boxes, bi)
        nrm.index_copy_(1, bidx, nb.T)
        surf.index_copy_(0, bidx, n + 2 + n_dec + bi)
        tex_u.index_copy_(0, bidx, uvb[:, 0])
        tex_v.index_copy_(0, bidx, uvb[:, 1])
    sem, inst = semantic.index_select(0, surf), instance.index_select(0, surf)
    # normals face the ray
    flip = nrm[0] * direction[0] + nrm[1] * direction[1] + nrm[2] * direction[2] > 0
    nrm = torch.where(flip[None], -nrm, nrm)
    nrm = nrm * hit[None]
    image = _shade(material, surf, tex_u, tex_v, point, nrm, hit, colour, texture, scale, emissive, lights, ambient,
                   shadow)
    return image, sem * hit, inst * hit, rotation.T @ nrm


def _shade(mat_t: Tensor, surf: Tensor, tu: Tensor, tv: Tensor, point: Tensor, normal: Tensor, hit: Tensor,
           colour: Tensor, texture: Tensor, scale: Tensor, emissive: Tensor, lights: Tensor, ambient: float,
           shadow: Tensor | None) -> Tensor:
    """Lambertian shading ``(3, P)``: albedo (procedural texture) x (ambient + point lights).

    ``mat_t (S,)``: material per surface, ``surf (P,)``: surface per pixel; ``point``, ``normal``: ``(3, P)``.
    The material fields are looked up per surface first, then gathered per pixel once.
    """
    c12 = colour.T.index_select(1, mat_t).index_select(1, surf)                 # (6, P)
    c1, c2 = c12[:3], c12[3:]
    kinds = sorted(set(texture.tolist()))
    tex = texture[mat_t].index_select(0, surf)
    sc = scale[mat_t].index_select(0, surf)
    w = texture_mix(tex, sc, tu, tv, kinds)[None]
    albedo = c1 * (1 - w) + c2 * w
    everything = bool(hit.all())
    hits = slice(None) if everything else hit.nonzero()[:, 0]
    p, n = point[:, hits], normal[:, hits]
    lp, power = lights[:, :3], lights[:, 3]
    # all lights at once: n.(l - p) and |l - p|^2 from (L, P) products
    n_dot_l = lp @ n - (n[0] * p[0] + n[1] * p[1] + n[2] * p[2])[None]
    dist2 = ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2])[None] - lp @ (2 * p) + (lp * lp).sum(-1)[:, None])
    dist2 = dist2.clamp_min(1e-12)
    lam = (n_dot_l * dist2.rsqrt()).clamp_min(0.0)
    contrib = power[:, None] * lam / (1.0 + 0.25 * dist2)                       # (L, P)
    if shadow is not None:
        contrib = contrib * shadow[:, hits]
    light = ambient + contrib.sum(0)
    light = 1.25 * light / (1.0 + 0.25 * light)      # soft highlight roll-off
    em = emissive[mat_t].index_select(0, surf if everything else surf[hits])
    a = albedo[:, hits]
    shaded = torch.where(em[None], a, a * light[None]).clamp_(0.0, 1.0)
    if everything:
        return shaded
    out = torch.zeros_like(albedo)
    out[:, hits] = shaded
    return out


# ---- CPU: the native kernel --------------------------------------------------------------------------------------

@surface_shade.register_kernel("cpu")
def _surface_shade_cpu(point, direction, hit, box_id, kind, wall, wall_s, n_walls, openings, opening_wall,
                       opening_panel, boxes, semantic, instance, material, normal, colour, texture, scale, emissive,
                       lights, ambient, rotation, shadow=None):
    args = (point, direction, hit, box_id, kind, wall, wall_s, n_walls, openings, opening_wall, opening_panel, boxes,
            semantic, instance, material, normal, colour, texture, scale, emissive, lights, ambient, rotation, shadow)
    if point.dtype != torch.float32 or native_library() is None:
        return torch_surface_shade(*args)
    check_arguments(*args[:21], rotation, shadow)
    _check_material(material, len(colour))
    c = [t.contiguous() for t in (point, direction, hit, box_id, kind, wall, wall_s)]
    tables = [t.contiguous() for t in (opening_wall, openings, opening_panel, boxes)]
    surfaces = [t.contiguous() for t in (semantic, instance, material, normal, colour, texture, scale, emissive)]
    lt, rot = lights.contiguous(), rotation.contiguous()
    sh = None if shadow is None else shadow.contiguous()
    P = hit.shape[0]
    image = torch.empty(3, P, dtype=point.dtype)
    sem = torch.empty(P, dtype=torch.int64)
    inst = torch.empty(P, dtype=torch.int64)
    normal_cam = torch.empty(3, P, dtype=point.dtype)
    status = native_library().omnidl_surface_shade(
        P, *(t.data_ptr() for t in c), n_walls, len(openings), *(t.data_ptr() for t in tables[:3]),
        tables[3].data_ptr(), len(boxes), *(t.data_ptr() for t in surfaces), len(lights), lt.data_ptr(),
        _native.pointer(sh), float(ambient), rot.data_ptr(), image.data_ptr(), sem.data_ptr(), inst.data_ptr(),
        normal_cam.data_ptr(), max(1, torch.get_num_threads()))
    if status:
        raise _index_error(len(boxes), n_walls)
    return image, sem, inst, normal_cam
