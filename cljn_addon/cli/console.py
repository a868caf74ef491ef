"""Lines for the user: results on stdout, errors, warnings and progress on stderr."""
import sys


def err(line: str):
    print(line, file=sys.stderr, flush=True)


def out(line: str):
    print(line, file=sys.stdout, flush=True)
