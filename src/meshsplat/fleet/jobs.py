"""The jobs file of ``meshsplat batch``: which captures to train, each with its own options.

YAML or JSON: a list of jobs, or ``{"defaults": {...}, "jobs": [...]}``; a job is a capture path or a
mapping with the keys of ``JOB_KEYS`` (``data`` required; the defaults' keys apply where a job is silent;
``set`` lists add up: the defaults' first). Text: one job per line, ``PATH [KEY=VALUE ...]`` (``--set``
overrides), ``#`` starts a comment. Relative capture paths are relative to the jobs file's folder.
Names (default: the capture folder's name) must be unique: each job writes ``DIR/NAME/``.

A file that cannot be read at all is one MeshsplatError (also one over ``MAX_FILE_BYTES``, a YAML file
whose aliases expand past ``MAX_NODES`` values, nesting deeper than ``MAX_DEPTH``, an unclosed quote in a
text file); a job with a bad key or value becomes a failed job with its one-line reason (``Job.problem``)
and the others still run. Values are taken as written, never coerced: ``eval: "false"`` or
``iterations: 2.9`` are problems, not ``True`` and ``2``. ``Job.spec()`` is the digest of everything a job
asks for: a finished job whose entry was edited since is run again (``runner.finished_result``).
"""

from __future__ import annotations

import hashlib
import json
import re
import shlex
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from meshsplat.errors import MeshsplatError
from meshsplat.export import SPLAT_FORMATS
from meshsplat.train.config import TrainConfig, apply_overrides
from meshsplat.train.recipes import DEFAULT_RECIPE, RECIPES, recipe_config

__all__ = ["Job", "JOB_KEYS", "read_jobs", "job_config", "MAX_FILE_BYTES", "MAX_NODES", "MAX_DEPTH"]

MAX_FILE_BYTES = 16 * 2**20  # a jobs file of 10,000 jobs is well under 2 MB
MAX_NODES = 1_000_000  # values in the file once YAML aliases are expanded
MAX_DEPTH = 64  # nesting of lists and mappings (a job needs 3)

# key -> meaning (docs/scale-out.md lists them)
JOB_KEYS = {
    "name": "folder name under --out (default: the capture folder's name)",
    "data": "capture folder (any layout meshsplat train reads)",
    "recipe": "training recipe (quality | paper)",
    "iterations": "training iterations",
    "set": "list of config overrides KEY=VALUE (as meshsplat train --set)",
    "format": "capture layout (default: detect)",
    "model_dir": "SMPL/FLAME model folder",
    "device": "cpu | cuda | auto",
    "threads": "torch CPU threads of the job (default 1)",
    "eval": "evaluate on the test splits (default true)",
    "export": "splat formats to export (default [ply]; [] = none)",
}
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")


@dataclass
class Job:
    """One capture to train; ``problem`` is set when its entry in the jobs file is wrong."""

    name: str
    data: str
    recipe: str = DEFAULT_RECIPE
    iterations: int | None = None
    set: list[str] = field(default_factory=list)
    format: str = ""
    model_dir: str = ""
    device: str = "auto"
    threads: int = 1
    eval: bool = True
    export: list[str] = field(default_factory=lambda: ["ply"])
    problem: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def spec(self) -> str:
        """Digest of everything the job asks for (every field but ``problem``): equal specs, same job."""
        d = {k: v for k, v in self.to_dict().items() if k != "problem"}
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def job_config(job: Job, run_dir: str | Path) -> TrainConfig:
    """The job's ``TrainConfig``, training into ``run_dir``."""
    cfg = apply_overrides(recipe_config(job.recipe), list(job.set))
    cfg.data, cfg.out, cfg.progress = job.data, str(run_dir), False
    cfg.data_format, cfg.model_dir, cfg.device = job.format, job.model_dir, job.device
    if job.iterations is not None:
        cfg.iterations = job.iterations
    return cfg.validate()


def _yaml_size(node: Any, path: Path) -> None:
    """Refuse a YAML document whose aliases expand past ``MAX_NODES`` values or that nests deeper than
    ``MAX_DEPTH`` (an alias bomb is a few lines that expand to billions), before anything is built."""
    count = 0
    stack = [(node, 1)]
    while stack:
        n, depth = stack.pop()
        count += 1
        if count > MAX_NODES:
            raise MeshsplatError(
                f"{path}: more than {MAX_NODES:,} values once its YAML aliases (*name) are expanded; "
                "write the jobs out, or use fewer aliases"
            )
        if depth > MAX_DEPTH:
            raise MeshsplatError(f"{path}: nested deeper than {MAX_DEPTH} levels; a jobs file needs 3")
        value = getattr(n, "value", None)
        if isinstance(value, list):
            for item in value:
                if isinstance(item, tuple):  # a mapping's (key, value)
                    stack.extend((x, depth + 1) for x in item)
                else:
                    stack.append((item, depth + 1))


def _depth(doc: Any, path: Path) -> None:
    stack = [(doc, 1)]
    while stack:
        v, depth = stack.pop()
        if depth > MAX_DEPTH:
            raise MeshsplatError(f"{path}: nested deeper than {MAX_DEPTH} levels; a jobs file needs 3")
        if isinstance(v, dict):
            stack.extend((x, depth + 1) for x in v.values())
        elif isinstance(v, list):
            stack.extend((x, depth + 1) for x in v)


