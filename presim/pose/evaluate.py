"""Benchmark evaluator: score BOP results against a BOP dataset (thesis §6.3.1, Tables 6.1/6.2,
Figs 6.5, 6.6, 6.13) and BOP'19 Average Recall.

Protocol (choices written down in docs/pose-metrics.md):

- Targets: ``test_targets_bop19.json`` (or ``--targets``); without one, every (image, object) with
  an instance at least 10 % visible (as BOP's ``create_test_targets``). For a target with
  ``inst_count`` k, the k most visible GT instances of the object are the valid GT (BOP'19,
  ``visib_gt_min = -1``) and the k highest-scoring estimates are kept (BOP's ``n_top = -1``).
- ADD-family errors: the kept estimates are matched greedily in score order, each to the unmatched
  valid GT with the lowest ADD(-S). GT left unmatched (missing estimates) are failures (error inf).
  With k = 1 (LM-O, YCB-V) this is simply "the highest-scoring estimate".
- BOP AR: errors of every kept estimate against every valid GT, then bop_toolkit's greedy matching
  per threshold (``error < th``); recall = matched GT / all valid GT; AR_X = mean recall over the
  thresholds (VSD also over taus); AR = mean of AR_VSD, AR_MSSD, AR_MSPD (only when depth exists).
- Model points: ``models_eval/`` when present, else ``models/`` vertices (as bop_toolkit).
- Symmetric objects (ADD-S in ADD(-S)): ``models_info`` symmetries or the ``symmetric_obj_ids``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from presim.datasets.bop_reader import BopDataset
from presim.formats.bop import GtInstance, Target
from presim.io_utils import progress
from presim.pose import curves
from presim.pose.metrics import MeshDepthRenderer, symmetry_transformations, vsd
from presim.pose.nn_grid import NNGrid, adi_batch_kdtree
from presim.pose.results import BopResults, Estimate, read_bop_results

__all__ = ["EvalConfig", "TargetRecord", "EvalReport", "evaluate", "evaluate_files"]

_BOP_TH = tuple(float(x) for x in np.arange(0.05, 0.51, 0.05))


@dataclass(frozen=True)
class EvalConfig:
    """Evaluation settings (defaults = thesis §6.3.1 + BOP'19)."""

    split: str = "test"
    """Split folder of the dataset."""
    targets_path: Path | None = None
    """Targets JSON; default ``<dataset>/test_targets_bop19.json`` when present."""
    scene_ids: tuple[int, ...] | None = None
    """Evaluate only these scenes (None: all scenes with targets)."""
    symmetric_obj_ids: tuple[int, ...] = ()
    """Objects scored with ADD-S in ADD(-S), in addition to those with symmetries in models_info."""
    use_models_eval: bool = True
    """Use models_eval/ points when present (bop_toolkit does)."""
    max_sym_disc_step: float = 0.01
    """Discretisation of continuous symmetries (bop_toolkit's default)."""
    auc_max_m: float = 0.1
    """Max threshold of the ADD(-S) AUC (PoseCNN/DenseFusion: 0.1 m)."""
    acc_threshold_m: float = 0.02
    """Accuracy threshold in metres (thesis: 2 cm, a gripper's tolerance)."""
    acc_threshold_diam: float = 0.1
    """Accuracy threshold as a fraction of the diameter (the classic ADD(-S) 0.1 d)."""
    proj_max_px: float = 50.0
    """Max threshold of the reprojection-error curve (Fig 6.6)."""
    vsd: str = "auto"
    """'auto' (when every evaluated image has depth), 'on' (error without depth) or 'off'."""
    vsd_delta_m: float = 0.015
    """VSD visibility tolerance (BOP: 15 mm)."""
    vsd_taus: tuple[float, ...] = _BOP_TH
    """VSD misalignment tolerances, fractions of the diameter (BOP'19)."""
    vsd_th: tuple[float, ...] = _BOP_TH
    """VSD correctness thresholds (BOP'19)."""
    mssd_th: tuple[float, ...] = _BOP_TH
    """MSSD thresholds, fractions of the diameter (BOP'19)."""
    mspd_th_px: tuple[float, ...] = tuple(float(x) for x in np.arange(5, 51, 5))
    """MSPD thresholds in pixels at 640 px image width (errors are scaled by 640 / width)."""
    visib_bins: tuple[float, ...] = tuple(float(x) for x in np.linspace(0.0, 1.0, 11))
    """Bin edges of visible fraction for the accuracy-vs-occlusion table (Fig 6.13)."""
    device: str = "cpu"
    """'cpu' (numba/KD-tree ADD-S, torch CPU for the rest) or 'cuda' (torch)."""
    rot_tol: float = 1e-2
    """Rotations in the results with max |R R^T - I| above this are rejected rows (LM-O's own GT
    rotations are up to 2e-3 off, so the bound is looser than float32 rounding)."""


@dataclass
class TargetRecord:
    """One valid GT instance and the errors of the estimate matched to it (inf: none)."""

    scene_id: int
    im_id: int
    obj_id: int
    gt_idx: int
    visib_fract: float
    est_line: int = -1
    score: float = float("nan")
    add: float = math.inf
    adi: float = math.inf
    add_s: float = math.inf
    add_s_diam: float = math.inf
    proj: float = math.inf
    re_deg: float = math.inf
    te: float = math.inf
    mssd: float = math.inf
    mspd: float = math.inf


@dataclass
class EvalReport:
    """Everything the evaluator computed; :func:`presim.pose.report.write_report` writes it."""

    dataset: str
    results: str
    config: EvalConfig
    records: list[TargetRecord]
    per_object: dict[int, dict]
    overall: dict
    mean_over_objects: dict
    visibility: dict
    curves: dict
    rejections: list[dict]
    notes: list[str] = field(default_factory=list)


# ---- records of the evaluation steps ---------------------------------------------------------

class PairKey(NamedTuple):
    """One (estimate, GT) pair of a target: positions in :attr:`TargetCase.estimates` / ``.valid_gt``."""

    target_idx: int
    est_rank: int
    """Index of the estimate among the target's kept estimates (score order)."""
    gt_rank: int
    """Index of the GT among the target's valid GT instances (visibility order)."""


@dataclass(frozen=True)
class TargetCase:
    """A target with its valid GT instances and its kept estimates."""

    target: Target
    valid_gt: list[int]
    """gt_idx (position in scene_gt) of the ``inst_count`` most visible instances of the object."""
    estimates: list[Estimate]
    """The ``inst_count`` highest-scoring estimates (stable for equal scores: file order)."""
    visib: dict[int, float]
    """Visible fraction per candidate gt_idx (1.0 without scene_gt_info)."""
    gt: list[GtInstance]
    """The image's scene_gt instances (indexed by gt_idx)."""
    K: np.ndarray
    """(3, 3) camera matrix of the image."""


@dataclass(frozen=True)
class Pair:
    """One (estimate, GT) pair to score."""

    key: PairKey
    est: Estimate
    gt: GtInstance
    K: np.ndarray


@dataclass
class PairErrors:
    """Errors of one (estimate, GT) pair (metres, pixels, degrees)."""

    add: float
    adi: float
    add_s: float
    """``adi`` for symmetric objects, else ``add``."""
    proj: float
    re: float
    te: float
    mssd: float
    mspd: float
    vsd: list[float] | None = None
    """VSD per tau of ``EvalConfig.vsd_taus`` (None when VSD is not computed)."""


@dataclass
class ArHits:
    """BOP AR counts of one object (or all): valid GT and GT matched per threshold."""

    n: float
    mssd: np.ndarray
    mspd: np.ndarray
    vsd: np.ndarray
    """(taus, thresholds)."""

    @classmethod
    def zeros(cls, cfg: EvalConfig) -> "ArHits":
        return cls(0.0, np.zeros(len(cfg.mssd_th)), np.zeros(len(cfg.mspd_th_px)),
                   np.zeros((len(cfg.vsd_taus), len(cfg.vsd_th))))


class ObjectData:
    """Per-object data the errors need: diameter, model points (metres), symmetries, a renderer."""

    def __init__(self, ds: BopDataset, obj_id: int, cfg: EvalConfig, symmetric: bool):
        info = ds.models_info(eval=cfg.use_models_eval)[obj_id]
        self.diameter = info.diameter_m
        self.pts = np.ascontiguousarray(ds.model_mesh_m(obj_id, eval=cfg.use_models_eval).vertices)
        self.syms = symmetry_transformations(info.symmetries_discrete, info.symmetries_continuous,
                                             cfg.max_sym_disc_step)
        self.symmetric = symmetric
        self._ds, self._obj_id = ds, obj_id
        self._renderer = None

    def renderer(self):
        if self._renderer is None:
            m = self._ds.model_mesh_m(self._obj_id, eval=False)  # full mesh for rendering, as BOP
            self._renderer = MeshDepthRenderer(m.vertices, m.faces)
        return self._renderer


# ---- error computation ------------------------------------------------------------------------

def _pair_errors(od: ObjectData, R_e, t_e, R_g, t_g, K, cfg: EvalConfig) -> dict[str, np.ndarray]:
    """Errors of E (estimate, GT) pairs of one object; K (E, 3, 3)."""
    import torch  # optional dependency, imported when a batch is scored

    from presim.pose import metrics_torch as mt  # imports torch

    E = len(R_e)
    if E == 0:
        return {k: np.zeros(0) for k in ("add", "adi", "proj", "re", "te", "mssd", "mspd")}
    dev = cfg.device
    if dev.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError("--device cuda requested but torch.cuda.is_available() is False")
    Re, te_, Rg, tg = mt.as_batch(R_e, t_e, R_g, t_g, device=dev)
    pts = torch.as_tensor(od.pts, dtype=torch.float64, device=dev)
    Kt = torch.as_tensor(np.asarray(K), dtype=torch.float64, device=dev)
    out = {
        "add": mt.add(Re, te_, Rg, tg, pts),
        "proj": mt.proj(Re, te_, Rg, tg, Kt, pts),
        "re": mt.re(Re, Rg),
        "te": mt.te(te_, tg),
        "mssd": mt.mssd(Re, te_, Rg, tg, pts, od.syms),
        "mspd": mt.mspd(Re, te_, Rg, tg, Kt, pts, od.syms),
    }
    out = {k: v.cpu().numpy() for k, v in out.items()}
    if dev.startswith("cuda"):
        out["adi"] = mt.adi(Re, te_, Rg, tg, pts).cpu().numpy()
    else:
        # The grid index pays off from a few thousand poses; below, one batched KD-tree query.
        out["adi"] = (NNGrid(od.pts).adi(R_e, t_e, R_g, t_g) if E >= 3000
                      else adi_batch_kdtree(od.pts, R_e, t_e, R_g, t_g))
    return out


def _vsd_errors(od: ObjectData, ds: BopDataset, scene_id: int, im_id: int, R_e, t_e, R_g, t_g, K,
                cfg: EvalConfig) -> list[float]:
    depth = ds.read_depth_m(scene_id, im_id)
    return vsd(R_e, t_e, R_g, t_g, depth, K, cfg.vsd_delta_m, cfg.vsd_taus, True, od.diameter, od.renderer())


def _match_threshold(est_errs: list[list[float]], th: float) -> int:
    """bop_toolkit greedy matching for one target: estimates in score order, each to the unmatched
    GT with the lowest error below ``th``. est_errs[e][g] = error of estimate e vs GT g.
    Returns the number of matched GT."""
    matched: set[int] = set()
    for errs in est_errs:
        best_g, best = -1, th
        for g, err in enumerate(errs):
            if g not in matched and err < best:
                best_g, best = g, err
        if best_g >= 0:
            matched.add(best_g)
    return len(matched)


def _gt_info_or_none(ds: BopDataset, scene_id: int, notes: list[str]):
    """scene_gt_info.json of a scene, or None (visible fractions then count as 1.0) with a note."""
    try:
        return ds.scene_gt_info(scene_id)
    except FileNotFoundError:
        msg = f"scene {scene_id}: no scene_gt_info.json, visible fractions taken as 1.0"
        if msg not in notes:
            notes.append(msg)
        return None


def _default_targets(ds: BopDataset, scene_ids, notes: list[str]) -> list[Target]:
    targets = []
    for sid in scene_ids:
        info = _gt_info_or_none(ds, sid, notes) or {}
        gt = ds.scene_gt(sid)
        for im_id in sorted(gt):
            counts: dict[int, int] = {}
            infos = info.get(im_id) or [None] * len(gt[im_id])
            for inst, inf in zip(gt[im_id], infos):
                if inf is None or inf.visib_fract >= 0.1:
                    counts[inst.obj_id] = counts.get(inst.obj_id, 0) + 1
            targets += [Target(sid, im_id, o, n) for o, n in sorted(counts.items())]
    return targets


# ---- the steps of evaluate() --------------------------------------------------------------------

def select_targets(ds: BopDataset, cfg: EvalConfig, notes: list[str]) -> tuple[list[Target], set[int]]:
    """Step 1: the targets (file, or default) of the selected scenes, checked against models_info,
    and the ids of the objects scored with ADD-S in ADD(-S)."""
    models_info = ds.models_info(eval=cfg.use_models_eval)
    obj_ids = sorted(models_info)
    if cfg.targets_path is not None or (ds.root / "test_targets_bop19.json").is_file():
        targets = ds.test_targets(cfg.targets_path)
    else:
        targets = _default_targets(ds, ds.scene_ids(), notes)
        notes.append("no targets file: targets = (image, object) with instances >= 10% visible")
    if cfg.scene_ids is not None:
        keep = set(cfg.scene_ids)
        targets = [t for t in targets if t.scene_id in keep]
    if not targets:
        raise ValueError(f"{ds.root}: no evaluation targets (check --scene-ids / --targets)")
    unknown = sorted({t.obj_id for t in targets} - set(obj_ids))
    if unknown:
        default = ds.root / "test_targets_bop19.json"
        src = cfg.targets_path or (default if default.is_file() else ds.root)
        raise ValueError(f"{src}: targets reference objects {unknown} missing from "
                         f"{ds.models_dir}/models_info.json")
    unknown_sym = sorted(set(cfg.symmetric_obj_ids) - set(obj_ids))
    if unknown_sym:
        raise ValueError(f"--symmetric: objects {unknown_sym} are not in {ds.models_dir}/models_info.json "
                         f"(known: {obj_ids})")
    sym_ids = set(cfg.symmetric_obj_ids) | {o for o, i in models_info.items() if i.is_symmetric}
    return targets, sym_ids


def estimates_by_target(results: BopResults, targets: list[Target],
                        notes: list[str]) -> dict[tuple[int, int, int], list[Estimate]]:
    """Step 2: estimates grouped by (scene_id, im_id, obj_id) in file order; a note counts the
    estimates of non-targets (ignored, as BOP)."""
    by_key: dict[tuple[int, int, int], list[Estimate]] = {}
    for e in results.estimates:
        by_key.setdefault((e.scene_id, e.im_id, e.obj_id), []).append(e)
    target_keys = {(t.scene_id, t.im_id, t.obj_id) for t in targets}
    n_ignored = sum(len(v) for k, v in by_key.items() if k not in target_keys)
    if n_ignored:
        notes.append(f"{n_ignored} estimates are for (scene, image, object) that are not targets; ignored (as BOP)")
    return by_key


def target_cases(ds: BopDataset, targets: list[Target], by_key: dict[tuple[int, int, int], list[Estimate]],
                 notes: list[str]) -> list[TargetCase]:
    """Step 3: per target, the k most visible GT instances and the k best estimates (k = inst_count)."""
    cases = []
    for t in targets:
        gt_list = ds.scene_gt(t.scene_id).get(t.im_id)
        info_all = _gt_info_or_none(ds, t.scene_id, notes)
        info_list = info_all.get(t.im_id) if info_all is not None else None
        if gt_list is None:
            raise ValueError(f"{ds.scene_dir(t.scene_id) / 'scene_gt.json'}: no GT for target image {t.im_id}")
        cands = [g for g, inst in enumerate(gt_list) if inst.obj_id == t.obj_id]
        if len(cands) < t.inst_count:
            raise ValueError(f"target scene {t.scene_id} image {t.im_id} object {t.obj_id}: inst_count "
                             f"{t.inst_count} but only {len(cands)} GT instances")
        visib = {g: (info_list[g].visib_fract if info_list is not None and g < len(info_list) else 1.0) for g in cands}
        valid = sorted(cands, key=lambda g: -visib[g])[: t.inst_count]   # k most visible (stable)
        ests = sorted(by_key.get((t.scene_id, t.im_id, t.obj_id), []), key=lambda e: -e.score)[: t.inst_count]
        cases.append(TargetCase(t, valid, ests, visib, gt_list, ds.scene_camera(t.scene_id)[t.im_id].K))
    return cases


def pairs_by_object(cases: list[TargetCase]) -> dict[int, list[Pair]]:
    """Step 4: every (kept estimate, valid GT) pair of every target, grouped by object (in target order)."""
    pairs: dict[int, list[Pair]] = {}
    for ti, c in enumerate(cases):
        for r, e in enumerate(c.estimates):
            for gl, g in enumerate(c.valid_gt):
                pairs.setdefault(c.target.obj_id, []).append(Pair(PairKey(ti, r, gl), e, c.gt[g], c.K))
    return pairs


def score_pairs(pairs: dict[int, list[Pair]], objs: dict[int, ObjectData],
                cfg: EvalConfig) -> dict[PairKey, PairErrors]:
    """Step 5: ADD, ADD-S, proj, re, te, MSSD, MSPD of every pair, batched per object."""
    errors: dict[PairKey, PairErrors] = {}
    for obj_id, plist in pairs.items():
        od = objs[obj_id]
        R_e = np.stack([p.est.R for p in plist])
        t_e = np.stack([p.est.t_m for p in plist])
        R_g = np.stack([p.gt.R_m2c for p in plist])
        t_g = np.stack([p.gt.t_m2c_m for p in plist])
        K = np.stack([p.K for p in plist])
        errs = _pair_errors(od, R_e, t_e, R_g, t_g, K, cfg)
        for i, p in enumerate(plist):
            d = {k: float(v[i]) for k, v in errs.items()}
            errors[p.key] = PairErrors(add=d["add"], adi=d["adi"], add_s=d["adi"] if od.symmetric else d["add"],
                                       proj=d["proj"], re=d["re"], te=d["te"], mssd=d["mssd"], mspd=d["mspd"])
    return errors


def vsd_possible(ds: BopDataset, cases: list[TargetCase], cfg: EvalConfig, notes: list[str]) -> bool:
    """Step 6a: whether VSD is computed (``cfg.vsd``, and every evaluated image has depth)."""
    if cfg.vsd == "off":
        return False
    missing = 0
    for c in cases:
        try:
            ds.image_path(c.target.scene_id, c.target.im_id, "depth")
        except FileNotFoundError:
            missing += 1
    if missing and cfg.vsd == "on":
        raise ValueError(f"{ds.root}: VSD requested but {missing} target images have no depth image")
    if missing:
        notes.append(f"VSD / AR_VSD / AR not computed: {missing} of {len(cases)} target images have no depth")
    return missing == 0


def add_vsd(ds: BopDataset, cases: list[TargetCase], objs: dict[int, ObjectData],
            errors: dict[PairKey, PairErrors], cfg: EvalConfig) -> None:
    """Step 6b: VSD of every pair (needs the test depth map), stored in ``errors``."""
    for ti, c in enumerate(progress(cases, desc="pose-eval: VSD", unit="target")):
        t = c.target
        for r, e in enumerate(c.estimates):
            for gl, g in enumerate(c.valid_gt):
                inst = c.gt[g]
                errors[PairKey(ti, r, gl)].vsd = _vsd_errors(objs[t.obj_id], ds, t.scene_id, t.im_id, e.R, e.t_m,
                                                             inst.R_m2c, inst.t_m2c_m, c.K, cfg)


def match_add_family(ti: int, case: TargetCase, errors: dict[PairKey, PairErrors],
                     diameter_m: float) -> list[TargetRecord]:
    """Step 7: one record per valid GT; estimates in score order each take the unmatched GT with the
    lowest ADD(-S); GT left without an estimate keep infinite errors (failures)."""
    t = case.target
    recs = [TargetRecord(t.scene_id, t.im_id, t.obj_id, g, float(case.visib[g])) for g in case.valid_gt]
    taken: set[int] = set()
    for r, e in enumerate(case.estimates):
        best_g, best = -1, math.inf
        for gl in range(len(case.valid_gt)):
            if gl in taken:
                continue
            v = errors[PairKey(ti, r, gl)].add_s
            if best_g < 0 or v < best:
                best_g, best = gl, v
        if best_g < 0:
            continue
        taken.add(best_g)
        d = errors[PairKey(ti, r, best_g)]
        rec = recs[best_g]
        rec.est_line, rec.score = e.line, e.score
        rec.add, rec.adi, rec.add_s, rec.proj = d.add, d.adi, d.add_s, d.proj
        rec.add_s_diam = d.add_s / diameter_m
        rec.re_deg, rec.te, rec.mssd, rec.mspd = d.re, d.te, d.mssd, d.mspd
    return recs


def count_ar_hits(hits: ArHits, ti: int, case: TargetCase, errors: dict[PairKey, PairErrors], diameter_m: float,
                  mspd_scale: float, do_vsd: bool, cfg: EvalConfig) -> None:
    """Step 8: add one target's BOP AR counts (matched GT per threshold, bop_toolkit matching)."""
    n_est, n_gt = len(case.estimates), len(case.valid_gt)
    hits.n += n_gt

    def table(err) -> list[list[float]]:
        return [[err(errors[PairKey(ti, r, gl)]) for gl in range(n_gt)] for r in range(n_est)]

    mssd_m = table(lambda d: d.mssd / diameter_m)
    mspd_m = table(lambda d: d.mspd * mspd_scale)
    for j, th in enumerate(cfg.mssd_th):
        hits.mssd[j] += _match_threshold(mssd_m, th)
    for j, th in enumerate(cfg.mspd_th_px):
        hits.mspd[j] += _match_threshold(mspd_m, th)
    if do_vsd:
        for a in range(len(cfg.vsd_taus)):
            vm = table(lambda d: d.vsd[a])
            for j, th in enumerate(cfg.vsd_th):
                hits.vsd[a, j] += _match_threshold(vm, th)


def summarize(recs: list[TargetRecord], hits: ArHits | None, do_vsd: bool, cfg: EvalConfig) -> dict:
    """Step 9: AUCs, accuracies, mean/median errors and AR of a set of records."""
    a = lambda name: np.array([getattr(r, name) for r in recs], dtype=np.float64)  # noqa: E731
    add_, adi_, adds, addsd, pr = a("add"), a("adi"), a("add_s"), a("add_s_diam"), a("proj")
    est = np.isfinite(adds)
    s = {
        "n_targets": len(recs),
        "n_estimated": int(est.sum()),
        "auc_add_s": curves.voc_auc(adds, cfg.auc_max_m),
        "auc_add": curves.voc_auc(add_, cfg.auc_max_m),
        "auc_adi": curves.voc_auc(adi_, cfg.auc_max_m),
        "auc_add_s_diam": curves.voc_auc(addsd, 1.0),
        "acc_add_s_2cm": curves.accuracy_at(adds, cfg.acc_threshold_m),
        "acc_add_2cm": curves.accuracy_at(add_, cfg.acc_threshold_m),
        "acc_adi_2cm": curves.accuracy_at(adi_, cfg.acc_threshold_m),
        "acc_add_s_01d": curves.accuracy_at(addsd, cfg.acc_threshold_diam),
        # Same, over targets that have an estimate (the protocol of some published tables).
        "acc_add_s_01d_est": curves.accuracy_at(addsd[est], cfg.acc_threshold_diam) if est.any() else float("nan"),
        "mean_proj_px": float(np.mean(pr[est])) if est.any() else float("nan"),
        "median_re_deg": float(np.median(a("re_deg")[est])) if est.any() else float("nan"),
        "median_te_m": float(np.median(a("te")[est])) if est.any() else float("nan"),
    }
    if hits is not None and hits.n > 0:
        n = hits.n
        s["ar_mssd"] = float(np.mean(hits.mssd / n))
        s["ar_mspd"] = float(np.mean(hits.mspd / n))
        if do_vsd:
            s["ar_vsd"] = float(np.mean(hits.vsd / n))
            s["ar"] = float(np.mean([s["ar_vsd"], s["ar_mssd"], s["ar_mspd"]]))
    return s


def visibility_table(records: list[TargetRecord], cfg: EvalConfig) -> dict:
    """Step 10: accuracy vs visible fraction (Fig 6.13)."""
    edges = np.asarray(cfg.visib_bins)
    vf = np.array([r.visib_fract for r in records])
    adds_all = np.array([r.add_s for r in records])
    addsd_all = np.array([r.add_s_diam for r in records])
    bins = np.clip(np.searchsorted(edges, vf, side="right") - 1, 0, len(edges) - 2)
    visibility: dict = {"bin_edges": edges.tolist(), "n": [], "acc_add_s_2cm": [], "acc_add_s_01d": []}
    for b in range(len(edges) - 1):
        m = bins == b
        visibility["n"].append(int(m.sum()))
        visibility["acc_add_s_2cm"].append(curves.accuracy_at(adds_all[m], cfg.acc_threshold_m) if m.any() else None)
        visibility["acc_add_s_01d"].append(curves.accuracy_at(addsd_all[m], cfg.acc_threshold_diam) if m.any() else None)
    return visibility


def accuracy_curves(records: list[TargetRecord], obj_ids: list[int], cfg: EvalConfig) -> dict:
    """Step 11: accuracy-threshold curves per object and for all (Figs 6.5, 6.6, diameter-normalised)."""
    th_cm = np.linspace(0.0, cfg.auc_max_m, 101)
    th_d = np.linspace(0.0, 1.0, 101)
    th_px = np.linspace(0.0, cfg.proj_max_px, 101)
    curve_data: dict = {"add_s_m": {"thresholds": th_cm.tolist()}, "add_s_diam": {"thresholds": th_d.tolist()},
                        "proj_px": {"thresholds": th_px.tolist()}}
    for label, recs in [(str(o), [r for r in records if r.obj_id == o]) for o in obj_ids] + [("all", records)]:
        curve_data["add_s_m"][label] = curves.accuracy_curve([r.add_s for r in recs], th_cm).tolist()
        curve_data["add_s_diam"][label] = curves.accuracy_curve([r.add_s_diam for r in recs], th_d).tolist()
        curve_data["proj_px"][label] = curves.accuracy_curve([r.proj for r in recs], th_px).tolist()
    return curve_data


def _mspd_scale(ds: BopDataset, notes: list[str]) -> float:
    """MSPD thresholds are for 640 px wide images: errors are scaled by 640 / width."""
    try:
        width = ds.camera().K.width
    except FileNotFoundError:
        width = 640
        notes.append("no camera.json: MSPD normalised assuming 640 px image width")
    return 640.0 / width


# ---- main ---------------------------------------------------------------------------------------

def evaluate(ds: BopDataset, results: BopResults, cfg: EvalConfig = EvalConfig()) -> EvalReport:
    """Score ``results`` on ``ds``; see the module doc for the protocol and the steps above."""
    notes: list[str] = []
    targets, sym_ids = select_targets(ds, cfg, notes)
    by_key = estimates_by_target(results, targets, notes)
    cases = target_cases(ds, targets, by_key, notes)
    objs: dict[int, ObjectData] = {}
    for c in cases:
        if c.target.obj_id not in objs:
            objs[c.target.obj_id] = ObjectData(ds, c.target.obj_id, cfg, c.target.obj_id in sym_ids)
    mspd_scale = _mspd_scale(ds, notes)
    errors = score_pairs(pairs_by_object(cases), objs, cfg)
    do_vsd = vsd_possible(ds, cases, cfg, notes)
    if do_vsd:
        add_vsd(ds, cases, objs, errors, cfg)

    records: list[TargetRecord] = []
    hits: dict[int, ArHits] = {}
    for ti, c in enumerate(cases):
        diameter = objs[c.target.obj_id].diameter
        records += match_add_family(ti, c, errors, diameter)
        h = hits.setdefault(c.target.obj_id, ArHits.zeros(cfg))
        count_ar_hits(h, ti, c, errors, diameter, mspd_scale, do_vsd, cfg)

    rej_by_obj: dict[int, int] = {}
    for rj in results.rejections:
        if rj.obj_id is not None:
            rej_by_obj[rj.obj_id] = rej_by_obj.get(rj.obj_id, 0) + 1
    per_object: dict[int, dict] = {}
    for obj_id in sorted({r.obj_id for r in records}):
        s = summarize([r for r in records if r.obj_id == obj_id], hits.get(obj_id), do_vsd, cfg)
        s["symmetric"] = obj_id in sym_ids
        s["diameter_m"] = objs[obj_id].diameter
        s["n_rejected_rows"] = rej_by_obj.get(obj_id, 0)
        per_object[obj_id] = s
    all_hits = ArHits(*(sum(getattr(h, k) for h in hits.values()) for k in ("n", "mssd", "mspd", "vsd")))
    overall = summarize(records, all_hits, do_vsd, cfg)
    overall["n_rejected_rows"] = len(results.rejections)
    overall["n_estimates_read"] = len(results.estimates)
    first = next(iter(per_object.values()))
    keys = [k for k in first if isinstance(first[k], float) and k != "diameter_m"]
    mean_over_objects = {k: float(np.mean([s[k] for s in per_object.values()])) for k in keys}

    rejections = [{"line": r.line, "reason": r.reason, "obj_id": r.obj_id, "text": r.text} for r in results.rejections]
    return EvalReport(dataset=str(ds.root), results=str(results.path), config=cfg, records=records,
                      per_object=per_object, overall=overall, mean_over_objects=mean_over_objects,
                      visibility=visibility_table(records, cfg), curves=accuracy_curves(records, list(per_object), cfg),
                      rejections=rejections, notes=notes)


def evaluate_files(dataset_dir: str | Path, results_csv: str | Path, cfg: EvalConfig = EvalConfig()) -> EvalReport:
    """Read a BOP dataset and a results CSV, then :func:`evaluate`."""
    ds = BopDataset(dataset_dir, split=cfg.split)
    obj_ids = ds.models_info(eval=cfg.use_models_eval).keys()
    res = read_bop_results(results_csv, known_obj_ids=obj_ids, rot_tol=cfg.rot_tol)
    return evaluate(ds, res, cfg)


def report_to_dict(rep: EvalReport) -> dict:
    """JSON-ready dict (inf/nan -> None)."""
    def clean(x):
        if isinstance(x, float):
            return x if math.isfinite(x) else None
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, Path):
            return str(x)
        if isinstance(x, (np.floating, np.integer)):
            return clean(x.item())
        return x
    cfg = asdict(rep.config)
    return clean({"dataset": rep.dataset, "results": rep.results, "config": cfg, "overall": rep.overall,
                  "mean_over_objects": rep.mean_over_objects, "per_object": rep.per_object,
                  "visibility": rep.visibility, "curves": rep.curves, "rejections": rep.rejections,
                  "notes": rep.notes})
