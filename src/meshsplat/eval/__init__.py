"""Evaluation of trained runs: metrics on the test splits, reports, run loading."""
from meshsplat.eval.evaluate import evaluate_avatar, evaluate_run
from meshsplat.eval.run import LoadedRun, load_run, run_dataset_path

__all__ = ["evaluate_run", "evaluate_avatar", "LoadedRun", "load_run", "run_dataset_path"]
