"""The ``pivot`` command line: thin typer commands over ``stages``.

Ctrl-C while the command's modules load (seconds on a busy machine) is one line and exit 130, as
in a command (``pivotcli.common.cli_errors``), not a traceback from inside an import.
"""

import os
import signal
import sys


def _interrupted_while_starting(signum, frame) -> None:
    os.write(2, b"pivot: interrupted\n")
    os._exit(130)


def started() -> None:
    """The command runs: Ctrl-C raises ``KeyboardInterrupt`` again, which the command turns into one
    line after its clean-up (temporary files removed, lock released)."""
    if signal.getsignal(signal.SIGINT) is _interrupted_while_starting:
        signal.signal(signal.SIGINT, signal.default_int_handler)


if os.path.basename(sys.argv[0]) in ("pivot", "-m") and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
    signal.signal(signal.SIGINT, _interrupted_while_starting)
