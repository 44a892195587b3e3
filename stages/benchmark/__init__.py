"""The benchmark of general objects and goals: make a suite of scenes, sweep the chain over it, report.

- :mod:`stages.benchmark.suite` (``pivot benchmark make``): objects of :mod:`stages.objects`, seeded
  goals of three kinds (translate, rotate, another face down) in the robot's reach on the default
  table, one ordinary scene file per case, and a cheap necessary reachability label per case.
- :mod:`stages.benchmark.sweep` (``pivot benchmark run``): every case's whole chain, each stage as its
  own ``pivot`` process, as Dask tasks (a ``LocalCluster`` or an existing scheduler); the physics for
  K seeds; resumable; one row per (case, seed) in ``results.parquet``.
- :mod:`stages.benchmark.report` (``pivot benchmark report``): success rates per object and goal kind,
  failure reasons ranked, time per stage, as ``report.md`` with figures.

Layout of a suite folder ``OUT``::

    suite.json              the cases: object, goal kind, scene file, reachability label
    objects/<object>.obj    the meshes the scenes name        robots/  the robot's URDF
    analysis/<object>/      each object's analysis (placements for the goals, the label's grasps)
    scenes/<case>.json      one scene per case (rerun one alone: ``pivot run OUT/scenes/<case>.json``)
    runs/<case>/            the case's build folder, stage logs and ``case.json`` (its result rows)
    results.parquet         one row per (case, seed)       report.md, figures/
"""
