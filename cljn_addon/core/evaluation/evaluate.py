"""Evaluation on held-out meshes against the classic tools (METHOD.md protocol, extended).

Per noise level and averaged, every baseline's neighbourhood tuned per level and shared by
all shapes, as the paper does:
- positions: Chamfer and Point2Surface of the noisy input, the PCA-plane filter, CGAL's jet
  smoothing (when the `cgal` package is installed) and ours; "never worse than the input"
  is checked per cloud;
- origin normals: MSAE against the normal of the face each point was sampled from, for tuned
  PCA, ours in normals-only mode (`estimate_normals`: the normal at each input point, the
  mode scored on this metric) and the floor no method can pass (`metrics.msae_floor_normals`),
  and the share of the PCA-to-floor gap we close; the joint mode's normals (placed at the
  output points) are reported beside them;
- output normals: MSAE of each output normal against the clean surface's normal at the point
  nearest its output position (what shading and reconstruction see), against the classic
  pipeline "jet smoothing (else the plane filter), then PCA normals of the smoothed cloud";
- sign agreement with the outward truth, per shape, on closed meshes, each mode against the
  truth where its normals sit: normals-only mode against each input point's face of origin,
  beside that metric's ceiling (the most any method can reach: `metrics.sign_ceiling_normals`;
  below 100% where a part is thinner than the noise); the denoise's normals against the clean
  surface at the point nearest each output position (a flipped patch in the output's shading).
  The denoise's normals against the faces of origin are kept beside them ("joint"): near an
  edge a point put back on the other face carries that face's normal, at right angles to its
  origin's, which that metric counts as a miss.
"""
from __future__ import annotations

import time

import numpy as np

from ..config import TEST_NOISE_LEVELS
from ..infer import denoise, estimate_normals
from .baselines import jet_smooth, jet_smoothing_available, pca_normals, pca_projection_filter
from .metrics import MeshDistance, chamfer, floor_and_ceiling_normals, msae, sharp_feature_mask, sign_agreement
from .shapes import normalise_unit_diagonal, sample_mesh, signed_volume

PCA_K = (10, 20, 40, 60, 100, 150, 200)
FILTER_K = (20, 40, 60, 100, 150, 200)
JET_K = (15, 30, 60, 120)
PIPELINE_PCA_K = (10, 20, 40, 60, 100)


