"""Per-point pose loss of DenseFusion (thesis eq. 6.1/6.2): ADD, ADD-S for symmetric objects, with
the confidence regulariser ``L = mean_i (c_i * D_i - w * log c_i)``.

``D_i`` is the mean distance (metres) between the model points moved by point ``i``'s pose and the
same points moved by the true pose (ADD), or to the closest of them (ADD-S). At the true pose with
``c = 1`` the loss is exactly 0; with ``c = 1`` and a translation error ``d`` it is ``|d|``.

Example:
    >>> out = pose_loss(R, t, conf, model_points, target, symmetric)    # doctest: +SKIP
    >>> out.loss.backward()                                              # doctest: +SKIP
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["LossConfig", "LossOut", "quat_to_R", "point_distances", "pose_loss"]


@dataclass(frozen=True)
class LossConfig:
    """Weights of the pose loss."""

    conf_weight: float = 0.015
    """``w`` of the ``- w log c`` regulariser (DenseFusion's default)."""


@dataclass
class LossOut:
    loss: torch.Tensor
    """Scalar to minimise."""
    dist_m: torch.Tensor
    """(B, P) ADD(-S) of each per-point pose, metres."""
    best_dist_m: torch.Tensor
    """(B,) ADD(-S) of the most confident pose of each instance, metres."""


def quat_to_R(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternions ``(..., 4)`` as ``(w, x, y, z)`` (normalised here) -> rotations ``(..., 3, 3)``."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(q.shape[:-1] + (3, 3))


def point_distances(R: torch.Tensor, t: torch.Tensor, model_points: torch.Tensor, target: torch.Tensor,
                    symmetric: torch.Tensor) -> torch.Tensor:
    """ADD (ADD-S where ``symmetric``) of P candidate poses per instance.

    Args:
        R: (B, P, 3, 3), t: (B, P, 3) candidate poses model -> camera (metres).
        model_points: (B, M, 3) model frame. target: (B, M, 3) the same points at the true pose.
        symmetric: (B,) bool.

    Returns:
        (B, P) mean point distance, metres.
    """
    pred = torch.einsum("bpij,bmj->bpmi", R, model_points) + t[:, :, None, :]  # (B, P, M, 3)
    dist = (pred - target[:, None]).norm(dim=-1).mean(-1)                       # ADD
    sym = symmetric.nonzero().flatten().tolist()
    if sym:
        dist = dist.clone()
        for b in sym:  # ADD-S: closest true point, one instance at a time to bound memory (P*M*M)
            d = torch.cdist(pred[b], target[b][None].expand(pred.shape[1], -1, -1))
            dist[b] = d.min(-1).values.mean(-1)
    return dist


def pose_loss(R: torch.Tensor, t: torch.Tensor, conf: torch.Tensor, model_points: torch.Tensor,
              target: torch.Tensor, symmetric: torch.Tensor, cfg: LossConfig = LossConfig()) -> LossOut:
    """DenseFusion's confidence-weighted per-point loss; ``conf`` (B, P) in (0, 1]."""
    if R.shape[:2] != conf.shape or t.shape[:2] != conf.shape:
        raise ValueError(f"pose_loss: R {tuple(R.shape)}, t {tuple(t.shape)}, conf {tuple(conf.shape)} disagree")
    dist = point_distances(R, t, model_points, target, symmetric)
    loss = (dist * conf - cfg.conf_weight * torch.log(conf.clamp_min(1e-12))).mean()
    best = conf.argmax(dim=1)
    return LossOut(loss=loss, dist_m=dist, best_dist_m=dist.gather(1, best[:, None])[:, 0])
