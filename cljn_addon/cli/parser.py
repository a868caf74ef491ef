"""The argument parser of run.py: the denoise/normals options, the help text (formats and exit
codes), and one sub-command per entry of main.COMMANDS."""
from __future__ import annotations

import argparse
import math

from ..core.config import BACKENDS, DEVICE_CHOICES, ORIENTATIONS
from ..core.formats import POINT_SUFFIXES

PROG = "run.py"
BLEND_SUFFIX = ".blend"
ALL_SUFFIXES = POINT_SUFFIXES + (BLEND_SUFFIX,)

EPILOG = """\
invocation:
  python standalone/run.py COMMAND ...            (Python 3.11 with the bpy wheel)
  blender -b -P standalone/run.py -- COMMAND ...  (Blender 4.2 or newer)

formats (by extension):
  .ply    in: ascii and binary (little/big endian), any extra properties (kept)
          out: binary little endian: x y z nx ny nz, the input's other properties,
               cljn_outlier (uchar, 1 = flagged as outlier)
  .xyz    in/out: "x y z" per line; normals in the sibling .normals file (PCPNet layout);
          other properties are not written
  .npy    in: (N,3), (N,6) x y z nx ny nz, or a structured array with x y z fields
          out: (N,6) x y z nx ny nz in the input's float type
  .las .laz  in/out (laspy + lazrs): the input's point format, header (scale, offset, CRS and
          other VLRs/EVLRs) and every field in order; positions at the file's scale, or
          10-1000x finer where that grid would round the cleaning away (--keep-las-scale:
          never; unmoved points keep their exact coordinates); normals as extra bytes
          NormalX NormalY NormalZ (float32) and cljn_outlier (uint8, 1 = flagged). Streamed
          in chunks. A COPC tile comes back as plain LAZ (its octree index left out). From
          another format: LAS 1.4 point format 6 (7 with red/green/blue).
  .blend  in: every point-cloud object (or --objects NAME...) is processed; other objects
          are left alone; saved as a new .blend (or --in-place, keeping NAME.blend1)
          out from a point file: a new scene holding the cloud as a mesh of vertices
          (from .las/.laz: as File > Import > LAS/LAZ makes it, recentred, exportable)

exit codes:
  0    success
  1    unexpected internal error (a bug; rerun with --debug and report it)
  2    bad input or usage: unreadable/truncated/empty file, NaN coordinates, a .blend
       without point clouds, a missing or mismatched model (also: every input of a batch
       failed)
  3    a batch where some inputs failed; the others were processed and written
  130  interrupted (Ctrl-C); no partial output is left behind
"""


def _positive_int(text):
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def iterations_arg(text):
    """A whole number of iterations, or 'auto' (1-4, from the estimated noise)."""
    if str(text).strip().lower() == "auto":
        return "auto"
    return _positive_int(text)


