"""The command line (run.py): parser, exit codes, progress, report and the commands."""
