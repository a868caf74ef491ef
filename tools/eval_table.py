"""The README's and model card's eval tables, from the JSON of `eval` runs.

One run per level and block, as "Where the eval stands" in the README says:

  python standalone/run.py eval --points 50000 --levels L --no-thin --json V_L.json
  python standalone/run.py eval --points 50000 --levels L --thin-only --json T_L.json
  python tools/eval_table.py V_*.json T_*.json

prints the per-block table (one row per block and level) and the table of both blocks together
(each level's ten clouds; each block's classic filters keep their own tuned k). Bold marks the
issue's targets met: Chamfer <= 0.9x and P2S <= 0.8x the best tuned classic filter, output MSAE
<= 0.75x the classic pipeline, origin MSAE below tuned PCA's, gap closed >= 30%.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cljn_addon.core.evaluation.evaluate import gap_closed  # noqa: E402

BLOCK_NAMES = {"validation": "validation", "thin_parts": "thin parts"}
TARGETS = {"cd": 0.9, "p2s": 0.8, "out": 0.75, "gap": 0.30}


def bold(text, met):
    return f"**{text}**" if met else text


def load_rows(paths):
    """{(block, level): the level's record} from every run's JSON."""
    rows = {}
    for path in paths:
        for block, run in json.loads(Path(path).read_text()).items():
            for record in run["levels"]:
                rows[(block, round(record["level"] * 100, 2))] = record
    return rows


def best_classic(record):
    """The classic filter with the lower Chamfer, and its tuned k."""
    name = min(record["k_filters"], key=lambda f: record[f"cd_{f}"])
    return name, record["k_filters"][name]


def block_row(block, level, r):
    name, k = best_classic(r)
    cd, p2s, out = r["cd_ours"] / r["cd_classic"], r["p2s_ours"] / r["p2s_classic"], r["out_msae_ours"] / r["out_msae_classic"]
    gap = gap_closed(r)
    closed = [s for s in r["shapes"] if not math.isnan(s["sign_out"])]
    lowest = min(closed, key=lambda s: s["sign_out"]) if closed else None
    sign_out = f"{r['sign_out']:.1%}" + (f" (lowest {lowest['sign_out']:.1%}, {lowest['shape']})" if lowest else "")
    worse = ", ".join(r["worse_than_input"]) or "none"
    ours, pca = r["msae_ours"], r["msae_pca"]
    chamfer = f"{r['cd_ours'] * 1e5:.2f} / {r['cd_classic'] * 1e5:.2f} {name} {k}"
    return (f"| {BLOCK_NAMES.get(block, block)} | {level:.1f}% "
            f"| {bold(f'{cd:.3f}', cd <= TARGETS['cd'])} ({chamfer}) "
            f"| {bold(f'{p2s:.3f}', p2s <= TARGETS['p2s'])} | {bold(f'{out:.3f}', out <= TARGETS['out'])} "
            f"| {bold(f'{ours:.4f}', ours < pca)} / {pca:.4f} ({bold(f'{gap:.0%}', gap >= TARGETS['gap'])}) "
            f"| {sign_out} | {r['sign_joint']:.1%} ({r['sign_ceiling']:.1%}) | {worse} | {r['seconds']:.0f} s |")


def together_row(level, records):
    def total(key):
        return sum(r[key] for r in records)

    cd, p2s = total("cd_ours") / total("cd_classic"), total("p2s_ours") / total("p2s_classic")
    out = total("out_msae_ours") / total("out_msae_classic")
    gap = (total("msae_pca") - total("msae_ours")) / (total("msae_pca") - total("msae_floor"))
    return (f"| {level:.1f}% | {bold(f'{cd:.3f}', cd <= TARGETS['cd'])} | {bold(f'{p2s:.3f}', p2s <= TARGETS['p2s'])} "
            f"| {bold(f'{out:.3f}', out <= TARGETS['out'])} | {bold(f'{gap:.0%}', gap >= TARGETS['gap'])} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("json", nargs="+", help="eval --json outputs")
    args = ap.parse_args(argv)
    rows = load_rows(args.json)
    print("| block | noise | Chamfer ours/classic (ours / best classic, k) | P2S | output MSAE "
          "| origin MSAE ours / PCA (gap closed) | sign output (lowest closed shape) | sign joint (ceiling) "
          "| worse than input | s/cloud |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    blocks = sorted({b for b, _ in rows}, key=lambda b: list(BLOCK_NAMES).index(b) if b in BLOCK_NAMES else 9)
    for block in blocks:
        for level in sorted(lv for b, lv in rows if b == block):
            print(block_row(block, level, rows[(block, level)]))
    levels = sorted({lv for _, lv in rows})
    both = [lv for lv in levels if all((b, lv) in rows for b in blocks)]
    if len(blocks) > 1 and both:
        print("\n| noise | Chamfer ours/classic | P2S | output MSAE | origin gap closed |")
        print("|---|---|---|---|---|")
        for level in both:
            print(together_row(level, [rows[(b, level)] for b in blocks]))


if __name__ == "__main__":
    main()
