"""``alexnet()``: torchvision's AlexNet feature layers (``features``), loaded from the file
named by ``$LPIPS_TEST_BACKBONE`` (a torchvision-format state dict)."""

import os

import torch
from torch import nn


class _AlexNet(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2), nn.ReLU(inplace=True),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(64, 192, kernel_size=5, padding=2), nn.ReLU(inplace=True),
            nn.MaxPool2d(kernel_size=3, stride=2),
            nn.Conv2d(192, 384, kernel_size=3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(384, 256, kernel_size=3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(256, 256, kernel_size=3, padding=1), nn.ReLU(inplace=True),
            nn.MaxPool2d(kernel_size=3, stride=2),
        )


def alexnet(pretrained: bool = False, **_) -> _AlexNet:
    model = _AlexNet()
    state = torch.load(os.environ["LPIPS_TEST_BACKBONE"], weights_only=True)
    model.load_state_dict({k: v for k, v in state.items() if k.startswith("features.")})
    return model
