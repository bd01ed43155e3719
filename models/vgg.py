"""VGG-16 feature distance for the optional perceptual term (its own layer definition).

Loads a local torchvision-format state dict (`features.N.weight` / `features.N.bias`, e.g. the
file torchvision caches as `vgg16-397923af.pth`); nothing is downloaded. Only the convolutions up
to relu3_3 are used, on focal-stack planes at half resolution (full VGG on every plane took 21 s
per step on the development machine).
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

# torchvision's VGG-16 "D" configuration up to relu3_3 (index = position in `features`).
_CFG = [64, 64, "M", 128, 128, "M", 256, 256, 256]
_TAPS = (3, 8, 15)  # relu1_2, relu2_2, relu3_3
_MEAN = (0.485, 0.456, 0.406)
_STD = (0.229, 0.224, 0.225)


class VGGFeatures(nn.Module):
    """VGG-16's convolutions up to relu3_3, frozen, with ImageNet's input normalisation."""

    def __init__(self) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        c = 3
        for v in _CFG:
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(c, int(v), 3, padding=1), nn.ReLU(inplace=False)]
                c = int(v)
        self.features = nn.Sequential(*layers)
        self.register_buffer("mean", torch.tensor(_MEAN)[None, :, None, None])
        self.register_buffer("std", torch.tensor(_STD)[None, :, None, None])
        self.requires_grad_(False)

    @staticmethod
    def from_file(path: str | Path) -> VGGFeatures:
        """The network with the weights of a local torchvision VGG-16 state dict, in eval mode;
        FileNotFoundError when absent, ValueError when it is not VGG-16's."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"VGG-16 weights {path} not found (nothing is downloaded)")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            raise ValueError(f"{path}: not a torch state dict ({exc})") from exc
        net = VGGFeatures()
        wanted = {k for k in net.state_dict() if k.startswith("features.")}
        missing = wanted - set(state)
        if missing:
            raise ValueError(f"{path}: not torchvision VGG-16 weights (missing {sorted(missing)})")
        net.load_state_dict({k: state[k] for k in wanted} | {"mean": net.mean, "std": net.std})
        return net.eval()

    def taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The relu1_2, relu2_2 and relu3_3 features of `[N, 3, H, W]` images."""
        x = (x - self.mean) / self.std
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _TAPS:
                out.append(x)
        return out

    def distance(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """Mean L1 feature distance of `[N, 3, H, W]` intensity images (at half resolution)."""
        p = F.avg_pool2d(pred, 2)
        t = F.avg_pool2d(target, 2)
        with torch.no_grad():
            ft = self.taps(t)
        return sum((a - b).abs().mean() for a, b in zip(self.taps(p), ft, strict=True)) / len(ft)