def _load(path: Path) -> Any:
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise MeshsplatError(f"{path}: {size / 2**20:.0f} MB is not a jobs file (at most {MAX_FILE_BYTES // 2**20} MB)")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise MeshsplatError(f"{path}: not UTF-8 text (byte {exc.start}); save the jobs file as UTF-8") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml  # optional: comes with the [ray] extra
        except ImportError:
            raise MeshsplatError(f"{path}: reading YAML needs pyyaml: pip install 'meshsplat[ray]'") from None
        try:
            for node in yaml.compose_all(text, Loader=yaml.SafeLoader):
                if node is not None:
                    _yaml_size(node, path)
            return yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise MeshsplatError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
        except RecursionError:
            raise MeshsplatError(f"{path}: nested too deeply; a jobs file needs 3 levels") from None
    if path.suffix.lower() == ".json":
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise MeshsplatError(f"{path}: not valid JSON ({exc})") from None
        except RecursionError:
            raise MeshsplatError(f"{path}: nested too deeply; a jobs file needs 3 levels") from None
        _depth(doc, path)
        return doc
    if path.suffix.lower() == ".txt":
        jobs = []
        for number, line in enumerate(text.splitlines(), 1):
            try:
                words = shlex.split(line, comments=True)
            except ValueError as exc:  # "No closing quotation", "No escaped character"
                raise MeshsplatError(f"{path}:{number}: {exc} in {line.strip()[:80]!r}; close the quote") from None
            if words:
                jobs.append({"data": words[0], "set": words[1:]})
        return jobs
    raise MeshsplatError(f"{path}: a jobs file is .yaml, .yml, .json or .txt")


def _typed(key: str, value: Any, kind: str) -> Any:
    """``value`` of job key ``key`` as written, or ValueError naming what was expected (no coercion)."""
    if kind == "str" and isinstance(value, str):
        return value
    if kind == "int" and isinstance(value, int) and not isinstance(value, bool):
        return value
    if kind == "bool" and isinstance(value, bool):
        return value
    if kind == "strs" and isinstance(value, list) and all(isinstance(x, str) for x in value):
        return list(value)
    want = {
        "str": "text",
        "int": "a whole number",
        "bool": "true or false (unquoted)",
        "strs": "a list of text items",
    }[kind]
    raise ValueError(f"{key}: expected {want}, got {value!r}")


def _job(entry: Any, defaults: dict[str, Any], base: Path, index: int) -> Job:
    if isinstance(entry, str):
        entry = {"data": entry}
    if not isinstance(entry, dict) or not entry.get("data"):
        return Job(f"job{index + 1}", "", problem=f"job {index + 1}: expected a capture path or a mapping with 'data'")
    label = f"job{index + 1}"
    if not isinstance(entry.get("data"), str):
        return Job(label, "", problem=f"job {index + 1}: data: expected a capture path, got {entry['data']!r}")
    sets = [defaults.get("set", []), entry.get("set", [])]
    if not all(isinstance(s, list) for s in sets):
        return Job(label, "", problem=f"job {index + 1}: set: expected a list of KEY=VALUE items")
    d = {**defaults, **entry, "set": [*sets[0], *sets[1]]}
    data = Path(d["data"]).expanduser()
    data = data if data.is_absolute() else base / data
    name = d.get("name") or data.name
    if not isinstance(name, str):
        return Job(label, str(data), problem=f"job {index + 1}: name: expected text, got {name!r}")
    job = Job(name, str(data))
    unknown = sorted(str(k) for k in set(d) - set(JOB_KEYS))
    if unknown:
        job.problem = f"unknown key(s) {', '.join(unknown)}; a job takes {', '.join(JOB_KEYS)}"
        return job
    try:
        for key in ("recipe", "format", "model_dir", "device"):
            if key in d:
                setattr(job, key, _typed(key, d[key], "str"))
        for key in ("iterations", "threads"):
            if key in d and d[key] is not None:
                setattr(job, key, _typed(key, d[key], "int"))
        job.set = _typed("set", d["set"], "strs")
        job.eval = _typed("eval", d.get("eval", True), "bool")
        job.export = _typed("export", d.get("export", ["ply"]), "strs")
    except ValueError as exc:
        job.problem = f"bad value ({exc})"
        return job
    if not _NAME.match(job.name):
        job.problem = f"name {job.name!r}: letters, digits, '.', '_', '-' only"
    elif job.recipe not in RECIPES:
        job.problem = f"recipe {job.recipe!r}: expected one of {', '.join(RECIPES)}"
    elif bad := [f for f in job.export if f not in SPLAT_FORMATS]:
        job.problem = f"export {bad}: expected some of {', '.join(SPLAT_FORMATS)}"
    elif job.threads < 1:
        job.problem = "threads must be >= 1"
    else:
        try:
            job_config(job, "unused")
        except MeshsplatError as exc:
            job.problem = str(exc)
    return job


def read_jobs(path: str | Path) -> list[Job]:
    """The jobs of a jobs file (see the module docstring); names made unique is the author's job:
    a repeated name is a problem of the later jobs."""
    path = Path(path)
    if not path.is_file():
        raise MeshsplatError(f"jobs file not found: {path}")
    doc = _load(path)
    defaults: dict[str, Any] = {}
    if isinstance(doc, dict):
        defaults = doc.get("defaults") or {}
        doc = doc.get("jobs")
        if not isinstance(defaults, dict):
            raise MeshsplatError(f"{path}: 'defaults' must be a mapping of job keys")
    if not isinstance(doc, list) or not doc:
        raise MeshsplatError(f"{path}: expected a non-empty list of jobs (or a mapping with 'jobs')")
    jobs = [_job(e, defaults, path.resolve().parent, i) for i, e in enumerate(doc)]
    seen: set[str] = set()
    for job in jobs:
        if job.name in seen and not job.problem:
            job.problem = f"name {job.name!r} is used by an earlier job; give each job its own 'name'"
        seen.add(job.name)
    return jobs
