"""pivot's pipeline stages and the shared geometry, robot and artifact modules they use.

One module per stage (``analyze``, ``sample``, ...), each with a frozen ``Params`` dataclass, a pure
``compute`` and a ``run`` that reads and writes artifacts. Shared modules: ``se3`` (batched
transforms), ``artifacts`` (Parquet/JSON I/O with metadata), ``errors``, ``tol``, ``objects`` (the
object families of the general-object benchmark).
"""

__version__ = "0.1.0"
