"""`run.py bench`: network patches per second and the seconds of a whole denoise per preset, as a
Markdown table (the timing is core.evaluation.benchmark)."""
from __future__ import annotations

import argparse

from .console import out
from .exitcodes import EXIT_OK


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="run.py bench",
        description="Speed benchmark: network patches per second and seconds for a 100K-point "
                    "cloud, 4 iterations, per preset (untrained weights: speed does not depend on "
                    "their values).")
    parser.add_argument("--presets", nargs="+", default=["small", "paper"])
    parser.add_argument("--points", type=int, default=100_000)
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--backends", nargs="+", default=["torch", "numpy"], choices=["torch", "numpy"],
                        help="inference backends timed side by side (default: both)")
    parser.add_argument("--skip-full", nargs="*", default=["paper"], metavar="PRESET",
                        help="presets timed on the network only (the paper preset's full run takes ~15 min here)")
    return parser


def _row(row) -> str:
    if "seconds" in row:
        full = f"{row['seconds']:.1f} s (peak memory of this process so far {row['peak_gib']:.2f} GiB)"
    else:
        full = f"~{row['estimated_seconds']:.0f} s (network time only, estimated)"
    return (f"| {row['preset']} | {row['backend']} | {row['points_per_patch']} | "
            f"{row['patches_per_second']:,.0f} | {full} |")


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from ..core.evaluation.benchmark import bench_cloud, bench_preset, machine_line

    out(machine_line(args.device))
    noisy = bench_cloud(args.points)
    out(f"| preset | backend | points/patch | network patches/s | {args.points // 1000}K points x "
        f"{args.iterations} iterations |")
    out("|---|---|---|---|---|")
    for name in args.presets:
        for backend in args.backends:
            row = bench_preset(name, noisy, args.iterations, args.device, full=name not in args.skip_full,
                               backend=backend)
            out(_row(row))
    return EXIT_OK
