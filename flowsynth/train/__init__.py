"""What ``flowsynth tune``, the learning benchmark and the examples train with (torch only; torchvision on demand):
RAFT's recipe (``steps``: loss, augmentation, the training step), K nets trained at once (``ensemble``) and RAFT-small
(``nets``). Each module is exported by name: ``from flowsynth.train.steps import train_step``."""

from flowsynth.train import ensemble, nets, steps

__all__ = ["ensemble", "nets", "steps"]
