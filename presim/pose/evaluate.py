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

import numpy as np

from presim.datasets.bop_reader import BopDataset, Target
from presim.pose import curves
from presim.pose.metrics import symmetry_transformations
from presim.pose.results import BopResults, read_bop_results

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


# ---- error computation ------------------------------------------------------------------------

class _ObjectData:
    def __init__(self, ds: BopDataset, obj_id: int, cfg: EvalConfig, symmetric: bool):
        info = ds.models_info(eval=cfg.use_models_eval)[obj_id]
        self.diameter = info.diameter_m
        self.pts = np.ascontiguousarray(ds.load_model(obj_id, eval=cfg.use_models_eval).pts)
        self.syms = symmetry_transformations(info, cfg.max_sym_disc_step)
        self.symmetric = symmetric
        self._ds, self._obj_id = ds, obj_id
        self._renderer = None

    def renderer(self):
        if self._renderer is None:
            from presim.pose.metrics import MeshDepthRenderer
            m = self._ds.load_model(self._obj_id, eval=False)  # full mesh for rendering, as BOP
            self._renderer = MeshDepthRenderer(m.pts, m.faces)
        return self._renderer


def _pair_errors(od: _ObjectData, R_e, t_e, R_g, t_g, K, cfg: EvalConfig) -> dict[str, np.ndarray]:
    """Errors of E (estimate, GT) pairs of one object; K (E, 3, 3)."""
    import torch

    from presim.pose import metrics_torch as mt

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
        from presim.pose.nn_grid import NNGrid, adi_batch_kdtree
        # The grid index pays off from a few thousand poses; below, one batched KD-tree query.
        out["adi"] = (NNGrid(od.pts).adi(R_e, t_e, R_g, t_g) if E >= 3000
                      else adi_batch_kdtree(od.pts, R_e, t_e, R_g, t_g))
    return out


def _vsd_errors(od: _ObjectData, ds: BopDataset, scene_id: int, im_id: int, R_e, t_e, R_g, t_g, K,
                cfg: EvalConfig) -> list[float]:
    from presim.pose.metrics import vsd
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


# ---- main ---------------------------------------------------------------------------------------

