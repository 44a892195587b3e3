"""``python -m pivotcli``: the ``pivot`` command (the benchmark runs its stages this way)."""

from pivotcli.app import main

main()
