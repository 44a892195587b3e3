"""Where every artifact of a scene lives, what each stage reads and writes, and when it is stale.

One place decides the default paths of the pipeline (DESIGN.md, Pipeline): the CLI's defaults,
``pivot run`` and the Makefile's generated prerequisites (``pivot deps``) all come from ``Layout`` and
``STAGES``. Under ``build/<scene>/`` (``<scene>`` the scene file's stem)::

    analysis/   analyze: analysis.json, segments, hull, placements, contacts, pairs (.parquet), object.ply
    sample/     sample:  sample.json, poses, pose_links, grasps, grasp_rejects (.parquet)
    graph/      graph:   graph.json, nodes, edges, catches (.parquet)
    <variant>/  plan.json; mpc: trajectories.json (+ .parquet); execute: execution.json, execution.parquet,
                frames.npz; figures plan.png, trajectories.png, execution.png/.gif
    analysis.png, poses.png

``<variant>`` is ``full`` (the whole planner) or the paper's ablation (``no-regrasp``, ``no-tumble``,
``no-usp``). A stage's prerequisites are its upstream stage's outputs, the scene and the data files it
names (object mesh, robot URDF, obstacle meshes), and the code the stage runs: every module of
``pivotcli`` and ``stages`` that its command module imports, directly or not (found by reading the
sources' import statements, as ``gcc -M`` lists a C file's headers). A stage is stale, as for Make,
when one of its outputs is missing or older than one of its prerequisites.

This module imports only the standard library, so that ``pivot run`` decides quickly that nothing
changed.
"""

from __future__ import annotations

import functools
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[1]
VARIANTS = ("full", "no-regrasp", "no-tumble", "no-usp")


@dataclass(frozen=True)
class Stage:
    """One pipeline stage: its command (``module:function``), its folder, outputs and upstream stage.

    ``folder`` is ``"{v}"`` for the per-variant stages; ``outputs`` are file names in that folder, the
    first the JSON summary every run of the stage writes; ``optional`` ones may legitimately be absent
    (``pivot execute --frames 0`` renders no frames) and never make the stage stale.
    """

    name: str
    command: str
    folder: str
    outputs: tuple[str, ...]
    upstream: str | None
    data: tuple[str, ...]
    optional: tuple[str, ...] = ()


STAGES = (
    Stage("analyze", "pivotcli.analyze:analyze", "analysis", ("analysis.json", "segments.parquet", "hull.parquet",
          "placements.parquet", "contacts.parquet", "pairs.parquet", "object.ply"), None, ("mesh",)),
    Stage("sample", "pivotcli.sample:sample", "sample", ("sample.json", "poses.parquet", "pose_links.parquet",
          "grasps.parquet", "grasp_rejects.parquet"), "analyze", ("robot", "obstacles")),
    Stage("graph", "pivotcli.plan:graph", "graph", ("graph.json", "nodes.parquet", "edges.parquet", "catches.parquet"),
          "sample", ("robot", "obstacles")),
    Stage("plan", "pivotcli.plan:plan", "{v}", ("plan.json",), "graph", ("robot", "obstacles")),
    Stage("mpc", "pivotcli.plan:mpc", "{v}", ("trajectories.json", "trajectories.parquet"), "plan", ("robot",)),
    Stage("execute", "pivotcli.execute:execute", "{v}", ("execution.json", "execution.parquet", "frames.npz"), "mpc",
          ("robot", "obstacles"), optional=("frames.npz",)),
)
BY_NAME = {s.name: s for s in STAGES}


@dataclass(frozen=True)
class Figure:
    """A figure ``pivot run`` draws: its file (``{v}``: the variant folder) and the stage it shows."""

    name: str
    path: str
    stage: str
    module: str = "pivotcli.show"

    @property
    def command(self) -> str:
        return f"{self.module}:{self.name}"


FIGURES = (Figure("analysis", "analysis.png", "analyze"), Figure("poses", "poses.png", "sample"),
           Figure("plan", "{v}/plan.png", "plan"), Figure("trajectories", "{v}/trajectories.png", "mpc"),
           Figure("execution", "{v}/execution.png", "execute"),
           Figure("view", "{v}/view.html", "execute", "pivotcli.view"))


@dataclass(frozen=True)
class Layout:
    """The default paths of one scene's build: ``build/<scene stem>/`` under the working folder.

    ``scene`` is the scene file, ``build`` the scene's build folder, ``variant`` the planner variant
    whose plan, trajectories and execution sit in ``build/<variant>/``.
    """

    scene: Path
    build: Path
    variant: str = "full"

    @classmethod
    def of(cls, scene: Path, build: Path | None = None, variant: str = "full") -> Layout:
        """The layout of ``scene``: ``build`` defaults to ``build/<scene stem>`` in the working folder."""
        return cls(Path(scene), Path(build) if build is not None else Path("build") / Path(scene).stem, variant)

    def folder(self, stage: str) -> Path:
        """The folder holding ``stage``'s outputs."""
        return self.build / BY_NAME[stage].folder.format(v=self.variant)

    @property
    def analysis(self) -> Path:
        return self.folder("analyze")

    @property
    def sample(self) -> Path:
        return self.folder("sample")

    @property
    def graph(self) -> Path:
        return self.folder("graph")

    @property
    def run_dir(self) -> Path:
        """The variant's folder: plan, trajectories, execution and their figures."""
        return self.build / self.variant

    @property
    def plan(self) -> Path:
        return self.run_dir / "plan.json"

    @property
    def trajectories(self) -> Path:
        return self.run_dir / "trajectories.parquet"

    @property
    def execution(self) -> Path:
        return self.run_dir / "execution.json"

    def outputs(self, stage: str, required_only: bool = False) -> list[Path]:
        """Every file ``stage`` writes (``required_only``: less the ones it may leave out)."""
        s = BY_NAME[stage]
        names = [n for n in s.outputs if not (required_only and n in s.optional)]
        return [self.folder(stage) / n for n in names]

    def figure(self, name: str) -> Path:
        return self.build / next(f.path for f in FIGURES if f.name == name).format(v=self.variant)

    def prerequisites(self, stage: str) -> list[Path]:
        """What ``stage`` reads: the upstream stage's required outputs, the scene, its data files, its code."""
        s = BY_NAME[stage]
        upstream = self.outputs(s.upstream, required_only=True) if s.upstream else []
        data = scene_data_files(self.scene)
        files = [p for kind in s.data for p in data.get(kind, [])]
        return [*upstream, self.scene, *files, *code_files(s.command)]

    def stale(self, stage: str) -> list[str]:
        """Why ``stage`` must run (as Make decides it): missing outputs, newer prerequisites; [] if current."""
        outs = self.outputs(stage, required_only=True)
        missing = [str(p) for p in outs if not p.is_file()]
        if missing:
            return [f"missing {p}" for p in missing]
        oldest = min(p.stat().st_mtime_ns for p in outs)
        return [f"{p} is newer" for p in self.prerequisites(stage) if _mtime(p) > oldest]


