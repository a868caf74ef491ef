"""Exit codes of run.py (documented in its --help)."""

EXIT_OK = 0
EXIT_INTERNAL = 1       # unexpected internal error (a bug)
EXIT_USAGE = 2          # bad input or usage; a missing or mismatched model; every input failed
EXIT_PARTIAL = 3        # a batch where some inputs failed (the others are written)
EXIT_INTERRUPTED = 130  # Ctrl-C


class UsageError(Exception):
    """Bad command line: one line on stderr, exit 2."""
