"""Many captures at once: ``meshsplat batch JOBS --out DIR`` trains, evaluates and exports every job of a
jobs file on Ray (``meshsplat.fleet.batch.run_batch``; docs/scale-out.md)."""

from meshsplat.fleet.jobs import Job, read_jobs
from meshsplat.fleet.runner import run_job

__all__ = ["Job", "read_jobs", "run_job"]
