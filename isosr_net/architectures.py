"""Network parts: the residual block SRNet and ReconNet share, and the architectures the
losses use: VGG-19 features (the perceptual loss) and the spatio-temporal patch discriminator
(the adversarial loss). SRNet itself is in :mod:`isosr_net.model`, ReconNet in
:mod:`isosr_net.reconnet`.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from safetensors.torch import load_file
from torch import nn

from isosr_render.conventions import HIGHRES_CHANNELS, LOWRES_CHANNELS
from isosr_render.shapes import check_shape

class ResidualBlock(nn.Module):
    """conv-ReLU-conv plus the input (3x3 convolutions, the channel count kept)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(x)))


# VGG-19 "features" as torchvision numbers it: conv (+ ReLU) per int, max-pool per "M".
_VGG19_CFG: tuple[int | str, ...] = (64, 64, "M", 128, 128, "M", 256, 256, 256, 256, "M",
                                     512, 512, 512, 512, "M", 512, 512, 512, 512, "M")
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def _vgg19_layer_index() -> dict[str, int]:
    """``"relu{block}_{conv}"`` -> index of that ReLU in the features ``nn.Sequential``."""
    names, index, block, conv = {}, 0, 1, 0
    for item in _VGG19_CFG:
        if item == "M":
            block, conv, index = block + 1, 0, index + 1
        else:
            conv += 1
            names[f"relu{block}_{conv}"] = index + 1
            index += 2
    return names


VGG19_LAYERS = _vgg19_layer_index()


def vgg19_features() -> nn.Sequential:
    """VGG-19's convolutional part, indexed like torchvision's ``vgg19().features``."""
    layers: list[nn.Module] = []
    channels = 3
    for item in _VGG19_CFG:
        if item == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(channels, int(item), kernel_size=3, padding=1), nn.ReLU(inplace=True)]
            channels = int(item)
    return nn.Sequential(*layers)


def load_vgg19_features(path: str | Path) -> nn.Sequential:
    """VGG-19 features with weights from ``path``, frozen and in eval mode.

    The file holds a state dict (``.safetensors``, or ``.pt`` / ``.pth`` saved with
    ``torch.save``), either of the features alone or of a whole torchvision ``vgg19`` (its
    ``features.`` keys are used, the classifier is ignored).

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: keys missing, unexpected or of the wrong shape.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"VGG-19 weights not found at '{path}'. The perceptual loss needs ImageNet-trained "
            "VGG-19 weights: save torchvision's vgg19(weights='IMAGENET1K_V1').state_dict() "
            f"(or its .features part) as .safetensors or .pt at '{path}', or point the loss's "
            "weights_path at such a file.")
    if path.suffix == ".safetensors":
        state = load_file(str(path))
    else:
        state = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ValueError(f"VGG-19 weights '{path}': expected a state dict of tensors")
    if any(k.startswith("features.") for k in state):
        state = {k.removeprefix("features."): v for k, v in state.items() if k.startswith("features.")}
    model = vgg19_features()
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    mismatched = sorted(f"{k} {tuple(state[k].shape)} != {tuple(expected[k].shape)}"
                        for k in set(expected) & set(state) if state[k].shape != expected[k].shape)
    if missing or unexpected or mismatched:
        raise ValueError(f"VGG-19 weights '{path}' do not fit VGG-19 features: missing keys {missing}, "
                         f"unexpected keys {unexpected}, shape mismatches {mismatched}")
    model.load_state_dict(state)
    return model.requires_grad_(False).eval()


class SpatioTemporalDiscriminator(nn.Module):
    """Small patch discriminator on [frame, previous frame warped, low-res condition].

    Spectrally normalized convolutions with LeakyReLU, three of them with stride 2.

    Args:
        in_channels: input channels, 6 + 6 + 5 = 17 by default.
        base: channels of the first layer; deeper layers use 2x and 4x.

    Shape:
        Input (B, in_channels, H, W). Output (B, 1, H/8, W/8) logits (H, W divisible by 8).
    """

    def __init__(self, in_channels: int = 2 * len(HIGHRES_CHANNELS) + len(LOWRES_CHANNELS),
                 base: int = 32) -> None:
        super().__init__()
        if in_channels < 1 or base < 1:
            raise ValueError(f"in_channels and base must be >= 1, got {in_channels} and {base}")
        sn = nn.utils.parametrizations.spectral_norm
        widths = (base, 2 * base, 4 * base, 4 * base)
        layers: list[nn.Module] = [sn(nn.Conv2d(in_channels, base, 3, padding=1)), nn.LeakyReLU(0.2)]
        for c_in, c_out in zip(widths[:-1], widths[1:]):
            layers += [sn(nn.Conv2d(c_in, c_out, 4, stride=2, padding=1)), nn.LeakyReLU(0.2)]
        layers.append(sn(nn.Conv2d(widths[-1], 1, 3, padding=1)))
        self.net = nn.Sequential(*layers)
        self.in_channels = in_channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_shape(x, f"(B, {self.in_channels}, H, W)", "input", "SpatioTemporalDiscriminator")
        return self.net(x)
