"""The JSON report of denoise/normals (--report FILE.json): options, one entry per input, totals."""
from __future__ import annotations

import json
from pathlib import Path

from .console import err


def build_report(args, jobs, code, seconds, model_error=None) -> dict:
    report = {
        "command": args.command,
        "exit_code": code,
        "model": args.model or "default",
        "options": {"iterations": args.iterations, "patch_radius_percent": args.patch_radius,
                    "orient": args.orient, "viewpoint": args.viewpoint, "device": args.device,
                    "threads": args.threads, "seed": args.seed, "in_place": args.in_place,
                    "objects": args.objects, "use_mesh_vertices": args.use_mesh_vertices,
                    "max_displacement": getattr(args, "max_displacement", None),
                    "noise": getattr(args, "noise", None), "solid": getattr(args, "solid", False)},
        "inputs": [job.report for job in jobs],
        "succeeded": sum(job.report.get("status") == "ok" for job in jobs),
        "failed": sum(job.report.get("status") == "error" for job in jobs),
        "seconds": round(seconds, 3),
    }
    if model_error:
        report["error"] = model_error
    return report


def write_report(path, report: dict) -> None:
    """Write atomically; a failure is a message on stderr, never an exit code of its own."""
    from ..core.formats.points import atomic_paths

    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_paths(path) as (tmp,):
            tmp.write_text(json.dumps(report, indent=2) + "\n")
    except OSError as exc:
        err(f"error: {path}: cannot write the report ({exc.strerror or exc})")
