"""Training/test instances for the pose networks, read from any BOP folder with depth.

One instance = one annotated object in one image: the colour crop around its visible mask (resized
to ``crop_px`` square), ``n_points`` points of the masked depth back-projected to the camera frame
(metres) with the index of each point's pixel in the crop (DenseFusion's ``choose``), and
``n_model_points`` model points with their ground-truth positions (the loss targets).

Files are read only through :class:`presim.datasets.bop_reader.BopDataset` (records of
:mod:`presim.formats.bop`, models through :mod:`presim.formats.ply`); symmetric objects are those with
symmetries in ``models_info.json``.

Example:
    >>> ds = PoseInstanceDataset("out/bop", PoseDataConfig(split="train"))   # doctest: +SKIP
    >>> item = ds[0]; item["points"].shape                                    # doctest: +SKIP
    torch.Size([256, 3])
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from presim.datasets.bop_reader import BopDataset
from presim.geometry import Intrinsics, unproject
from presim.io_utils import progress
from presim.pose.metrics import symmetry_transformations

__all__ = ["PoseDataConfig", "InstanceRef", "ObjectTable", "PoseInstanceDataset", "PreparedInstance",
           "prepare_instance", "sample_instance", "make_instance", "load_object_table"]

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)  # input normalisation only;
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)   # no pretrained weights are used


@dataclass(frozen=True)
class PoseDataConfig:
    """What an instance holds and how it is augmented."""

    split: str = "train"
    """BOP split folder read (``train``, ``test``, ...)."""
    n_points: int = 256
    """Points sampled from the masked depth per instance (DenseFusion: 500; fewer for CPU)."""
    n_model_points: int = 200
    """Model points per object used by the loss (DenseFusion: 500)."""
    crop_px: int = 64
    """Side of the square colour crop fed to the CNN, pixels (the mask's box, padded, resized)."""
    crop_pad: float = 0.1
    """Padding of the mask's box on each side, as a fraction of its larger side."""
    min_visib_fract: float = 0.1
    """Instances less visible than this are skipped (pose-eval's default targets use the same 10 %)."""
    min_points: int = 32
    """Instances with fewer masked valid-depth pixels are skipped."""
    augment: bool = False
    """Colour jitter and depth noise (training)."""
    jitter_brightness: float = 0.2
    """Colour gain drawn uniformly in ``1 ± this``."""
    jitter_contrast: float = 0.2
    """Contrast gain about the crop's mean grey, uniformly in ``1 ± this``."""
    jitter_color: float = 0.05
    """Per-channel gain offset, uniformly in ``± this``."""
    depth_noise_m: float = 0.002
    """Std of Gaussian noise added to each point's depth, metres."""
    seed: int = 0
    """Seeds the model-point sampling and the augmentation stream."""
    sym_step: float = 0.1
    """Continuous symmetries of ``models_info.json`` are cut into ``ceil(pi / sym_step)`` rotations
    (:func:`presim.pose.metrics.symmetry_transformations`) for the symmetry-aware loss targets."""
    cache: bool = True
    """Keep each instance's crop and masked depth pixels in memory after the first read
    (:class:`PreparedInstance`, ~30 kB each); only the point draw and the jitter run per step."""


@dataclass(frozen=True)
class InstanceRef:
    """Where an instance lives in the BOP folder."""

    scene_id: int
    im_id: int
    gt_idx: int
    """Position in scene_gt.json (the ``_NNNNNN`` of its mask file)."""
    obj_id: int


@dataclass(frozen=True)
class ObjectTable:
    """The dataset's objects, in ``models_info.json`` order (the networks' output slots)."""

    obj_ids: tuple[int, ...]
    model_points_m: dict[int, np.ndarray]
    """obj_id -> (n_model_points, 3) float32 model points, metres."""
    diameter_m: dict[int, float]
    symmetric: dict[int, bool]
    """True when models_info.json lists a discrete or continuous symmetry (scored with ADD-S)."""
    sym_transforms: dict[int, np.ndarray] | None = None
    """obj_id -> (S, 4, 4) model-frame symmetry transforms of models_info.json, identity first (metres)."""

    def index(self, obj_id: int) -> int:
        return self.obj_ids.index(obj_id)


def load_object_table(bop: BopDataset, n_model_points: int, seed: int = 0, sym_step: float = 0.1) -> ObjectTable:
    """Models of every object of ``models_info.json``, subsampled to ``n_model_points`` (seeded), with
    their symmetry transforms (continuous ones cut into ``ceil(pi / sym_step)`` rotations)."""
    info = bop.models_info()
    if not info:
        raise ValueError(f"{bop.models_dir / 'models_info.json'}: no objects")
    pts, diam, sym, syms = {}, {}, {}, {}
    for obj_id in sorted(info):
        try:
            v = bop.model_mesh_m(obj_id).vertices
        except FileNotFoundError as e:
            raise FileNotFoundError(f"{e} (object {obj_id} is listed in models_info.json)") from None
        if len(v) == 0:
            raise ValueError(f"{bop.model_path(obj_id)}: model of object {obj_id} has no vertices")
        rng = np.random.default_rng([seed, obj_id])
        idx = rng.choice(len(v), n_model_points, replace=len(v) < n_model_points)
        pts[obj_id] = v[idx].astype(np.float32)
        diam[obj_id] = info[obj_id].diameter_m
        sym[obj_id] = info[obj_id].is_symmetric
        syms[obj_id] = symmetry_transformations(info[obj_id].symmetries_discrete, info[obj_id].symmetries_continuous,
                                                max_sym_disc_step=sym_step).astype(np.float32)
    return ObjectTable(tuple(sorted(info)), pts, diam, sym, syms)


def _crop_box(mask: np.ndarray, pad: float) -> tuple[int, int, int, int]:
    """Square box ``(x0, y0, side)`` around the mask (may extend past the image; padded with 0)."""
    ys, xs = np.nonzero(mask)
    x0, x1, y0, y1 = xs.min(), xs.max() + 1, ys.min(), ys.max() + 1
    side = int(np.ceil(max(x1 - x0, y1 - y0) * (1 + 2 * pad)))
    cx, cy = (x0 + x1) / 2.0, (y0 + y1) / 2.0
    return int(np.floor(cx - side / 2.0)), int(np.floor(cy - side / 2.0)), max(side, 1)


@dataclass(frozen=True)
class PreparedInstance:
    """The part of an instance that does not depend on the random draw (cached by the dataset).

    ``crop`` is the mask's padded square box resized to ``crop_px`` (uint8, before jitter); ``u, v, z``
    are the masked valid-depth pixels and their depths; ``x0, y0, side`` the box in the image.
    """

    crop: np.ndarray
    u: np.ndarray
    v: np.ndarray
    z: np.ndarray
    x0: int
    y0: int
    side: int
    K: Intrinsics


def prepare_instance(rgb: np.ndarray, depth_m: np.ndarray, mask: np.ndarray, K: Intrinsics,
                     cfg: PoseDataConfig) -> PreparedInstance | None:
    """Crop and masked depth pixels of one object, or None when fewer than ``cfg.min_points`` have depth."""
    valid = mask & (depth_m > 0)
    vs, us = np.nonzero(valid)
    if len(vs) < cfg.min_points:
        return None
    x0, y0, side = _crop_box(mask, cfg.crop_pad)
    S = cfg.crop_px
    # Crop with zero padding outside the image, then resize to S x S.
    H, W = mask.shape
    crop = np.zeros((side, side, 3), dtype=np.uint8)
    sx0, sy0, sx1, sy1 = max(x0, 0), max(y0, 0), min(x0 + side, W), min(y0 + side, H)
    crop[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = rgb[sy0:sy1, sx0:sx1]
    crop = cv2.resize(crop, (S, S), interpolation=cv2.INTER_LINEAR)
    return PreparedInstance(crop=crop, u=us, v=vs, z=depth_m[vs, us].astype(np.float32), x0=x0, y0=y0,
                            side=side, K=K)


def sample_instance(prep: PreparedInstance, cfg: PoseDataConfig,
                    rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The random part of an instance: points drawn from ``prep`` and (``cfg.augment``) the jitter."""
    S = cfg.crop_px
    # pixels first, augmentation after: the same rng state picks the same pixels with or without it
    sel = rng.choice(len(prep.u), cfg.n_points, replace=len(prep.u) < cfg.n_points)
    crop = prep.crop.astype(np.float32) / 255.0
    if cfg.augment:
        grey = crop.mean()
        crop = (crop - grey) * rng.uniform(1 - cfg.jitter_contrast, 1 + cfg.jitter_contrast) + grey
        crop = crop * rng.uniform(1 - cfg.jitter_brightness, 1 + cfg.jitter_brightness)
        crop = crop * (1 + rng.uniform(-cfg.jitter_color, cfg.jitter_color, size=3)).astype(np.float32)
        crop = np.clip(crop, 0.0, 1.0)
    crop = (crop - IMAGENET_MEAN) / IMAGENET_STD
    u, v = prep.u[sel], prep.v[sel]
    z = prep.z[sel].astype(np.float64)
    if cfg.augment and cfg.depth_noise_m > 0:
        z = np.maximum(z + rng.normal(0.0, cfg.depth_noise_m, size=z.shape), 1e-3)
    pts = unproject(prep.K, np.stack([u, v], axis=-1).astype(np.float64), z)
    # pixel -> crop pixel (nearest, pixel centres at integers)
    cu = np.clip(np.floor((u - prep.x0 + 0.5) * S / prep.side), 0, S - 1).astype(np.int64)
    cv = np.clip(np.floor((v - prep.y0 + 0.5) * S / prep.side), 0, S - 1).astype(np.int64)
    return {"rgb": np.ascontiguousarray(crop.transpose(2, 0, 1), dtype=np.float32),
            "points": pts.astype(np.float32), "choose": cv * S + cu}


def make_instance(rgb: np.ndarray, depth_m: np.ndarray, mask: np.ndarray, K: Intrinsics,
                  cfg: PoseDataConfig, rng: np.random.Generator) -> dict[str, np.ndarray] | None:
    """Network input of one object: colour crop, sampled points and their crop pixels.

    ``= sample_instance(prepare_instance(...))``: the dataset caches the prepared part.

    Args:
        rgb: (H, W, 3) uint8. depth_m: (H, W) float32 z-depth, 0 = invalid. mask: (H, W) bool.
        K: intrinsics of the image. rng: draws the points (and the augmentation when ``cfg.augment``).

    Returns:
        ``{"rgb": (3, S, S) float32 normalised, "points": (N, 3) float32 camera-frame metres,
        "choose": (N,) int64 index v*S+u into the crop}``, or None when fewer than
        ``cfg.min_points`` masked pixels have depth.
    """
    prep = prepare_instance(rgb, depth_m, mask, K, cfg)
    return None if prep is None else sample_instance(prep, cfg, rng)


class PoseInstanceDataset(torch.utils.data.Dataset):
    """Every usable annotated instance of a BOP split (ground-truth visible masks).

    Raises a one-line ``ValueError``/``FileNotFoundError`` naming the folder for a split without
    scenes or instances, a dataset without depth images, or an object without a model.
    """

    def __init__(self, root: str | Path, cfg: PoseDataConfig = PoseDataConfig(),
                 objects: ObjectTable | None = None):
        self.cfg = cfg
        self.bop = BopDataset(root, cfg.split)
        self.objects = (objects if objects is not None
                        else load_object_table(self.bop, cfg.n_model_points, cfg.seed, cfg.sym_step))
        syms = self.objects.sym_transforms or {o: np.eye(4, dtype=np.float32)[None] for o in self.objects.obj_ids}
        self._n_sym = max(len(v) for v in syms.values())
        # model points under each symmetry, padded with the identity to the same count (min is unchanged)
        self._sym_points = {}
        for o in self.objects.obj_ids:
            T = np.concatenate([syms[o], np.repeat(syms[o][:1], self._n_sym - len(syms[o]), 0)])
            m = self.objects.model_points_m[o]
            self._sym_points[o] = (np.einsum("sij,mj->smi", T[:, :3, :3], m) + T[:, None, :3, 3]).astype(np.float32)
        self._cache: dict[int, PreparedInstance | None] = {}
        self.refs: list[InstanceRef] = []
        scene_ids = self.bop.scene_ids()
        if not scene_ids:
            raise ValueError(f"{self.bop.split_dir}: split has no scene folders")
        for sid in scene_ids:
            depth_dir = self.bop.scene_dir(sid) / "depth"
            if not depth_dir.is_dir() or not any(depth_dir.iterdir()):
                raise ValueError(f"{depth_dir}: no depth images (the pose networks need RGB-D)")
            gt, info = self.bop.scene_gt(sid), self.bop.scene_gt_info(sid)
            for im_id in sorted(gt):
                for gt_idx, inst in enumerate(gt[im_id]):
                    if inst.obj_id not in self.objects.obj_ids:
                        raise FileNotFoundError(f"{self.bop.models_dir}: object {inst.obj_id} of scene {sid} "
                                                f"image {im_id} has no model in models_info.json")
                    gi = info.get(im_id, [])
                    if gt_idx < len(gi) and (gi[gt_idx].visib_fract < cfg.min_visib_fract
                                             or gi[gt_idx].px_count_valid == 0):
                        continue
                    self.refs.append(InstanceRef(sid, im_id, gt_idx, inst.obj_id))
        if not self.refs:
            raise ValueError(f"{self.bop.split_dir}: no instances with visib_fract >= {cfg.min_visib_fract}")
        self._epoch = 0

    def __len__(self) -> int:
        return len(self.refs)

    def set_epoch(self, epoch: int) -> None:
        """Changes the augmentation / sampling stream (deterministic per (seed, epoch, index))."""
        self._epoch = int(epoch)

    def _prepare(self, i: int, rgb=None, depth=None) -> PreparedInstance | None:
        r, bop = self.refs[i], self.bop
        mask = bop.read_mask(r.scene_id, r.im_id, r.gt_idx, visib=True)
        if not mask.any():
            return None
        rgb = bop.read_rgb(r.scene_id, r.im_id) if rgb is None else rgb
        depth = bop.read_depth_m(r.scene_id, r.im_id) if depth is None else depth
        return prepare_instance(rgb, depth, mask, bop.intrinsics(r.scene_id, r.im_id), self.cfg)

    def precompute(self, indices=None, show_progress: bool = False) -> None:
        """Fill the cache for ``indices`` (default all), reading each image once (``cfg.cache``)."""
        if not self.cfg.cache:
            return
        todo = [i for i in (range(len(self.refs)) if indices is None else indices) if i not in self._cache]
        by_image: dict[tuple[int, int], list[int]] = {}
        for i in todo:
            by_image.setdefault((self.refs[i].scene_id, self.refs[i].im_id), []).append(i)
        for (sid, im), idx in progress(by_image.items(), desc="caching instances", unit="image",
                                       disable=None if show_progress else True):
            rgb, depth = self.bop.read_rgb(sid, im), self.bop.read_depth_m(sid, im)
            for i in idx:
                self._cache[i] = self._prepare(i, rgb, depth)

    def load(self, i: int, rng: np.random.Generator) -> dict | None:
        r = self.refs[i]
        bop = self.bop
        if self.cfg.cache:
            if i not in self._cache:
                self._cache[i] = self._prepare(i)
            prep = self._cache[i]
        else:
            prep = self._prepare(i)
        if prep is None:
            return None
        inst = sample_instance(prep, self.cfg, rng)
        gt = bop.scene_gt(r.scene_id)[r.im_id][r.gt_idx]
        m = self.objects.model_points_m[r.obj_id]
        R, t = gt.R_m2c.astype(np.float32), gt.t_m2c_m.astype(np.float32)
        inst.update(model_points=m, target=(m @ R.T + t).astype(np.float32), R_gt=R, t_gt=t,
                    sym_targets=(self._sym_points[r.obj_id] @ R.T + t).astype(np.float32),
                    obj_idx=np.int64(self.objects.index(r.obj_id)),
                    symmetric=np.bool_(self.objects.symmetric[r.obj_id]),
                    diameter_m=np.float32(self.objects.diameter_m[r.obj_id]),
                    scene_id=np.int64(r.scene_id), im_id=np.int64(r.im_id), obj_id=np.int64(r.obj_id))
        return inst

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        rng = np.random.default_rng([self.cfg.seed, self._epoch, i])
        inst = self.load(i, rng)
        j = i
        while inst is None:  # too few depth pixels: a deterministic substitute keeps batch shapes
            j = (j + 1) % len(self.refs)
            if j == i:
                raise ValueError(f"{self.bop.split_dir}: no instance has {self.cfg.min_points} pixels with depth")
            inst = self.load(j, rng)
        return {k: torch.as_tensor(v) for k, v in inst.items()}