def _number(text, ok, requirement):
    """A float argument that must satisfy ok(value); otherwise 'must be <requirement>'."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (math.isfinite(value) and ok(value)):
        raise argparse.ArgumentTypeError(f"must be {requirement}, got {text}")
    return value


def _percent(text):
    return _number(text, lambda v: 0.0 < v <= 100.0, "above 0 and at most 100 (percent)")


def _positive_float(text):
    return _number(text, lambda v: v > 0, "above 0")


def _finite(text):
    return _number(text, lambda v: True, "finite")


def _add_cloud_options(p: argparse.ArgumentParser, normals_only: bool):
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="point clouds (.ply .xyz .npy .las .laz) or Blender scenes (.blend)")
    out = p.add_argument_group("output (one of -o, --out-dir, --in-place)")
    dest = out.add_mutually_exclusive_group(required=True)
    dest.add_argument("-o", "--output", metavar="OUTPUT",
                      help="output file for a single input; its extension picks the format")
    dest.add_argument("--out-dir", metavar="DIR",
                      help="write each result as DIR/<input name> (created if missing)")
    dest.add_argument("--in-place", action="store_true",
                      help="replace each input, keeping a backup (NAME.blend1 for .blend, "
                           "NAME.bak otherwise)")
    out.add_argument("--format", choices=[s[1:] for s in ALL_SUFFIXES],
                     help="with --out-dir: output format (default: the input's)")
    out.add_argument("--keep-las-scale", action="store_true",
                     help="LAS/LAZ out of LAS/LAZ: keep the input's scale even where its grid is "
                          "too coarse for the cleaning (moves of a few mm on a 1 cm grid round "
                          "back to the input). Default: then a scale 10-1000x finer, every input "
                          "coordinate still exact (a larger LAZ: +8%% for plane.laz with normals)")
    out.add_argument("--classify-outliers", action="store_true",
                     help="LAS/LAZ out: also give flagged outliers classification 7 (ASPRS low "
                          "point/noise, as PDAL's outlier filter does), for tools that filter by "
                          "class; their own class is overwritten in the output (the input keeps it)")
    out.add_argument("--report", metavar="FILE.json",
                     help="write a machine-readable summary (per input: points, outliers, "
                          "seconds, output path, status)")
    out.add_argument("--preview", metavar="FILE.png",
                     help="render a before/after picture (several clouds: FILE_<name>.png)")
    out.add_argument("--preview-color", choices=["normal", "displacement"], default="normal",
                     help="colour the result by normal (default) or by displacement")
    blend = p.add_argument_group(".blend input")
    blend.add_argument("--objects", nargs="+", metavar="NAME",
                       help="process only these objects (default: every point-cloud object); "
                            "put it after the inputs")
    blend.add_argument("--use-mesh-vertices", action="store_true",
                       help="treat the vertices of any mesh as a point cloud")
    eng = p.add_argument_group("engine (as in the panel)")
    eng.add_argument("--model", metavar="FILE.safetensors",
                     help="weights file with its .json beside it (default: the shipped model)")
    eng.add_argument("--iterations", type=iterations_arg, default="auto",
                     help=("accepted for symmetry with denoise: normals take one network pass"
                           if normals_only else
                           "filtering iterations, or auto (default): 1-4 chosen from the estimated noise, "
                           "stopping once points have moved as far as the noise"))
    eng.add_argument("--patch-radius", type=_percent, metavar="PERCENT",
                     help="patch radius in percent of the bounding-box diagonal (default 5); "
                          "for normals, the largest: a dense cloud gets the ball one patch fills")
    if not normals_only:
        eng.add_argument("--max-displacement", type=_positive_float, metavar="DISTANCE",
                         help="no point moves further than this, in the cloud's units (default: "
                              "3 x the noise level estimated from the cloud)")
        eng.add_argument("--solid", action="store_true",
                         help="handle the object as solid even where its surface reads as a thin "
                              "part's two sides (the summary says 'thin-walled'): a sculpt whose "
                              "relief, ribs or limbs come out under-cleaned")
    eng.add_argument("--noise", type=_positive_float, metavar="DISTANCE",
                     help=("the scanner's noise (standard deviation) in the cloud's units, when you know it "
                           "(a spec sheet's range precision): how far round each point its surface may lie, "
                           "for the normal of the surface it came from (default: estimated)"
                           if normals_only else
                           "the scanner's noise (standard deviation) in the cloud's units, when you "
                           "know it (a spec sheet's range precision): used in place of the estimate "
                           "for the pass count, the stop and the motion bound. Give it when fine "
                           "relief reads as noise and gets smoothed away (default: estimated)"))
    eng.add_argument("--orient", choices=ORIENTATIONS, default="outward",
                     help="normal orientation (default outward)")
    eng.add_argument("--viewpoint", type=_finite, nargs=3, metavar=("X", "Y", "Z"),
                     help="with --orient viewpoint: the scanner position (a .blend uses its "
                          "scene camera when this is not given)")
    eng.add_argument("--device", default="auto", type=str.lower, choices=DEVICE_CHOICES,
                     metavar="DEVICE",
                     help="auto (default), cpu, cuda, gpu or mps")
    eng.add_argument("--backend", default="auto", type=str.lower, choices=BACKENDS,
                     help="what runs the network: auto (default: torch when installed, else "
                          "numpy), torch (GPUs, bf16 on CPU) or numpy (CPU, no torch needed)")
    eng.add_argument("--threads", type=_positive_int, metavar="N",
                     help="CPU threads for the network (torch backend: torch.set_num_threads)")
    eng.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    misc = p.add_argument_group("messages")
    misc.add_argument("--no-progress", action="store_true", help="no progress bar or lines")
    misc.add_argument("--debug", action="store_true", help="print tracebacks of internal errors")


def build_parser(commands: dict) -> argparse.ArgumentParser:
    """denoise and normals in full; the other commands (name -> (entry, help)) parse their own
    arguments and are listed here for --help only."""
    parser = argparse.ArgumentParser(
        prog=PROG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="CLJN Denoise: filter point clouds and estimate their normals with a "
                    "learned network (contrastive learning for joint normal estimation and "
                    "point-cloud filtering).",
        epilog=EPILOG)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    p = sub.add_parser("denoise", help="filter positions and estimate normals",
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
                       description="Filter positions and estimate normals of point clouds.")
    _add_cloud_options(p, normals_only=False)
    p = sub.add_parser("normals", help="estimate normals only (positions bit-identical)",
                       formatter_class=argparse.RawDescriptionHelpFormatter, epilog=EPILOG,
                       description="Estimate normals only; positions are written back "
                                   "bit-identical.")
    _add_cloud_options(p, normals_only=True)
    for name, (_entry, text) in commands.items():
        sub.add_parser(name, help=f"{text} (see: {PROG} {name} --help)", add_help=False)
    return parser
