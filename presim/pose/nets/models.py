"""Pose networks in plain torch (thesis §6.3.3, §6.4): DenseFusion, C/G-AF and C/G-AF without attention.

All three share the colour branch (:class:`ColorEmbedding`: a ResNet-18-layout encoder — stem, four
stages of two basic blocks — and 4 up-sampling layers back to the crop, randomly initialised: no
pretrained weights are downloadable here) and the per-point heads (quaternion, translation offset
from the point, confidence; one output slot per object) and the iterative refiner
(:class:`PoseRefiner`, DenseFusion's: the points moved into the current object frame, a PointNet +
colour global feature, a pose update composed on the right).

- ``densefusion``: PointNet geometry (shared 1x1 convs), per-pixel fusion by concatenation at two
  depths plus a global average-pooled feature (DenseFusion's ``PoseNetFeat``).
- ``cgaf``: EdgeConv (DGCNN) on the points' k = 10 nearest-neighbour graph (MLP 3-64-64-64), local
  features plus a max-pooled global feature; nodes = [colour, local, global]; a 2-head graph attention
  layer (GAT) over the same kNN graph fuses them; per-node pose and confidence.
- ``cgaf-noatt``: the same with the GAT replaced by a per-node layer of the same width (no neighbour
  attention) — the Table 6.7 ablation.

Why plain torch and not torch_geometric: the graphs are fixed-size kNN graphs of N points per
instance, so neighbour indices are a dense (B, N, k) tensor (``cdist`` + ``topk``) and EdgeConv/GAT
are a gather, a 1x1 conv and a max/softmax over the last axis — batched, deterministic, on CPU and
CUDA alike, and without an extra compiled dependency (torch_geometric and its scatter kernels are not
installed here). Normalisation is GroupNorm, not BatchNorm: batches are small and train/eval must
agree (the overfit test and resumed runs).

Example:
    >>> net = PoseNet(ModelConfig(arch="cgaf", n_objects=5))                     # doctest: +SKIP
    >>> out = net(rgb, points, choose, obj_idx); out.R.shape                     # doctest: +SKIP
    torch.Size([8, 256, 3, 3])
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from presim.pose.nets.loss import quat_to_R

__all__ = ["ARCHS", "ModelConfig", "PoseOut", "ColorEmbedding", "knn", "EdgeConv", "GraphAttention",
           "PoseNet", "PoseRefiner", "best_pose"]

ARCHS = ("densefusion", "cgaf", "cgaf-noatt")


@dataclass(frozen=True)
class ModelConfig:
    """Sizes of a pose network. Defaults are the CPU quick recipe; :meth:`full` is the paper size."""

    arch: str = "cgaf"
    """``densefusion`` | ``cgaf`` | ``cgaf-noatt``."""
    n_objects: int = 1
    """Output slots (objects of models_info.json)."""
    cnn_width: int = 16
    """Channels of the first ResNet-18 stage (ResNet-18: 64); stages are x1, x2, x4, x8."""
    emb_dim: int = 32
    """Per-pixel colour embedding (DenseFusion: 32)."""
    geo_dims: tuple[int, ...] = (64, 64, 64)
    """EdgeConv layer widths (thesis: 64-64-64); DenseFusion uses the first two as its PointNet widths."""
    global_dim: int = 256
    """Global feature width (DenseFusion: 1024)."""
    fuse_dim: int = 128
    """Node width after fusion (GAT output = ``fuse_dim``, split over the heads)."""
    head_dims: tuple[int, ...] = (128, 64)
    """Hidden widths of each per-point head (DenseFusion: 640, 256, 128)."""
    k: int = 10
    """Neighbours of the kNN graph (self included)."""
    gat_heads: int = 2
    """Attention heads."""
    refine_iters: int = 2
    """Refinement iterations at prediction time."""

    @staticmethod
    def full(arch: str, n_objects: int) -> "ModelConfig":
        """The published sizes (GPU recipe)."""
        return ModelConfig(arch=arch, n_objects=n_objects, cnn_width=64, emb_dim=32, geo_dims=(64, 64, 64),
                           global_dim=1024, fuse_dim=256, head_dims=(640, 256, 128))


@dataclass
class PoseOut:
    R: torch.Tensor
    """(B, N, 3, 3) per-point rotations model -> camera."""
    t: torch.Tensor
    """(B, N, 3) per-point translations, metres."""
    conf: torch.Tensor
    """(B, N) confidences in (0, 1)."""
    emb: torch.Tensor
    """(B, emb_dim, N) colour embedding at the points (the refiner reuses it)."""


def _norm2d(c: int) -> nn.Module:
    return nn.GroupNorm(8 if c % 8 == 0 else 1, c)


class _Block(nn.Module):
    """ResNet basic block (two 3x3 convs and a shortcut)."""

    def __init__(self, cin: int, cout: int, stride: int):
        super().__init__()
        self.c1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.n1 = _norm2d(cout)
        self.c2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.n2 = _norm2d(cout)
        self.short = (nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), _norm2d(cout))
                      if stride != 1 or cin != cout else nn.Identity())

    def forward(self, x):
        return F.relu(self.n2(self.c2(F.relu(self.n1(self.c1(x))))) + self.short(x))


class ColorEmbedding(nn.Module):
    """ResNet-18-layout encoder (/32) and 4 x2 up-sampling layers, then back to the crop size.

    (B, 3, S, S) -> (B, emb_dim, S, S); S must be a multiple of 32.
    """

    def __init__(self, width: int, emb_dim: int):
        super().__init__()
        w = width
        self.stem = nn.Sequential(nn.Conv2d(3, w, 7, 2, 3, bias=False), _norm2d(w), nn.ReLU(), nn.MaxPool2d(3, 2, 1))
        chans = [w, w, 2 * w, 4 * w, 8 * w]
        self.stages = nn.ModuleList(
            nn.Sequential(_Block(chans[i], chans[i + 1], 1 if i == 0 else 2), _Block(chans[i + 1], chans[i + 1], 1))
            for i in range(4))
        ups = [8 * w, 4 * w, 2 * w, w, w]
        self.ups = nn.ModuleList(
            nn.Sequential(nn.Conv2d(ups[i], ups[i + 1], 3, 1, 1, bias=False), _norm2d(ups[i + 1]), nn.ReLU())
            for i in range(4))
        self.out = nn.Conv2d(w, emb_dim, 1)

    def forward(self, x):
        S = x.shape[-1]
        if x.shape[-2] != S or S % 32:
            raise ValueError(f"ColorEmbedding: crop must be square with a side multiple of 32, got {tuple(x.shape)}")
        h = self.stem(x)
        for s in self.stages:
            h = s(h)
        for u in self.ups:
            h = u(F.interpolate(h, scale_factor=2.0, mode="bilinear", align_corners=False))
        h = F.interpolate(h, size=(S, S), mode="bilinear", align_corners=False)
        return F.relu(self.out(h))


def gather_pixels(emb: torch.Tensor, choose: torch.Tensor) -> torch.Tensor:
    """(B, C, S, S) map, (B, N) flat pixel indices -> (B, C, N)."""
    B, C = emb.shape[:2]
    return emb.reshape(B, C, -1).gather(2, choose[:, None, :].expand(B, C, choose.shape[1]))


def knn(points: torch.Tensor, k: int) -> torch.Tensor:
    """(B, N, 3) -> (B, N, k) indices of each point's k nearest points (itself first)."""
    d = torch.cdist(points, points)
    return d.topk(min(k, points.shape[1]), dim=-1, largest=False).indices


