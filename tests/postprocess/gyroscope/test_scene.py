import torch

from omnidl.cameras.equirectangular import Equirectangular
from omnidl.geometry.panorama import sample_panorama
from omnidl.geometry.rotations import euler_to_matrix
from omnidl.postprocess.gyroscope.scene import procedural_panorama


def test_procedural_scene_renders_exact_rotations():
    R = euler_to_matrix(torch.tensor(0.3, dtype=torch.float64), torch.tensor(0.2, dtype=torch.float64),
                        torch.tensor(-0.7, dtype=torch.float64))
    hi = procedural_panorama(None, 256, 512, seed=1, dtype=torch.float64)
    rendered = procedural_panorama(R, 32, 64, seed=1, dtype=torch.float64)
    d = Equirectangular(width=64, height=32).unproject_grid(torch.float64).direction
    resampled = sample_panorama(hi, torch.einsum("ij,hwj->hwi", R, d).reshape(-1, 3)).reshape(1, 3, 32, 64)
    assert (rendered - resampled).abs().mean() < 2e-3
