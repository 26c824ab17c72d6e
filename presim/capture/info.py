"""Summary of a scene (``presim info``): sizes, intrinsics, depth coverage, extent, trajectory, floor."""

from __future__ import annotations

import numpy as np

from presim.capture.scene import Scene
from presim.capture.store import load_scene, read_refined_poses

__all__ = ["scene_info", "format_info"]


def scene_info(scene: Scene, max_sample_frames: int = 50) -> dict:
    """JSON-ready summary of ``scene``.

    Depth coverage (mean fraction of valid depth pixels) is measured on at most
    ``max_sample_frames`` evenly spaced frames, so a 1000-frame scene stays quick.
    """
    n = len(scene)
    fx = np.array([K.fx for K in scene.intrinsics])
    fy = np.array([K.fy for K in scene.intrinsics])
    K0 = scene.intrinsics[0]
    sample = np.unique(np.linspace(0, n - 1, min(n, max_sample_frames)).round().astype(int))
    cov, dmin, dmax = [], np.inf, 0.0
    for i in sample:
        d = scene.depth(int(i), refined=False)
        v = (d > 0) & np.isfinite(d)
        cov.append(float(v.mean()))
        if v.any():
            dmin, dmax = min(dmin, float(d[v].min())), max(dmax, float(d[v].max()))
    pts = scene.points
    extent = None
    xyz = np.asarray(pts.xyz, dtype=np.float64) if pts is not None and len(pts) else np.zeros((0, 3))
    xyz = xyz[np.isfinite(xyz).all(axis=1)]  # float64: hi - lo of float32 points never overflows
    if len(xyz):
        lo, hi = xyz.min(axis=0), xyz.max(axis=0)
        extent = {"min_m": [round(float(x), 4) for x in lo], "max_m": [round(float(x), 4) for x in hi],
                  "size_m": [round(float(x), 4) for x in hi - lo]}
    stamps = scene.stamps_s
    return {
        "path": None if scene.path is None else str(scene.path),
        "source": scene.meta.source,
        "source_format": scene.meta.source_format,
        "importer_version": scene.meta.importer_version,
        "created_utc": scene.meta.created_utc,
        "num_frames": n,
        "resolution_wh": [scene.width, scene.height],
        "intrinsics": {
            "shared": bool(len({K for K in scene.intrinsics}) == 1),
            "fx": [float(fx.min()), float(fx.max())], "fy": [float(fy.min()), float(fy.max())],
            "cx": K0.cx, "cy": K0.cy, "hfov_deg": round(K0.hfov_deg, 2), "vfov_deg": round(K0.vfov_deg, 2),
        },
        "duration_s": float(stamps.max() - stamps.min()) if n > 1 else 0.0,
        "depth_coverage": {"mean_valid_frac": float(np.mean(cov)), "min_valid_frac": float(np.min(cov)),
                           "sampled_frames": int(len(sample)),
                           "range_m": [dmin, dmax] if dmax > 0 else None},
        "points": 0 if pts is None else len(pts),
        "extent": extent,
        "trajectory_length_m": scene.trajectory_length_m(),
        "floor": None if scene.floor is None else {
            "normal": list(scene.floor.normal), "offset_m": scene.floor.offset,
            "inlier_frac": scene.floor.inlier_frac},
        "gravity_world": np.asarray(scene.gravity_world, dtype=float).round(6).tolist(),
        "transforms": [t.name for t in scene.meta.transforms],
        "objects": [{"obj_id": int(o.obj_id), "name": o.name,
                     "position_m": [round(float(x), 4) for x in np.asarray(o.T_world_obj)[:3, 3]],
                     "model": o.model_path} for o in scene.objects],
        "refined_depth": scene.has_refined_depth,
        "fused_depth": scene.has_fused_depth,
        "poses": _poses_info(scene),
        "notes": list(scene.meta.notes),
    }


