"""Evaluation of trained runs: metrics on the test splits, reports, run loading."""
from meshsplat.eval.evaluate import BACKGROUNDS, background_color, evaluate_avatar, evaluate_run
from meshsplat.eval.run import LoadedRun, load_run, run_dataset_path

__all__ = ["evaluate_run", "evaluate_avatar", "background_color", "BACKGROUNDS",
           "LoadedRun", "load_run", "run_dataset_path"]
