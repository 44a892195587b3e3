"""Errors for bad input. Expected failures (IK misses, infeasible QPs) are data, not exceptions."""


class PivotError(Exception):
    """Bad input: the message names the file and the problem. The CLI prints it and exits 2."""


class InputError(PivotError):
    """An input file is missing, unreadable, or its content is invalid."""


class ArtifactError(PivotError):
    """An artifact is missing, truncated, or has the wrong schema."""
