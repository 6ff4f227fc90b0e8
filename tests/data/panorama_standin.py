"""A closed-form equirectangular panorama (stand-in for the synthetic engine in fast tests).

depth(d) = 2 + d_x + 0.5 d_y (metres, d = unit ray in the panorama's camera frame), 0 (invalid) on the
cap above latitude 75°; semantic = 1 + octant of d (classes 1..8); RGB a smooth function of d.
"""
import math

import torch

from omnidl.cameras.equirectangular import Equirectangular

CAP_LAT = math.radians(75)


def depth_of(d: torch.Tensor) -> torch.Tensor:
    return 2 + d[..., 0] + 0.5 * d[..., 1]


def label_of(d: torch.Tensor) -> torch.Tensor:
    return 1 + (d[..., 0] > 0).long() + 2 * (d[..., 1] > 0).long() + 4 * (d[..., 2] > 0).long()


def lat_of(d: torch.Tensor) -> torch.Tensor:
    return torch.asin((-d[..., 1]).clamp(-1, 1))


def make_panorama(width: int = 128, height: int = 64) -> dict:
    cam = Equirectangular(width=width, height=height)
    d = cam.unproject_grid(dtype=torch.float64).direction
    cap = lat_of(d) > CAP_LAT
    depth = torch.where(cap, torch.zeros_like(d[..., 0]), depth_of(d))
    image = torch.stack([0.5 + 0.5 * d[..., 0], 0.5 + 0.5 * d[..., 1], 0.5 + 0.5 * d[..., 2]], 0)
    return {"image": image.float(), "depth": depth[None].float(), "semantic": torch.where(cap, 0, label_of(d)),
            "meta": {"name": "standin"}}


class StandInPanoramas:
    def __init__(self, n: int = 2, width: int = 128, height: int = 64):
        self.pano = make_panorama(width, height)
        self.n = n

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        if not 0 <= i < self.n:
            raise IndexError(i)
        return self.pano
