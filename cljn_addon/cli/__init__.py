"""The command line (standalone/run.py): everything that parses arguments, prints or exits.

app.py       main(), argv_from_sys(), the command table,, dependency check
parser.py    denoise/normals options and the help text; exitcodes.py, console.py
progress.py  the one progress bar of every command
clouds.py    denoise / normals on point files and .blend files; report.py its JSON report
train.py, evaluate.py, demo.py, bench.py   the other commands; paths.py their data defaults

Layers import downward only: standalone -> cli -> blender -> core.
"""
from .app import COMMANDS, argv_from_sys, main  # noqa: F401