def _mtime(p: Path) -> int:
    try:
        return p.stat().st_mtime_ns
    except OSError:  # a prerequisite that is not there: the stage runs and says what is missing
        return 1 << 62


def variant_of(no_regrasp: bool = False, no_tumble: bool = False, no_usp: bool = False) -> str:
    """The variant folder of a plan with these ablations: ``full`` or e.g. ``no-regrasp``."""
    flags = [n for n, on in (("no-regrasp", no_regrasp), ("no-tumble", no_tumble), ("no-usp", no_usp)) if on]
    return "+".join(flags) or "full"


def scene_data_files(scene: Path) -> dict[str, list[Path]]:
    """The files a scene names (``mesh``, ``robot``, ``obstacles``), resolved against its folder.

    An unreadable scene gives none: the stage that reads it reports the problem in one line.
    """
    try:
        data = json.loads(Path(scene).read_text())
        root = Path(scene).parent

        def resolve(p: str) -> Path:
            return Path(os.path.normpath(root / p)) if not Path(p).is_absolute() else Path(p)

        return {"mesh": [resolve(data["object"]["mesh"])], "robot": [resolve(data["robot"]["urdf"])],
                "obstacles": [resolve(o["mesh"]) for o in data.get("obstacles", []) if "mesh" in o]}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


@functools.cache
def code_files(command: str) -> tuple[Path, ...]:
    """The source files a command runs: its module, and every ``pivotcli``/``stages`` module it imports.

    ``command`` is ``module:function``: of its own module only the top-level imports and the ones inside
    ``function`` count (a CLI module holds several commands, each importing its stage when it runs); of
    every module reached from there, all its imports count, transitively, also those inside functions. A
    package's ``__init__.py`` counts for each module imported from it. Sorted paths under the package
    root (the checkout, or site-packages for an installed wheel).
    """
    module, _, function = command.partition(":")
    seen = {module}
    todo = [*_parents(module), *_imports(module, function or None)]
    while todo:
        name = todo.pop()
        if name in seen or _source(name) is None:
            continue
        seen.add(name)
        todo += [*_parents(name), *_imports(name)]
    return tuple(sorted(_source(n) for n in seen))


def _parents(module: str) -> list[str]:
    parts = module.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def _source(module: str) -> Path | None:
    """The file of a ``pivotcli``/``stages`` module (its ``__init__.py`` for a package), or None."""
    if module.split(".")[0] not in ("pivotcli", "stages"):
        return None
    base = PACKAGE_ROOT.joinpath(*module.split("."))
    for p in (base.with_suffix(".py"), base / "__init__.py"):
        if p.is_file():
            return p
    return None


_IMPORT = re.compile(r"^[ \t]*import[ \t]+([\w., \t]+)", re.M)
_FROM = re.compile(r"^[ \t]*from[ \t]+(\.*[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n]*)", re.M)


def _imports(module: str, function: str | None = None) -> list[str]:
    """The modules ``module`` imports (``from a import b`` gives ``a.b`` too when that is a module).

    With ``function``: only the imports outside every top-level ``def``/``class`` and those inside
    ``def function``; a module named to ``pivotcli.common.quiet_import`` counts as imported. Read with
    regular expressions, not ``ast`` (fifty times faster over the package):
    an import-like line inside a string can only add a prerequisite, never lose one.
    """
    path = _source(module)
    if path is None:
        return []
    text = path.read_text()
    if function is not None:
        blocks = re.split(r"\n(?=[^\s)\]}#])", text)  # top-level statements, each with its indented body
        text = "\n".join(b for b in blocks if not re.match(r"(async def|def|class|@)\b|@", b)
                         or re.match(rf"def {re.escape(function)}\(", b))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for m in _IMPORT.finditer(text):
        found += [n.split()[0] for n in m.group(1).split(",") if n.strip()]
    for m in _FROM.finditer(text):
        base, level = m.group(1).lstrip("."), len(m.group(1)) - len(m.group(1).lstrip("."))
        if level:
            up = package.split(".")[: len(package.split(".")) - level + 1]
            base = ".".join([*up, base] if base else up)
        found.append(base)
        names = [n.split()[0] for n in re.sub(r"#[^\n]*", "", m.group(2)).strip("()").split(",") if n.strip()]
        found += [f"{base}.{n}" for n in names if _source(f"{base}.{n}") is not None]
    found += re.findall(r"""quiet_import\(\s*["']([\w.]+)["']""", text)  # pivotcli.common.quiet_import("a.b")
    return found
