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

__all__ = ["LossConfig", "LossOut", "quat_to_R", "point_distances", "symmetric_add", "pose_loss"]


@dataclass(frozen=True)
class LossConfig:
    """Weights of the pose loss."""

    conf_weight: float = 0.015
    """``w`` of the ``- w log c`` regulariser (DenseFusion's default)."""
    symmetry: str = "transforms"
    """How symmetric objects are scored in the loss: ``transforms`` = ADD to the closest of the true
    pose's symmetric copies listed in ``models_info.json`` (:func:`symmetric_add`: a flipped object is
    penalised unless the flip is a listed symmetry), ``adds`` = DenseFusion's ADD-S (closest point)."""


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


def symmetric_add(R: torch.Tensor, t: torch.Tensor, model_points: torch.Tensor,
                  sym_targets: torch.Tensor) -> torch.Tensor:
    """ADD to the closest symmetric copy of the true pose, for P candidate poses per instance.

    Args:
        R: (B, P, 3, 3), t: (B, P, 3) candidate poses. model_points: (B, M, 3).
        sym_targets: (B, S, M, 3) the model points under each symmetry transform ``T_s`` then the true
            pose (``R_gt (R_s x + t_s) + t_gt``; S = 1 with the identity for an asymmetric object).

    Returns:
        (B, P) ``mean_m |R x_m + t - target_s*,m|``, metres, where ``s*`` is the copy closest in RMS
        distance (chosen without gradient; the mean distance to it is differentiable).
    """
    pred = torch.einsum("bpij,bmj->bpmi", R, model_points) + t[:, :, None, :]      # (B, P, M, 3)
    if sym_targets.shape[1] == 1:
        return (pred - sym_targets[:, :1]).norm(dim=-1).mean(-1)
    with torch.no_grad():
        d = torch.cdist(pred.flatten(2), sym_targets.flatten(2)) / model_points.shape[1] ** 0.5  # (B, P, S)
        s = d.argmin(-1)                                                               # RMS-closest copy
    best = sym_targets.gather(1, s[..., None, None].expand(-1, -1, *sym_targets.shape[2:]))  # (B, P, M, 3)
    return (pred - best).norm(dim=-1).mean(-1)


def pose_loss(R: torch.Tensor, t: torch.Tensor, conf: torch.Tensor, model_points: torch.Tensor,
              target: torch.Tensor, symmetric: torch.Tensor, cfg: LossConfig = LossConfig(),
              sym_targets: torch.Tensor | None = None) -> LossOut:
    """DenseFusion's confidence-weighted per-point loss; ``conf`` (B, P) in (0, 1].

    With ``sym_targets`` (B, S, M, 3) and ``cfg.symmetry == "transforms"`` the distance is
    :func:`symmetric_add`; otherwise ADD, ADD-S where ``symmetric`` (:func:`point_distances`).
    """
    if R.shape[:2] != conf.shape or t.shape[:2] != conf.shape:
        raise ValueError(f"pose_loss: R {tuple(R.shape)}, t {tuple(t.shape)}, conf {tuple(conf.shape)} disagree")
    if cfg.symmetry not in ("transforms", "adds"):
        raise ValueError(f"pose_loss: symmetry must be 'transforms' or 'adds', got {cfg.symmetry!r}")
    if sym_targets is not None and cfg.symmetry == "transforms":
        dist = symmetric_add(R, t, model_points, sym_targets)
    else:
        dist = point_distances(R, t, model_points, target, symmetric)
    loss = (dist * conf - cfg.conf_weight * torch.log(conf.clamp_min(1e-12))).mean()
    best = conf.argmax(dim=1)
    return LossOut(loss=loss, dist_m=dist, best_dist_m=dist.gather(1, best[:, None])[:, 0])
