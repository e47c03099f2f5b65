"""One job of ``meshsplat batch``: train (resuming from the job's last checkpoint), evaluate, export.

``DIR/NAME/`` holds ``run/`` (the training run), ``export/``, ``attempts.jsonl`` (one line per attempt:
pid, host, start time, iteration resumed from) and ``result.json`` (``RESULT_KEYS``; status ``ok`` or
``failed`` with a one-line ``reason``, and the job's ``spec``). A job whose ``result.json`` says ``ok`` for
the same spec is finished: running it again returns that result. Anything else trains on from the newest
checkpoint (bit-exact resume), so a worker lost mid-run costs only the iterations since that checkpoint; a
job edited since (another spec) resumes its run where the change allows (more iterations, evaluation or
export switched on), and otherwise fails naming the change (its run is never overwritten).
"""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path
from typing import Any

import torch

from meshsplat.data.source_map import copy_source_map
from meshsplat.errors import MeshsplatError
from meshsplat.eval import evaluate_run
from meshsplat.export import export_avatar
from meshsplat.fleet.jobs import Job, job_config
from meshsplat.io.atomic import write_text_atomic
from meshsplat.run_folder import load_avatar
from meshsplat.train.trainer import Trainer

__all__ = ["run_job", "finished_result", "RESULT_KEYS", "failed_result"]

RESULT_KEYS = (
    "name",
    "status",
    "psnr",
    "ssim",
    "lpips",
    "n_gaussians",
    "iterations",
    "train_s",
    "eval_s",
    "export_s",
    "total_s",
    "attempts",
    "reason",
    "run",
)


def _result_path(out: Path, name: str) -> Path:
    return out / name / "result.json"


def _stored_result(out: Path, name: str) -> dict[str, Any] | None:
    try:
        res = json.loads(_result_path(out, name).read_text())
    except (OSError, ValueError, RecursionError):
        return None
    return res if isinstance(res, dict) else None


def finished_result(out: str | Path, job: Job) -> dict[str, Any] | None:
    """The stored result of ``job`` when it finished ``ok`` with the same spec (``Job.spec``; else None)."""
    res = _stored_result(Path(out), job.name)
    return res if res is not None and res.get("status") == "ok" and res.get("spec") == job.spec() else None


def failed_result(job: Job, reason: str, attempts: int = 0) -> dict[str, Any]:
    row: dict[str, Any] = {k: None for k in RESULT_KEYS}
    first = (reason.strip().splitlines() or ["failed"])[0]
    row.update(name=job.name, status="failed", reason=first[:400], attempts=attempts)
    return row


def _attempts(path: Path) -> int:
    return len(path.read_text().splitlines()) if path.exists() else 0


def _split_metrics(metrics: dict[str, Any]) -> dict[str, float | None]:
    """Mean of each metric over the evaluated splits (``metrics.json``'s ``splits``)."""
    out: dict[str, float | None] = {}
    for key in ("psnr", "ssim", "lpips"):
        vals = [
            float(v[key])
            for v in (metrics.get("splits") or {}).values()
            if isinstance(v, dict) and isinstance(v.get(key), (int, float)) and v.get(key) == v.get(key)
        ]
        out[key] = sum(vals) / len(vals) if vals else None
    return out


def run_job(job: Job, out: str | Path) -> dict[str, Any]:
    """Run ``job`` into ``out/NAME`` (see the module docstring); returns its result row. Bad input and
    failures are a ``failed`` row with the reason, never an exception (the fleet goes on)."""
    out = Path(out)
    if job.problem:
        return failed_result(job, job.problem)
    done = finished_result(out, job)
    if done is not None:
        return done
    before = _stored_result(out, job.name)
    edited = before is not None and before.get("spec") not in (None, job.spec())
    folder = out / job.name
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / "attempts.jsonl"
    t0 = time.perf_counter()
    try:
        torch.set_num_threads(job.threads)
        cfg = job_config(job, folder / "run")
        trainer = Trainer(cfg, resume=True)
        with open(log, "a") as fh:
            rec = {"pid": os.getpid(), "host": socket.gethostname(), "start": time.time(), "from": trainer.iteration}
            fh.write(json.dumps(rec) + "\n")
        copy_source_map(cfg.data, cfg.out)
        trainer.train()
        t_train = time.perf_counter() - t0
        row: dict[str, Any] = {k: None for k in RESULT_KEYS}
        row.update(name=job.name, status="ok", reason="", run=str(trainer.folder.root))
        row.update(n_gaussians=trainer.num_gaussians, iterations=trainer.iteration, train_s=round(t_train, 3))
        if job.eval and not [s for s in trainer.dataset.split_names if s != "train"]:
            row["reason"] = "not evaluated: the capture has no test split"
        elif job.eval:
            t1 = time.perf_counter()
            metrics = evaluate_run(trainer.folder.root, device=cfg.device, report=False, backend=cfg.backend)
            row.update(_split_metrics(metrics))
            row["eval_s"] = round(time.perf_counter() - t1, 3)
        if job.export:
            t1 = time.perf_counter()
            export_avatar(load_avatar(trainer.folder.root), folder / "export", job.data, trainer.iteration, job.export)
            row["export_s"] = round(time.perf_counter() - t1, 3)
    except MeshsplatError as exc:
        why = str(exc)
        if edited and why.startswith("cannot resume"):
            why = f"the job was edited since its run was trained, and {why}; or give the edited job another name"
        row = failed_result(job, why)
    except (OSError, MemoryError, RuntimeError, ValueError) as exc:
        row = failed_result(job, f"{type(exc).__name__}: {exc}")
    row["attempts"] = _attempts(log)
    row["total_s"] = round(time.perf_counter() - t0, 3)
    row["spec"] = job.spec()
    write_text_atomic(_result_path(out, job.name), json.dumps(row, indent=1) + "\n")
    return row