def is_closed_and_consistent(faces) -> bool:
    """Every edge shared by exactly two faces that run it in opposite directions: only then
    are the face normals a trustworthy outward truth."""
    f = np.asarray(faces, np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1
    key = directed[:, 0] * n + directed[:, 1]
    reverse = directed[:, 1] * n + directed[:, 0]
    unique, counts = np.unique(key, return_counts=True)
    return bool(np.all(counts == 1) and np.all(np.isin(reverse, unique)))


def prepare_shape(vertices, faces, n_points, seed):
    v = normalise_unit_diagonal(np.asarray(vertices, np.float64))
    f = np.asarray(faces, np.int64)
    if signed_volume(v, f) < 0:          # outward truth for consistently wound closed meshes
        f = f[:, ::-1].copy()
    clean, normals, _ = sample_mesh(v, f, n_points, np.random.default_rng(seed))
    return v, f, clean, normals


def noisy_cloud(clean, level, seed, level_index, shape_index):
    """The eval's noisy cloud of one shape at one level (its own seed per level and shape), so
    a study script can rebuild exactly the clouds of an eval run."""
    rng = np.random.default_rng(seed + 1000 * level_index + shape_index)
    return clean + rng.normal(scale=level, size=clean.shape)


def _tune(candidates, score):
    """(best candidate, its result list) for score(candidate) -> (mean score, per-shape results)."""
    scored = {k: score(k) for k in candidates}
    best = min(scored, key=lambda k: scored[k][0])
    return best, scored[best][1]


def _classic_filters(clouds, prepared, tune):
    """Tuned PCA-plane filter and jet smoothing outputs per cloud: {name: (k, [outputs])}."""
    def by_chamfer(fn):
        def score(k):
            outs = [fn(c, k) for c in clouds]
            return np.mean([chamfer(o, s["clean"]) for o, s in zip(outs, prepared)]), outs
        return score

    filters = {"plane": _tune(FILTER_K if tune else (60,), by_chamfer(pca_projection_filter))}
    if jet_smoothing_available():
        filters["jet"] = _tune(JET_K if tune else (30,), by_chamfer(jet_smooth))
    return filters


def evaluate(shapes, model, levels=TEST_NOISE_LEVELS, n_points=50_000, iterations=4, seed=0,
             log=print, tune=True, known_noise=False):
    """shapes: list of (name, vertices, faces). Returns a dict of per-level rows and means.
    known_noise: hand the engine the true sigma (`noise_sigma`), as a user who knows the
    scanner's noise would; by default it estimates the noise from each cloud."""
    prepared = []
    for i, (name, v, f) in enumerate(shapes):
        v, f, clean, normals = prepare_shape(v, f, n_points, seed + i)
        prepared.append(dict(name=name, v=v, f=f, clean=clean, normals=normals, closed=is_closed_and_consistent(f),
                             sharp=sharp_feature_mask(clean, normals), dist=MeshDistance(v, f)))
    rows = []
    for li, level in enumerate(levels):
        clouds = [noisy_cloud(shape["clean"], level, seed, li, si) for si, shape in enumerate(prepared)]
        # Classic baselines: one neighbourhood size per level, shared by every shape.
        k_pca, _ = _tune(PCA_K if tune else (60,), lambda k: (
            np.mean([msae(pca_normals(c, k), s["normals"]) for c, s in zip(clouds, prepared)]), None))
        filters = _classic_filters(clouds, prepared, tune)
        smoothed = filters.get("jet", filters["plane"])[1]
        truth_smoothed = [s["dist"].nearest(o)[1] for o, s in zip(smoothed, prepared)]
        k_pipe, pipe_normals = _tune(PIPELINE_PCA_K if tune else (20,), lambda k: (lambda outs: (
            np.mean([msae(n, t) for n, t in zip(outs, truth_smoothed)]), outs))([pca_normals(o, k) for o in smoothed]))
        per_shape = []
        for si, (cloud, shape) in enumerate(zip(clouds, prepared)):
            pca_n = pca_normals(cloud, k_pca)
            t0 = time.time()
            res = denoise(cloud, model, iterations=iterations, orientation="outward", seed=seed,
                          noise_sigma=level if known_noise else None)
            seconds = time.time() - t0
            normals_only = estimate_normals(cloud, model, orientation="outward", seed=seed,
                                            noise_sigma=level if known_noise else None).normals
            sharp = shape["sharp"]
            floor_n, ceiling_n = floor_and_ceiling_normals(cloud, shape["v"], shape["f"], level)
            p2s_ours, truth_out = shape["dist"].nearest(res.points)
            # Outward truth exists only for closed, consistently wound meshes.
            sign = sign_agreement if shape["closed"] else lambda *_: float("nan")
            entry = {
                "shape": shape["name"],
                "msae_pca": msae(pca_n, shape["normals"]),
                "msae_ours": msae(normals_only, shape["normals"]),
                "msae_joint": msae(res.normals, shape["normals"]),
                "msae_floor": msae(floor_n, shape["normals"]),
                "sharp_msae_pca": msae(pca_n, shape["normals"], sharp),
                "sharp_msae_ours": msae(normals_only, shape["normals"], sharp),
                "out_msae_ours": msae(res.normals, truth_out),
                "out_msae_classic": msae(pipe_normals[si], truth_smoothed[si]),
                "cd_noisy": chamfer(cloud, shape["clean"]),
                "cd_ours": chamfer(res.points, shape["clean"]),
                "p2s_noisy": float(shape["dist"].distance(cloud).mean()),
                "p2s_ours": float(p2s_ours.mean()),
                "sign_ours": sign(normals_only, shape["normals"]),
                "sign_joint": sign(res.normals, shape["normals"]),
                "sign_ceiling": sign(ceiling_n, shape["normals"]),
                "sign_out": sign(res.normals, truth_out),
                "noise_sigma_est": res.noise_sigma,
                "iterations_run": float(res.iterations),
                "seconds": seconds,
            }
            for fname, (_, outs) in filters.items():
                entry[f"cd_{fname}"] = chamfer(outs[si], shape["clean"])
                entry[f"p2s_{fname}"] = float(shape["dist"].distance(outs[si]).mean())
            per_shape.append(entry)
            log(f"  level {level * 100:.1f}% {shape['name']}: MSAE ours {entry['msae_ours']:.4f} "
                f"(joint {entry['msae_joint']:.4f}) pca {entry['msae_pca']:.4f}; out-MSAE ours {entry['out_msae_ours']:.4f} classic "
                f"{entry['out_msae_classic']:.4f}; CD x1e5 ours {entry['cd_ours'] * 1e5:.2f} noisy "
                f"{entry['cd_noisy'] * 1e5:.2f} " + " ".join(
                    f"{f} {entry[f'cd_{f}'] * 1e5:.2f}" for f in filters)
                + f"; sign ours {entry['sign_ours'] * 100:.1f}% joint {entry['sign_joint'] * 100:.1f}% output "
                f"{entry['sign_out'] * 100:.1f}%; {seconds:.1f} s")
        row = {key: float(np.nanmean([p[key] for p in per_shape])) for key in per_shape[0] if key != "shape"}
        row["cd_classic"] = min(row[f"cd_{f}"] for f in filters)
        row["p2s_classic"] = min(row[f"p2s_{f}"] for f in filters)
        row["worse_than_input"] = [p["shape"] for p in per_shape
                                   if p["cd_ours"] >= p["cd_noisy"] or p["p2s_ours"] >= p["p2s_noisy"]]
        row.update(level=level, k_pca=k_pca, k_pipeline_pca=k_pipe, shapes=per_shape,
                   k_filters={f: k for f, (k, _) in filters.items()})
        rows.append(row)
    scalar = [k for k, v in rows[0].items() if isinstance(v, float) and k != "level"]
    mean = {key: float(np.mean([r[key] for r in rows])) for key in scalar}
    return {"levels": rows, "mean": mean, "points": n_points, "iterations": iterations, "known_noise": known_noise,
            "filters": list(rows[0]["k_filters"]), "shapes": [s["name"] for s in prepared],
            "open_shapes": [s["name"] for s in prepared if not s["closed"]]}


def gap_closed(row) -> float:
    """Share of the tuned-PCA-to-floor MSAE gap that our normals close (1 = at the floor)."""
    gap = row["msae_pca"] - row["msae_floor"]
    return float((row["msae_pca"] - row["msae_ours"]) / gap) if gap > 0 else float("nan")


def format_table(result) -> str:
    filters = result["filters"]
    rows = result["levels"] + [dict(result["mean"], level=None)]

    def label(r):
        return "**mean**" if r["level"] is None else f"{r['level'] * 100:.1f}%"

    def k_of(r, key):
        return f" ({r[key]})" if r["level"] is not None else ""

    fk = {f: (lambda r, f=f: f" ({r['k_filters'][f]})" if r["level"] is not None else "") for f in filters}
    lines = ["Positions (CD x1e-5, P2S x1e-3; ratios against the best tuned classic filter of the level):", "",
             "| noise | CD noisy | " + " | ".join(f"CD {f} (k)" for f in filters) + " | CD ours | CD ours/classic | "
             "P2S noisy | " + " | ".join(f"P2S {f}" for f in filters) + " | P2S ours | P2S ours/classic | "
             "worse than input |",
             "|" + "---|" * (8 + 2 * len(filters))]
    for r in rows:
        worse = ", ".join(r.get("worse_than_input", [])) or ("none" if r["level"] is not None else
                                                              str(sum(len(x["worse_than_input"]) for x in result["levels"])) + " clouds")
        lines.append(
            f"| {label(r)} | {r['cd_noisy'] * 1e5:.2f} | " + " | ".join(f"{r[f'cd_{f}'] * 1e5:.2f}{fk[f](r)}" for f in filters)
            + f" | {r['cd_ours'] * 1e5:.2f} | {r['cd_ours'] / r['cd_classic']:.3f} | {r['p2s_noisy'] * 1e3:.2f} | "
            + " | ".join(f"{r[f'p2s_{f}'] * 1e3:.2f}" for f in filters)
            + f" | {r['p2s_ours'] * 1e3:.2f} | {r['p2s_ours'] / r['p2s_classic']:.3f} | {worse} |")
    lines += ["", "Normals (MSAE, rad^2). Origin: against each point's face of origin, ours in normals-only mode "
              "(joint: the denoise's normals); output: against the clean surface at the point nearest each output "
              "position, versus jet smoothing + PCA normals:", "",
              "| noise | PCA (k) | ours | joint | floor | gap closed | sharp PCA | sharp ours | out classic (k) | "
              "out ours | out ours/classic | sign ours (ceiling) | sign joint | sign output | s/cloud |",
              "|" + "---|" * 15]
    for r in rows:
        lines.append(
            f"| {label(r)} | {r['msae_pca']:.4f}{k_of(r, 'k_pca')} | {r['msae_ours']:.4f} | {r['msae_joint']:.4f} | "
            f"{r['msae_floor']:.4f} | "
            f"{gap_closed(r) * 100:.0f}% | {r['sharp_msae_pca']:.4f} | {r['sharp_msae_ours']:.4f} | "
            f"{r['out_msae_classic']:.4f}{k_of(r, 'k_pipeline_pca')} | {r['out_msae_ours']:.4f} | "
            f"{r['out_msae_ours'] / r['out_msae_classic']:.3f} | {r['sign_ours'] * 100:.1f}% ({r['sign_ceiling'] * 100:.1f}%) | "
            f"{r['sign_joint'] * 100:.1f}% | {r['sign_out'] * 100:.1f}% | {r['seconds']:.1f} |")
    names = result["shapes"]
    lines += ["", "Sign agreement per shape and level, closed meshes only: ours (normals only, against each input "
              "point's face of origin; ceiling: the most any method can reach there) / output (the denoise's "
              "normals, against the clean surface at the point nearest each output position):", "",
              "| shape | " + " | ".join(label(r) for r in result["levels"]) + " |", "|" + "---|" * (1 + len(result["levels"]))]
    for i, name in enumerate(names):
        vals = [(r["shapes"][i]["sign_ours"], r["shapes"][i]["sign_ceiling"], r["shapes"][i]["sign_out"])
                for r in result["levels"]]
        if all(np.isnan(v) for v, _, _ in vals):
            continue
        lines.append(f"| {name} | " + " | ".join(f"{v * 100:.1f}% ({c * 100:.1f}%) / {o * 100:.1f}%" for v, c, o in vals)
                     + " |")
    open_note = (f" Open or inconsistently wound (no sign truth): {', '.join(result['open_shapes'])}."
                 if result.get("open_shapes") else "")
    m = result["mean"]
    given = " (the engine given the true noise sigma: --known-noise)" if result.get("known_noise") else ""
    lines += ["", f"{result['points']} points per shape, {result['iterations']} iterations{given}; shapes: "
              f"{', '.join(names)}.{open_note}",
              "MSAE floor: the least origin-MSAE any method can reach on these clouds (metrics.msae_floor_normals); "
              "sign ceiling: the most origin sign agreement any method can reach (metrics.sign_ceiling_normals); "
              "sign joint: the denoise's normals against the faces of origin (an output point put back on the other "
              "face of an edge carries that face's normal, at right angles to its origin's).",
              f"Means: MSAE ours/PCA = {m['msae_ours'] / m['msae_pca']:.3f}, gap closed {gap_closed(m) * 100:.0f}%; "
              f"out-MSAE ours/classic = {m['out_msae_ours'] / m['out_msae_classic']:.3f}; "
              f"CD ours/noisy = {m['cd_ours'] / m['cd_noisy']:.3f}; CD ours/classic = {m['cd_ours'] / m['cd_classic']:.3f}; "
              f"P2S ours/classic = {m['p2s_ours'] / m['p2s_classic']:.3f}"]
    return "\n".join(lines)