def evaluate(ds: BopDataset, results: BopResults, cfg: EvalConfig = EvalConfig()) -> EvalReport:
    """Score ``results`` on ``ds``; see the module doc for the protocol."""
    notes: list[str] = []
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

    # Estimates by target key, score-descending (stable for equal scores: file order).
    by_key: dict[tuple[int, int, int], list] = {}
    for e in results.estimates:
        by_key.setdefault((e.scene_id, e.im_id, e.obj_id), []).append(e)
    target_keys = {(t.scene_id, t.im_id, t.obj_id) for t in targets}
    n_ignored = sum(len(v) for k, v in by_key.items() if k not in target_keys)
    if n_ignored:
        notes.append(f"{n_ignored} estimates are for (scene, image, object) that are not targets; ignored (as BOP)")

    # Collect (estimate, GT) pairs per object.
    objs: dict[int, _ObjectData] = {}
    pairs: dict[int, list] = {}   # obj -> list of (target_idx, est_rank, gt_local, est, gt_inst, K)
    target_info = []              # per target: (target, valid gt idxs, kept estimates, im width)
    for ti, t in enumerate(targets):
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
        K = ds.scene_camera(t.scene_id)[t.im_id].K
        target_info.append((t, valid, ests, visib))
        if t.obj_id not in objs:
            objs[t.obj_id] = _ObjectData(ds, t.obj_id, cfg, t.obj_id in sym_ids)
        for r, e in enumerate(ests):
            for gl, g in enumerate(valid):
                pairs.setdefault(t.obj_id, []).append((ti, r, gl, e, gt_list[g], K))

    try:
        width = ds.camera().K.width
    except FileNotFoundError:
        width = 640
        notes.append("no camera.json: MSPD normalised assuming 640 px image width")
    mspd_scale = 640.0 / width

    # Errors, batched per object.
    err_of: dict[tuple[int, int, int], dict] = {}
    for obj_id, plist in pairs.items():
        od = objs[obj_id]
        R_e = np.stack([p[3].R for p in plist])
        t_e = np.stack([p[3].t_m for p in plist])
        R_g = np.stack([p[4].R_m2c for p in plist])
        t_g = np.stack([p[4].t_m2c_m for p in plist])
        K = np.stack([p[5] for p in plist])
        errs = _pair_errors(od, R_e, t_e, R_g, t_g, K, cfg)
        for i, p in enumerate(plist):
            d = {k: float(v[i]) for k, v in errs.items()}
            d["add_s"] = d["adi"] if od.symmetric else d["add"]
            err_of[(p[0], p[1], p[2])] = d

    # VSD needs depth for every evaluated image.
    do_vsd = False
    if cfg.vsd != "off":
        missing = 0
        for t, *_ in target_info:
            try:
                ds.image_path(t.scene_id, t.im_id, "depth")
            except FileNotFoundError:
                missing += 1
        if missing and cfg.vsd == "on":
            raise ValueError(f"{ds.root}: VSD requested but {missing} target images have no depth image")
        do_vsd = missing == 0
        if missing:
            notes.append(f"VSD / AR_VSD / AR not computed: {missing} of {len(target_info)} target images have no depth")
    if do_vsd:
        for ti, (t, valid, ests, _) in enumerate(target_info):
            gt_list = ds.scene_gt(t.scene_id)[t.im_id]
            K = ds.scene_camera(t.scene_id)[t.im_id].K
            for r, e in enumerate(ests):
                for gl, g in enumerate(valid):
                    inst = gt_list[g]
                    err_of[(ti, r, gl)]["vsd"] = _vsd_errors(objs[t.obj_id], ds, t.scene_id, t.im_id, e.R, e.t_m,
                                                             inst.R_m2c, inst.t_m2c_m, K, cfg)

    # ADD-family matching and per-GT records.
    records: list[TargetRecord] = []
    bop_hits: dict[int, dict[str, np.ndarray]] = {}
    for ti, (t, valid, ests, visib) in enumerate(target_info):
        od = objs[t.obj_id]
        recs = [TargetRecord(t.scene_id, t.im_id, t.obj_id, g, float(visib[g])) for g in valid]
        taken: set[int] = set()
        for r, e in enumerate(ests):
            best_g, best = -1, math.inf
            for gl in range(len(valid)):
                if gl in taken:
                    continue
                v = err_of[(ti, r, gl)]["add_s"]
                if best_g < 0 or v < best:
                    best_g, best = gl, v
            if best_g < 0:
                continue
            taken.add(best_g)
            d = err_of[(ti, r, best_g)]
            rec = recs[best_g]
            rec.est_line, rec.score = e.line, e.score
            rec.add, rec.adi, rec.add_s, rec.proj = d["add"], d["adi"], d["add_s"], d["proj"]
            rec.add_s_diam = d["add_s"] / od.diameter
            rec.re_deg, rec.te, rec.mssd, rec.mspd = d["re"], d["te"], d["mssd"], d["mspd"]
        records += recs
        # BOP AR: matched-GT counts per threshold.
        h = bop_hits.setdefault(t.obj_id, {"n": np.zeros(1), "mssd": np.zeros(len(cfg.mssd_th)),
                                           "mspd": np.zeros(len(cfg.mspd_th_px)),
                                           "vsd": np.zeros((len(cfg.vsd_taus), len(cfg.vsd_th)))})
        h["n"][0] += len(valid)
        mssd_m = [[err_of[(ti, r, gl)]["mssd"] / od.diameter for gl in range(len(valid))] for r in range(len(ests))]
        mspd_m = [[err_of[(ti, r, gl)]["mspd"] * mspd_scale for gl in range(len(valid))] for r in range(len(ests))]
        for j, th in enumerate(cfg.mssd_th):
            h["mssd"][j] += _match_threshold(mssd_m, th)
        for j, th in enumerate(cfg.mspd_th_px):
            h["mspd"][j] += _match_threshold(mspd_m, th)
        if do_vsd:
            for a in range(len(cfg.vsd_taus)):
                vm = [[err_of[(ti, r, gl)]["vsd"][a] for gl in range(len(valid))] for r in range(len(ests))]
                for j, th in enumerate(cfg.vsd_th):
                    h["vsd"][a, j] += _match_threshold(vm, th)

    rej_by_obj: dict[int, int] = {}
    for rj in results.rejections:
        if rj.obj_id is not None:
            rej_by_obj[rj.obj_id] = rej_by_obj.get(rj.obj_id, 0) + 1

    def summarize(recs: list[TargetRecord], hits: dict | None) -> dict:
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
        if hits is not None and hits["n"][0] > 0:
            n = hits["n"][0]
            s["ar_mssd"] = float(np.mean(hits["mssd"] / n))
            s["ar_mspd"] = float(np.mean(hits["mspd"] / n))
            if do_vsd:
                s["ar_vsd"] = float(np.mean(hits["vsd"] / n))
                s["ar"] = float(np.mean([s["ar_vsd"], s["ar_mssd"], s["ar_mspd"]]))
        return s

    per_object: dict[int, dict] = {}
    for obj_id in sorted({r.obj_id for r in records}):
        recs = [r for r in records if r.obj_id == obj_id]
        s = summarize(recs, bop_hits.get(obj_id))
        s["symmetric"] = obj_id in sym_ids
        s["diameter_m"] = objs[obj_id].diameter
        s["n_rejected_rows"] = rej_by_obj.get(obj_id, 0)
        per_object[obj_id] = s
    all_hits = {k: sum(h[k] for h in bop_hits.values()) for k in ("n", "mssd", "mspd", "vsd")}
    overall = summarize(records, all_hits)
    overall["n_rejected_rows"] = len(results.rejections)
    overall["n_estimates_read"] = len(results.estimates)
    keys = [k for k in next(iter(per_object.values())) if isinstance(next(iter(per_object.values()))[k], float)
            and k != "diameter_m"]
    mean_over_objects = {k: float(np.mean([s[k] for s in per_object.values()])) for k in keys}

    # Accuracy vs visible fraction (Fig 6.13).
    edges = np.asarray(cfg.visib_bins)
    vf = np.array([r.visib_fract for r in records])
    adds_all = np.array([r.add_s for r in records])
    addsd_all = np.array([r.add_s_diam for r in records])
    bins = np.clip(np.searchsorted(edges, vf, side="right") - 1, 0, len(edges) - 2)
    visibility = {"bin_edges": edges.tolist(), "n": [], "acc_add_s_2cm": [], "acc_add_s_01d": []}
    for b in range(len(edges) - 1):
        m = bins == b
        visibility["n"].append(int(m.sum()))
        visibility["acc_add_s_2cm"].append(curves.accuracy_at(adds_all[m], cfg.acc_threshold_m) if m.any() else None)
        visibility["acc_add_s_01d"].append(curves.accuracy_at(addsd_all[m], cfg.acc_threshold_diam) if m.any() else None)

    # Curves (Figs 6.5, 6.6 and the diameter-normalised one).
    th_cm = np.linspace(0.0, cfg.auc_max_m, 101)
    th_d = np.linspace(0.0, 1.0, 101)
    th_px = np.linspace(0.0, cfg.proj_max_px, 101)
    curve_data = {"add_s_m": {"thresholds": th_cm.tolist()}, "add_s_diam": {"thresholds": th_d.tolist()},
                  "proj_px": {"thresholds": th_px.tolist()}}
    for label, recs in [(str(o), [r for r in records if r.obj_id == o]) for o in per_object] + [("all", records)]:
        curve_data["add_s_m"][label] = curves.accuracy_curve([r.add_s for r in recs], th_cm).tolist()
        curve_data["add_s_diam"][label] = curves.accuracy_curve([r.add_s_diam for r in recs], th_d).tolist()
        curve_data["proj_px"][label] = curves.accuracy_curve([r.proj for r in recs], th_px).tolist()

    rejections = [{"line": r.line, "reason": r.reason, "obj_id": r.obj_id, "text": r.text} for r in results.rejections]
    return EvalReport(dataset=str(ds.root), results=str(results.path), config=cfg, records=records,
                      per_object=per_object, overall=overall, mean_over_objects=mean_over_objects,
                      visibility=visibility, curves=curve_data, rejections=rejections, notes=notes)


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
