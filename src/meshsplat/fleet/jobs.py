"""The jobs file of ``meshsplat batch``: which captures to train, each with its own options.

YAML or JSON: a list of jobs, or ``{"defaults": {...}, "jobs": [...]}``; a job is a capture path or a
mapping with the keys of ``JOB_KEYS`` (``data`` required; the defaults' keys apply where a job is silent;
``set`` lists add up: the defaults' first). Text: one job per line, ``PATH [KEY=VALUE ...]`` (``--set``
overrides), ``#`` starts a comment. Relative capture paths are relative to the jobs file's folder.
Names (default: the capture folder's name) must be unique: each job writes ``DIR/NAME/``.

A file that cannot be read at all is one MeshsplatError; a job with a bad key or value becomes a failed
job with its one-line reason (``Job.problem``) and the others still run.
"""

from __future__ import annotations

import json
import re
import shlex
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from meshsplat.errors import MeshsplatError
from meshsplat.export import SPLAT_FORMATS
from meshsplat.train.config import TrainConfig, apply_overrides
from meshsplat.train.presets import DEFAULT_PRESET, PRESETS, preset_config

__all__ = ["Job", "JOB_KEYS", "read_jobs", "job_config"]

# key -> meaning (docs/scale-out.md lists them)
JOB_KEYS = {
    "name": "folder name under --out (default: the capture folder's name)",
    "data": "capture folder (any layout meshsplat train reads)",
    "preset": "training preset (quality | paper)",
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
    preset: str = DEFAULT_PRESET
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


def job_config(job: Job, run_dir: str | Path) -> TrainConfig:
    """The job's ``TrainConfig``, training into ``run_dir``."""
    cfg = apply_overrides(preset_config(job.preset), list(job.set))
    cfg.data, cfg.out, cfg.progress = job.data, str(run_dir), False
    cfg.data_format, cfg.model_dir, cfg.device = job.format, job.model_dir, job.device
    if job.iterations is not None:
        cfg.iterations = job.iterations
    return cfg.validate()


def _load(path: Path) -> Any:
    text = path.read_text()
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml  # optional: comes with the [ray] extra

        try:
            return yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise MeshsplatError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if path.suffix.lower() == ".json":
        try:
            return json.loads(text)
        except json.JSONDecodeError as exc:
            raise MeshsplatError(f"{path}: not valid JSON ({exc})") from None
    if path.suffix.lower() == ".txt":
        jobs = []
        for line in text.splitlines():
            words = shlex.split(line, comments=True)
            if words:
                jobs.append({"data": words[0], "set": words[1:]})
        return jobs
    raise MeshsplatError(f"{path}: a jobs file is .yaml, .yml, .json or .txt")


def _job(entry: Any, defaults: dict[str, Any], base: Path, index: int) -> Job:
    if isinstance(entry, str):
        entry = {"data": entry}
    if not isinstance(entry, dict) or not entry.get("data"):
        return Job(f"job{index + 1}", "", problem=f"job {index + 1}: expected a capture path or a mapping with 'data'")
    d = {**defaults, **entry, "set": [*defaults.get("set", []), *entry.get("set", [])]}
    data = Path(str(d["data"])).expanduser()
    data = data if data.is_absolute() else base / data
    name = str(d.get("name") or data.name)
    job = Job(name, str(data))
    unknown = sorted(set(d) - set(JOB_KEYS))
    if unknown:
        job.problem = f"unknown key(s) {', '.join(unknown)}; a job takes {', '.join(JOB_KEYS)}"
        return job
    try:
        for key in ("preset", "format", "model_dir", "device"):
            if key in d:
                setattr(job, key, str(d[key]))
        for key in ("iterations", "threads"):
            if key in d and d[key] is not None:
                setattr(job, key, int(d[key]))
        job.set = [str(s) for s in d["set"]]
        job.eval = bool(d.get("eval", True))
        job.export = [str(f) for f in d.get("export", ["ply"])]
    except (TypeError, ValueError) as exc:
        job.problem = f"bad value ({exc})"
        return job
    if not _NAME.match(job.name):
        job.problem = f"name {job.name!r}: letters, digits, '.', '_', '-' only"
    elif job.preset not in PRESETS:
        job.problem = f"preset {job.preset!r}: expected one of {', '.join(PRESETS)}"
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
