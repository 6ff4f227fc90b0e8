"""Train a model: ``python train.py model=fredsnet [key=value ...]`` (see docs/engine.md).

A thin wrapper of ``omnidl train`` (:mod:`omnidl.apps.train`), kept for the README's commands: the same Hydra
app, configs (``omnidl/configs``, linked as ``configs/``) and ``outputs/<date>/<time>/`` run folders.
Under ``torchrun --nproc_per_node=N train.py ...`` every rank shares one Hydra run dir.
"""
import sys

from omnidl.apps.train import main

if __name__ == "__main__":
    sys.exit(main())
