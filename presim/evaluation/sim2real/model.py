"""A small DenseDepth-style encoder-decoder and its loss (thesis §4.5 uses DenseDepth).

Encoder: the ResNet-18 topology (7x7 stride-2 stem, max-pool, four stages of two BasicBlocks with
stride 1, 2, 2, 2) at channel width ``width`` (64 = ResNet-18's 64-128-256-512; the CPU default 32
halves every stage), randomly initialised (no pretrained weights can be downloaded here).
Decoder (DenseDepth): 1x1 conv of the bottleneck to half its channels, then four up-sampling blocks
(bilinear x2, concatenate the encoder skip, two 3x3 conv + LeakyReLU(0.2)), a 3x3 conv to one channel
at 1/2 resolution, bilinear up-sampling to the input size. Output depth = ``max_depth_m * sigmoid``.

Loss (DenseDepth's three terms, masked because labels have holes):
``L = w_l1 * mean|y^ - y| + w_grad * mean|grad y^ - grad y| + w_ssim * (1 - SSIM(y^, y')) / 2``
over valid label pixels (gradients: finite differences where both pixels are valid; SSIM: 3x3
mean-filter SSIM on the depth with label holes replaced by the detached prediction, so holes add no
signal). Depth in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["DepthLossConfig", "DepthNet", "depth_loss"]


class _BasicBlock(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.c1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.b1 = nn.BatchNorm2d(cout)
        self.c2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.b2 = nn.BatchNorm2d(cout)
        self.down = None
        if stride != 1 or cin != cout:
            self.down = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))

    def forward(self, x):
        y = F.relu(self.b1(self.c1(x)))
        y = self.b2(self.c2(y))
        return F.relu(y + (x if self.down is None else self.down(x)))


class _Up(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.a = nn.Conv2d(cin, cout, 3, 1, 1)
        self.b = nn.Conv2d(cout, cout, 3, 1, 1)

    def forward(self, x, skip):
        x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        x = F.leaky_relu(self.a(torch.cat([x, skip], 1)), 0.2)
        return F.leaky_relu(self.b(x), 0.2)


class DepthNet(nn.Module):
    """RGB (B, 3, H, W) in [0, 1] -> depth (B, 1, H, W) in metres, in (0, max_depth_m)."""

    def __init__(self, width: int = 32, max_depth_m: float = 10.0):
        super().__init__()
        w = width
        self.max_depth_m = max_depth_m
        self.stem = nn.Sequential(nn.Conv2d(3, w, 7, 2, 3, bias=False), nn.BatchNorm2d(w), nn.ReLU(inplace=True))
        self.pool = nn.MaxPool2d(3, 2, 1)
        chans = [w, w, 2 * w, 4 * w, 8 * w]
        self.stages = nn.ModuleList(
            nn.Sequential(_BasicBlock(chans[i], chans[i + 1], 1 if i == 0 else 2),
                          _BasicBlock(chans[i + 1], chans[i + 1], 1)) for i in range(4))
        f = 4 * w  # DenseDepth: decoder starts at half the bottleneck channels
        self.mid = nn.Conv2d(8 * w, f, 1)
        self.up = nn.ModuleList([_Up(f + 4 * w, f // 2), _Up(f // 2 + 2 * w, f // 4),
                                 _Up(f // 4 + w, f // 8), _Up(f // 8 + w, f // 16)])
        self.head = nn.Conv2d(f // 16, 1, 3, 1, 1)
        for m in [self.stem, self.stages]:
            for c in m.modules():
                if isinstance(c, nn.Conv2d):
                    nn.init.kaiming_normal_(c.weight, mode="fan_out", nonlinearity="relu")
        # Start near 2 m everywhere with a small spread: a saturated sigmoid would learn nothing.
        nn.init.normal_(self.head.weight, std=1e-3)
        nn.init.constant_(self.head.bias, float(torch.logit(torch.tensor(2.0 / max_depth_m))))

    def forward(self, rgb: torch.Tensor) -> torch.Tensor:
        x0 = self.stem(rgb - 0.5)             # 1/2
        skips = [x0]
        x = self.pool(x0)                      # 1/4
        for s in self.stages:
            x = s(x)
            skips.append(x)                    # 1/4, 1/8, 1/16, 1/32
        x = self.mid(x)
        for up, skip in zip(self.up, [skips[3], skips[2], skips[1], skips[0]]):
            x = up(x, skip)
        x = F.interpolate(self.head(x), size=rgb.shape[-2:], mode="bilinear", align_corners=False)
        return self.max_depth_m * torch.sigmoid(x)


@dataclass(frozen=True)
class DepthLossConfig:
    """Weights of the masked DenseDepth loss."""

    w_l1: float = 1.0
    """Weight of the point-wise L1 term (metres)."""
    w_grad: float = 1.0
    """Weight of the L1 term on x/y finite differences of depth."""
    w_ssim: float = 1.0
    """Weight of (1 - SSIM) / 2."""
    ssim_range_m: float = 10.0
    """Dynamic range L of SSIM's constants C1 = (0.01 L)^2, C2 = (0.03 L)^2."""


def _ssim(x: torch.Tensor, y: torch.Tensor, L: float) -> torch.Tensor:
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    mx, my = F.avg_pool2d(x, 3, 1, 1), F.avg_pool2d(y, 3, 1, 1)
    sxx = F.avg_pool2d(x * x, 3, 1, 1) - mx * mx
    syy = F.avg_pool2d(y * y, 3, 1, 1) - my * my
    sxy = F.avg_pool2d(x * y, 3, 1, 1) - mx * my
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


def depth_loss(pred: torch.Tensor, gt: torch.Tensor, cfg: DepthLossConfig = DepthLossConfig()) -> torch.Tensor:
    """Masked L1 + gradient + SSIM loss of ``pred`` against ``gt`` (both (B, 1, H, W), metres; gt 0 =
    no label). A batch without any label gives 0 (with a gradient path)."""
    m = gt > 0
    mf = m.float()
    n = mf.sum().clamp(min=1.0)
    l1 = ((pred - gt).abs() * mf).sum() / n
    mx = mf[..., :, 1:] * mf[..., :, :-1]
    my = mf[..., 1:, :] * mf[..., :-1, :]
    gx = ((pred[..., :, 1:] - pred[..., :, :-1]) - (gt[..., :, 1:] - gt[..., :, :-1])).abs()
    gy = ((pred[..., 1:, :] - pred[..., :-1, :]) - (gt[..., 1:, :] - gt[..., :-1, :])).abs()
    grad = (gx * mx).sum() / mx.sum().clamp(min=1.0) + (gy * my).sum() / my.sum().clamp(min=1.0)
    filled = torch.where(m, gt, pred.detach())
    ssim = ((1 - _ssim(pred, filled, cfg.ssim_range_m)) / 2).clamp(0, 1)
    ssim = (ssim * mf).sum() / n
    return cfg.w_l1 * l1 + cfg.w_grad * grad + cfg.w_ssim * ssim