def _neighbours(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """(B, C, N) features, (B, N, k) indices -> (B, C, N, k)."""
    B, C, N = x.shape
    k = idx.shape[-1]
    return x.gather(2, idx.reshape(B, 1, N * k).expand(B, C, N * k)).reshape(B, C, N, k)


class EdgeConv(nn.Module):
    """DGCNN edge convolution: ``h_i = max_j MLP([x_i, x_j - x_i])`` over the kNN graph ``idx``."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Conv2d(2 * cin, cout, 1, bias=False), nn.GroupNorm(1, cout), nn.LeakyReLU(0.2))

    def forward(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """(B, C, N), (B, N, k) -> (B, cout, N).

        The 1x1 convolution of ``[x_i, x_j - x_i]`` is linear, so it is computed per point and then
        gathered: ``W [x_i, x_j - x_i] = (W_1 - W_2) x_i + W_2 x_j`` (k times fewer multiplications
        than convolving the (B, 2C, N, k) edge tensor; :meth:`forward_reference` does the latter).
        """
        w = self.mlp[0].weight[:, :, 0, 0]
        cin = x.shape[1]
        w1, w2 = w[:, :cin], w[:, cin:]
        centre = torch.einsum("oc,bcn->bon", w1 - w2, x)
        edge = _neighbours(torch.einsum("oc,bcn->bon", w2, x), idx)
        return self.mlp[2](self.mlp[1](edge + centre[..., None])).max(dim=-1).values

    def forward_reference(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """The textbook form: the MLP on the explicit (B, 2C, N, k) edge features (tests compare)."""
        nb = _neighbours(x, idx)
        xi = x[..., None].expand_as(nb)
        return self.mlp(torch.cat([xi, nb - xi], dim=1)).max(dim=-1).values


class GraphAttention(nn.Module):
    """Graph attention layer (GAT, multi-head, concatenated) over the kNN graph ``idx``.

    ``e_ij = LeakyReLU(a_src . W h_i + a_dst . W h_j)``, softmax over the k neighbours of i (itself
    included), ``h_i' = ELU(concat_heads sum_j alpha_ij W h_j)``.
    """

    def __init__(self, cin: int, cout: int, heads: int):
        super().__init__()
        if cout % heads:
            raise ValueError(f"GraphAttention: output width {cout} is not divisible by {heads} heads")
        self.heads, self.f = heads, cout // heads
        self.W = nn.Conv1d(cin, cout, 1, bias=False)
        self.a_src = nn.Parameter(torch.randn(heads, self.f) * 0.1)
        self.a_dst = nn.Parameter(torch.randn(heads, self.f) * 0.1)

    def forward(self, x: torch.Tensor, idx: torch.Tensor, return_attention: bool = False):
        B, _, N = x.shape
        Wh = self.W(x)                                                      # (B, H*F, N)
        nb = _neighbours(Wh, idx).reshape(B, self.heads, self.f, N, -1)     # (B, H, F, N, k)
        Wh = Wh.reshape(B, self.heads, self.f, N)
        s = torch.einsum("bhfn,hf->bhn", Wh, self.a_src)[..., None] + torch.einsum("bhfnk,hf->bhnk", nb, self.a_dst)
        alpha = torch.softmax(F.leaky_relu(s, 0.2), dim=-1)                 # (B, H, N, k)
        out = F.elu(torch.einsum("bhnk,bhfnk->bhfn", alpha, nb).reshape(B, -1, N))
        return (out, alpha) if return_attention else out


class _Head(nn.Module):
    """Per-point MLP -> ``dim`` outputs per object; the instance's object slot is selected."""

    def __init__(self, cin: int, hidden: tuple[int, ...], dim: int, n_objects: int):
        super().__init__()
        layers, c = [], cin
        for h in hidden:
            layers += [nn.Conv1d(c, h, 1), nn.ReLU()]
            c = h
        self.mlp = nn.Sequential(*layers)
        self.out = nn.Conv1d(c, dim * n_objects, 1)
        self.dim = dim

    def forward(self, x: torch.Tensor, obj_idx: torch.Tensor) -> torch.Tensor:
        """(B, C, N) -> (B, N, dim)."""
        y = self.out(self.mlp(x))
        B, _, N = y.shape
        y = y.reshape(B, -1, self.dim, N)
        return y[torch.arange(B, device=y.device), obj_idx].transpose(1, 2)


def _init_quat_head(head: _Head) -> None:
    """Start near the identity rotation (w = 1) so early poses are sane."""
    nn.init.zeros_(head.out.bias)
    with torch.no_grad():
        head.out.weight.mul_(0.1)
        head.out.bias.view(-1, 4)[:, 0] = 1.0


class _DenseFusionFeat(nn.Module):
    """PointNet + colour, fused per pixel at two depths, plus an average-pooled global feature."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        g1, g2 = cfg.geo_dims[0], cfg.geo_dims[1]
        self.conv1, self.e_conv1 = nn.Conv1d(3, g1, 1), nn.Conv1d(cfg.emb_dim, g1, 1)
        self.conv2, self.e_conv2 = nn.Conv1d(g1, g2, 1), nn.Conv1d(g1, g2, 1)
        self.conv5 = nn.Conv1d(2 * g2, cfg.global_dim // 2, 1)
        self.conv6 = nn.Conv1d(cfg.global_dim // 2, cfg.global_dim, 1)
        self.out_dim = 2 * g1 + 2 * g2 + cfg.global_dim

    def forward(self, x, emb, idx=None):
        x, emb = F.relu(self.conv1(x)), F.relu(self.e_conv1(emb))
        f1 = torch.cat([x, emb], 1)
        x, emb = F.relu(self.conv2(x)), F.relu(self.e_conv2(emb))
        f2 = torch.cat([x, emb], 1)
        g = F.relu(self.conv6(F.relu(self.conv5(f2)))).mean(-1, keepdim=True)
        return torch.cat([f1, f2, g.expand(-1, -1, x.shape[-1])], 1)


class _CGAFFeat(nn.Module):
    """EdgeConv local + global geometry, colour, fused by a GAT (or a per-node layer)."""

    def __init__(self, cfg: ModelConfig, attention: bool):
        super().__init__()
        dims = (3,) + tuple(cfg.geo_dims)
        self.edge = nn.ModuleList(EdgeConv(dims[i], dims[i + 1]) for i in range(len(cfg.geo_dims)))
        local = sum(cfg.geo_dims)
        self.glob = nn.Conv1d(local, cfg.global_dim, 1)
        self.color = nn.Conv1d(cfg.emb_dim, cfg.geo_dims[0], 1)
        node = cfg.geo_dims[0] + local + cfg.global_dim
        self.fuse = (GraphAttention(node, cfg.fuse_dim, cfg.gat_heads) if attention
                     else nn.Sequential(nn.Conv1d(node, cfg.fuse_dim, 1), nn.ELU()))
        self.attention = attention
        self.out_dim = cfg.fuse_dim + node

    def forward(self, x, emb, idx):
        feats, h = [], x
        for e in self.edge:
            h = e(h, idx)
            feats.append(h)
        local = torch.cat(feats, 1)
        g = F.relu(self.glob(local)).max(-1, keepdim=True).values.expand(-1, -1, x.shape[-1])
        node = torch.cat([F.relu(self.color(emb)), local, g], 1)
        fused = self.fuse(node, idx) if self.attention else self.fuse(node)
        return torch.cat([fused, node], 1)  # residual: the GAT output beside its input nodes


class PoseRefiner(nn.Module):
    """DenseFusion's refiner: one pose update from the points in the current object frame."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        g1, g2 = cfg.geo_dims[0], cfg.geo_dims[1]
        self.conv1, self.e_conv1 = nn.Conv1d(3, g1, 1), nn.Conv1d(cfg.emb_dim, g1, 1)
        self.conv2, self.e_conv2 = nn.Conv1d(g1, g2, 1), nn.Conv1d(g1, g2, 1)
        self.conv5 = nn.Conv1d(2 * (g1 + g2), cfg.global_dim // 2, 1)
        self.conv6 = nn.Conv1d(cfg.global_dim // 2, cfg.global_dim, 1)
        self.q = _Head(cfg.global_dim, cfg.head_dims, 4, cfg.n_objects)
        self.t = _Head(cfg.global_dim, cfg.head_dims, 3, cfg.n_objects)
        _init_quat_head(self.q)
        nn.init.zeros_(self.t.out.weight)
        nn.init.zeros_(self.t.out.bias)

    def forward(self, points: torch.Tensor, emb: torch.Tensor, obj_idx: torch.Tensor,
                R: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Refined ``(R (B, 3, 3), t (B, 3))`` from the current ``R, t`` and the (B, N, 3) points."""
        p_obj = torch.einsum("bji,bnj->bni", R, points - t[:, None])  # camera -> current object frame
        x = p_obj.transpose(1, 2)
        x1, e1 = F.relu(self.conv1(x)), F.relu(self.e_conv1(emb))
        x2, e2 = F.relu(self.conv2(x1)), F.relu(self.e_conv2(e1))
        f = torch.cat([x1, e1, x2, e2], 1)
        g = F.relu(self.conv6(F.relu(self.conv5(f)))).mean(-1, keepdim=True)
        dR = quat_to_R(self.q(g, obj_idx)[:, 0])
        dt = self.t(g, obj_idx)[:, 0]
        return R @ dR, torch.einsum("bij,bj->bi", R, dt) + t  # T_new = T_cur @ dT


class PoseNet(nn.Module):
    """Per-point pose estimator plus refiner (see the module docstring for ``cfg.arch``)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        if cfg.arch not in ARCHS:
            raise ValueError(f"unknown pose network '{cfg.arch}' (choose from {', '.join(ARCHS)})")
        self.cfg = cfg
        self.cnn = ColorEmbedding(cfg.cnn_width, cfg.emb_dim)
        self.feat = _DenseFusionFeat(cfg) if cfg.arch == "densefusion" else _CGAFFeat(cfg, cfg.arch == "cgaf")
        d = self.feat.out_dim
        self.q = _Head(d, cfg.head_dims, 4, cfg.n_objects)
        self.t = _Head(d, cfg.head_dims, 3, cfg.n_objects)
        self.c = _Head(d, cfg.head_dims, 1, cfg.n_objects)
        _init_quat_head(self.q)
        self.refiner = PoseRefiner(cfg)

    def forward(self, rgb: torch.Tensor, points: torch.Tensor, choose: torch.Tensor, obj_idx: torch.Tensor) -> PoseOut:
        """rgb (B, 3, S, S), points (B, N, 3) metres, choose (B, N) crop pixel indices, obj_idx (B,)."""
        emb = gather_pixels(self.cnn(rgb), choose)
        centre = points.mean(1, keepdim=True)
        x = (points - centre).transpose(1, 2)  # centred: the features see shape, the heads add the point back
        idx = knn(points, self.cfg.k) if self.cfg.arch != "densefusion" else None
        f = self.feat(x, emb, idx)
        R = quat_to_R(self.q(f, obj_idx))
        t = points + self.t(f, obj_idx)       # translation = the point + a predicted offset (DenseFusion)
        conf = torch.sigmoid(self.c(f, obj_idx))[..., 0]
        return PoseOut(R=R, t=t, conf=conf, emb=emb)

    def refine(self, points, emb, obj_idx, R, t):
        return self.refiner(points, emb, obj_idx, R, t)


def best_pose(out: PoseOut) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Most confident per-point pose of each instance: ``R (B, 3, 3), t (B, 3), conf (B,)``."""
    i = out.conf.argmax(1)
    b = torch.arange(len(i), device=i.device)
    return out.R[b, i], out.t[b, i], out.conf[b, i]
