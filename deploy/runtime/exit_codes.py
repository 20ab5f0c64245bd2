"""The exit statuses of every `impulse` command, defined once (the launcher, scripts and tests read them)."""

from __future__ import annotations

EXIT_FAILED = 1
"""The command ran and failed: a run that stopped on an error, an invalid level file, a failed import."""
EXIT_USAGE = 2
"""The command line or the configuration cannot be used (argparse's own status for a bad command line)."""
EXIT_CANNOT_RUN = 78
"""A process whose configuration cannot run here (sysexits' EX_CONFIG: its program does not fit in memory, its
devices are not there): restarting it would fail the same way, after the same long compile, so `impulse launch`
never restarts it."""
EXIT_BROKEN_PIPE = 128 + 13
"""The command wrote to a pipe whose reader had gone (128 + SIGPIPE), what a shell reports for `yes | head`: the
output was cut short, not the command wrong."""
