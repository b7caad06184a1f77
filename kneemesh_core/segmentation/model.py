"""The segmentation network: the paper's 2-D residual U-Net, sized for a CPU (PyTorch; training only).

Gibbons et al. 2022 (section 2.2) use a textbook 2-D encoder-decoder on sagittal
slices: batch norm, ReLU, strided-convolution downsampling, a residual
connection around each contractive block, four levels and a softmax.  This is
that network with one change for speed: the stem is itself a strided
convolution, so the four levels run at 1/2 to 1/16 of the slice, and a light
full-resolution head (the upsampled features beside the image) puts the
boundaries back on the native pixels.  Full-resolution levels dominate a
U-Net's cost; measured with onnxruntime on 2 cores the head costs a fifth of a
full-resolution level (``bench/segmentation.py``).
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


def _conv_bn_relu(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class ResidualBlock(nn.Module):
    """conv-BN-ReLU-conv-BN plus the input (1x1-projected where the width changes), then ReLU."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.body = nn.Sequential(_conv_bn_relu(cin, cout), nn.Conv2d(cout, cout, 3, 1, 1, bias=False), nn.BatchNorm2d(cout))
        self.skip = nn.Identity() if cin == cout else nn.Sequential(nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.relu(self.body(x) + self.skip(x))


class ResUNet2D(nn.Module):
    """Slices (N, 1, H, W) -> class logits (N, C, H, W); H and W multiples of 2 ** (levels + 1).

    ``widths``: channels of the four levels (1/2, 1/4, 1/8, 1/16 of the slice); ``head``: channels
    of the full-resolution head.
    """

    def __init__(self, n_classes: int, widths: tuple[int, ...] = (16, 32, 48, 64), head: int = 8):
        super().__init__()
        self.stem = _conv_bn_relu(1, widths[0], stride=2)
        self.enc = nn.ModuleList([ResidualBlock(widths[0], widths[0])])
        self.down = nn.ModuleList()
        for cin, cout in zip(widths[:-1], widths[1:]):
            self.down.append(_conv_bn_relu(cin, cout, stride=2))
            self.enc.append(ResidualBlock(cout, cout))
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        for cin, cout in zip(widths[:0:-1], widths[-2::-1]):
            self.up.append(nn.ConvTranspose2d(cin, cout, 2, stride=2))
            self.dec.append(ResidualBlock(2 * cout, cout))
        self.head_up = nn.ConvTranspose2d(widths[0], head, 2, stride=2)
        self.head = nn.Sequential(_conv_bn_relu(head + 1, head), nn.Conv2d(head, n_classes, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        h = self.enc[0](self.stem(x))
        for down, enc in zip(self.down, self.enc[1:]):
            skips.append(h)
            h = enc(down(h))
        for up, dec, skip in zip(self.up, self.dec, reversed(skips)):
            h = dec(torch.cat([up(h), skip], 1))
        return self.head(torch.cat([self.head_up(h), x], 1))