def _poses_info(scene: Scene) -> dict:
    """Which poses are in use, and how far ``presim align`` moved each frame from the given pose."""
    out: dict = {"in_use": scene.poses_source, "refined_available": False}
    if scene.path is None:
        return out
    rec = read_refined_poses(scene.path, scene.frame_ids)
    if rec is None:
        return out
    T_ref, prov = rec
    T_given = load_scene(scene.path, poses="given").T_world_cam
    dt = np.linalg.norm(T_ref[:, :3, 3] - T_given[:, :3, 3], axis=1)
    Rrel = np.einsum("nji,njk->nik", T_given[:, :3, :3], T_ref[:, :3, :3])
    dr = np.degrees(np.arccos(np.clip((np.trace(Rrel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    st = prov.get("stats", {})
    frames = {r.get("frame_id"): r for r in prov.get("frames", []) if isinstance(r, dict)}
    kept = st.get("kept_given", {})
    sig = [r["sigma_trans_m"] for r in frames.values() if r.get("sigma_trans_m") is not None]
    sig_r = [r["sigma_rot_deg"] for r in frames.values() if r.get("sigma_rot_deg") is not None]
    out.update({
        "refined_available": True,
        "kept_given": {k: list(v) for k, v in kept.items()} if isinstance(kept, dict) else {},
        "sigma_m": {"median": float(np.median(sig)), "max": float(np.max(sig))} if sig else None,
        "sigma_deg": {"median": float(np.median(sig_r)), "max": float(np.max(sig_r))} if sig_r else None,
        "change_m": {"median": float(np.median(dt)), "max": float(dt.max())},
        "change_deg": {"median": float(np.median(dr)), "max": float(dr.max())},
        "transfer_px": [st.get("transfer_px_before", {}).get("median"), st.get("transfer_px_after", {}).get("median")],
        "auto_matching": st.get("auto_matching"),
        "per_frame": [{"frame_id": f, "dt_m": round(float(a), 6), "dr_deg": round(float(b), 5),
                       **{k: v for k, v in frames.get(f, {}).items() if k not in ("frame_id", "dt_m", "dr_deg")}}
                      for f, a, b in zip(scene.frame_ids, dt, dr)],
    })
    return out


def format_info(info: dict) -> str:
    """Human-readable text of :func:`scene_info`."""
    i = info
    intr = i["intrinsics"]
    fx = intr["fx"]
    fx_s = f"{fx[0]:.2f}" if fx[0] == fx[1] else f"{fx[0]:.2f}-{fx[1]:.2f}"
    cov = i["depth_coverage"]
    lines = [
        f"scene       {i['path'] or '(not saved)'}",
        f"source      {i['source']} ({i['source_format']}, importer v{i['importer_version']})",
        f"frames      {i['num_frames']} over {i['duration_s']:.2f} s",
        f"resolution  {i['resolution_wh'][0]}x{i['resolution_wh'][1]}",
        f"intrinsics  fx {fx_s} fy {intr['fy'][0]:.2f} cx {intr['cx']:.2f} cy {intr['cy']:.2f} "
        f"(hfov {intr['hfov_deg']:.1f} deg, {'shared' if intr['shared'] else 'per frame'})",
        f"depth       {cov['mean_valid_frac']:.1%} valid on average (min {cov['min_valid_frac']:.1%}, "
        f"{cov['sampled_frames']} frames sampled)"
        + (f", range {cov['range_m'][0]:.2f}-{cov['range_m'][1]:.2f} m" if cov["range_m"] else ""),
    ]
    if i["extent"]:
        e = i["extent"]
        lo = ", ".join(f"{x:.2f}" for x in e["min_m"])
        hi = ", ".join(f"{x:.2f}" for x in e["max_m"])
        lines.append(f"extent      {e['size_m'][0]:.2f} x {e['size_m'][1]:.2f} x {e['size_m'][2]:.2f} m "
                     f"({i['points']} points; from ({lo}) to ({hi}))")
    else:
        lines.append("extent      (no point cloud)")
    lines.append(f"trajectory  {i['trajectory_length_m']:.2f} m")
    if i["floor"]:
        f = i["floor"]
        lines.append(f"floor       normal {np.round(f['normal'], 4).tolist()} offset {f['offset_m']:.4f} m "
                     f"({f['inlier_frac']:.0%} of points)")
    else:
        lines.append("floor       none")
    lines.append(f"gravity     {i['gravity_world']}")
    if i["transforms"]:
        lines.append(f"transforms  {', '.join(i['transforms'])}")
    lines.append(f"objects     {len(i['objects'])}" + "".join(
        f"\n  {o['obj_id']:>4} {o['name']} at {o['position_m']}" + ("" if o["model"] else " (no model)")
        for o in i["objects"]))
    lines.append(f"refined     {'yes' if i['refined_depth'] else 'no'}")
    lines.append(f"fused depth {'yes' if i.get('fused_depth') else 'no'}")
    ps = i.get("poses")
    if ps:
        if not ps["refined_available"]:
            lines.append(f"poses       {ps['in_use']} (no refined poses; `presim align` makes them)")
        else:
            cm, cd = ps["change_m"], ps["change_deg"]
            tp = ps["transfer_px"]
            tp_s = f"; feature transfer error {tp[0]:.2f} -> {tp[1]:.2f} px" if None not in tp else ""
            lines.append(f"poses       {ps['in_use']} in use; refined moved the cameras median {cm['median'] * 100:.2f} cm / "
                         f"{cd['median']:.2f} deg, max {cm['max'] * 100:.2f} cm / {cd['max']:.2f} deg{tp_s}")
            worst = sorted(ps["per_frame"], key=lambda r: -r["dt_m"])[:5]
            lines.append("  largest   " + ", ".join(f"{r['frame_id']} {r['dt_m'] * 100:.2f} cm/{r['dr_deg']:.2f} deg"
                                                   for r in worst) + " (per frame: --json)")
            if ps.get("sigma_m"):
                sm, sd = ps["sigma_m"], ps["sigma_deg"]
                lines.append(f"  uncertainty of the refined poses (1 sigma) median {sm['median'] * 1000:.2f} mm / "
                             f"{sd['median']:.3f} deg, max {sm['max'] * 1000:.2f} mm / {sd['max']:.3f} deg")
            am = ps.get("auto_matching")
            if isinstance(am, dict) and "message" in am:
                head = ("auto rule FIRED, given poses too noisy for distance neighbours" if am.get("fired")
                        else "auto rule not fired")
                lines.append(f"  matching  {head}: {am['message']}; used {am.get('appearance_neighbours')} appearance neighbours, "
                             f"{am.get('rematch_rounds')} second-pass round(s)")
            for reason, ids in ps.get("kept_given", {}).items():
                more = f" and {len(ids) - 6} more" if len(ids) > 6 else ""
                lines.append(f"  kept given {len(ids)} frame(s), {reason.removeprefix('given: ')}: "
                             f"{', '.join(ids[:6])}{more}")
    for n in i["notes"]:
        lines.append(f"note        {n}")
    return "\n".join(lines)
