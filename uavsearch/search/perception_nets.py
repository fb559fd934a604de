"""Backbones of perception kinds beside the paper's plain CNN: pure torch modules, no pooling or heads.

`perception.py` wraps each in a registered kind (cell pooling, classifier, person head, checkpoints), so a new
backbone needs a module here and a few lines there; nothing here imports the rest of the package.
"""

from __future__ import annotations

import torch
from torch import nn


class BasicBlock(nn.Module):
    """ResNet's basic block: two 3x3 conv + BatchNorm, the input added back (through a strided 1x1 conv + BatchNorm
    where the shape changes), ReLU. Residual paths keep small nets trainable from scratch at a few channels."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, 1, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.shortcut = None
        if stride != 1 or c_in != c_out:
            self.shortcut = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False), nn.BatchNorm2d(c_out))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = torch.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return torch.relu(y + (x if self.shortcut is None else self.shortcut(x)))


class ResidualTrunk(nn.Module):
    """A stem conv (out, kernel, stride) + BatchNorm + ReLU, then stages of basic blocks (channels, blocks, stride;
    the stride on a stage's first block). Returns every level's map: the stem's, then each stage's."""

    def __init__(self, stem: tuple[int, int, int], stages: tuple[tuple[int, int, int], ...]):
        super().__init__()
        c, k, s = stem
        self.stem = nn.Sequential(nn.Conv2d(3, c, k, s, padding=k // 2, bias=False), nn.BatchNorm2d(c),
                                  nn.ReLU(inplace=True))
        stages_: list[nn.Module] = []
        for c_out, blocks, stride in stages:
            stages_.append(nn.Sequential(*(BasicBlock(c if i == 0 else c_out, c_out, stride if i == 0 else 1)
                                           for i in range(max(1, blocks)))))
            c = c_out
        self.stages = nn.ModuleList(stages_)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        levels = [self.stem(x)]
        for stage in self.stages:
            levels.append(stage(levels[-1]))
        return levels


__all__ = ["BasicBlock", "ResidualTrunk"]
