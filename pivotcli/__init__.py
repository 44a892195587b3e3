"""The ``pivot`` command line: thin typer commands over ``stages``."""
