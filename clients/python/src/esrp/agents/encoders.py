"""Image encoders of the learning baselines (ESRP-BC, ESRP-PPO), trained from scratch: no pretrained
weights can be downloaded here (the paper's are ImageNet-pretrained ResNet-50s).

- `nature`: the DQN/PPO Atari network (8×8/4, 4×4/2 and 3×3/1 convolutions, 32-64-64 channels, a
  linear layer), what CleanRL's PPO uses; the cheapest per image.
- `cnn`: four strided 3×3 convolutions (32-64-128-128) with GroupNorm, global average pooling.
- `resnet18`: ResNet-18's layout with GroupNorm (as Diffusion Policy's encoders), no torchvision.

Every encoder takes float images (B, 3, R, R) in [-1, 1] (`float_images`) and returns (B, out).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F  # noqa: N812 - the usual name

__all__ = ["ENCODERS", "check_device", "float_images", "make_encoder", "resolve_device"]

ENCODERS = ("cnn", "nature", "resnet18")


def float_images(rgb: torch.Tensor) -> torch.Tensor:
    """uint8 (B, R, R, 3) → float (B, 3, R, R) in [-1, 1]."""
    return rgb.permute(0, 3, 1, 2).float() / 127.5 - 1.0


class NatureCnn(nn.Module):
    """The Nature-DQN convolutions (CleanRL's PPO encoder) for (B, 3, R, R) images, R ≥ 36."""

    def __init__(self, out: int, resolution: int) -> None:
        super().__init__()
        side = ((resolution - 8) // 4 + 1 - 4) // 2 + 1 - 2
        if side < 1:
            raise ValueError(f"the nature encoder needs images of at least 36 pixels, got {resolution}")
        self.body = nn.Sequential(
            nn.Conv2d(3, 32, 8, stride=4),
            nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2),
            nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        self.head = nn.Linear(64 * side * side, out)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = F.relu(self.head(self.body(images)))
        return out


class SmallCnn(nn.Module):
    """Four strided 3×3 convolutions (32-64-128-128 channels), global average pooling, a linear layer."""

    def __init__(self, out: int) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        channels = 3
        for width in (32, 64, 128, 128):
            layers += [nn.Conv2d(channels, width, 3, stride=2, padding=1), nn.GroupNorm(8, width), nn.ReLU()]
            channels = width
        self.body = nn.Sequential(*layers)
        self.head = nn.Linear(channels, out)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.head(self.body(images).mean(dim=(2, 3)))
        return out


class _Basic(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)
        self.norm1 = nn.GroupNorm(8, cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1, bias=False)
        self.norm2 = nn.GroupNorm(8, cout)
        self.skip: nn.Module = (
            nn.Identity()
            if stride == 1 and cin == cout
            else nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride, bias=False), nn.GroupNorm(8, cout))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.relu(self.norm1(self.conv1(x)))
        return F.relu(self.norm2(self.conv2(y)) + self.skip(x))


class ResNet18(nn.Module):
    """ResNet-18's layout (GroupNorm instead of BatchNorm, as Diffusion Policy does), from scratch."""

    def __init__(self, out: int) -> None:
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(3, 64, 7, stride=2, padding=3, bias=False),
            nn.GroupNorm(8, 64),
            nn.ReLU(),
            nn.MaxPool2d(3, 2, 1),
        )
        blocks: list[nn.Module] = []
        cin = 64
        for cout, stride in ((64, 1), (128, 2), (256, 2), (512, 2)):
            blocks += [_Basic(cin, cout, stride), _Basic(cout, cout, 1)]
            cin = cout
        self.blocks = nn.Sequential(*blocks)
        self.head = nn.Linear(512, out)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        out: torch.Tensor = self.head(self.blocks(self.stem(images)).mean(dim=(2, 3)))
        return out


def make_encoder(kind: str, out: int, resolution: int = 128) -> nn.Module:
    """The encoder `kind` (one of `ENCODERS`) with `out` features, for images of `resolution` pixels."""
    if kind == "resnet18":
        return ResNet18(out)
    if kind == "nature":
        return NatureCnn(out, resolution)
    if kind == "cnn":
        return SmallCnn(out)
    raise ValueError(f"encoder {kind!r}: one of {', '.join(ENCODERS)}")


def check_device(setting: str) -> None:
    """Raises `ValueError` unless `setting` names a training device: auto, cpu, cuda or cuda:N."""
    if setting not in ("auto", "cpu", "cuda") and not (setting.startswith("cuda:") and setting[5:].isdigit()):
        raise ValueError(f"device {setting!r}: auto, cpu, cuda or cuda:N")


def resolve_device(setting: str) -> torch.device:
    """The torch device of a config's `device`: `auto` is CUDA when torch sees a GPU, else the CPU."""
    check_device(setting)
    if setting == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if setting.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {setting!r}: torch sees no CUDA device here")
    return torch.device(setting)
