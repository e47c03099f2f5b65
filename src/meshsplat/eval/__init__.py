"""Evaluation of trained runs: metrics on the test splits and reports (runs load via ``meshsplat.run_folder``)."""

from meshsplat.eval.evaluate import evaluate_avatar, evaluate_run

__all__ = ["evaluate_run", "evaluate_avatar"]
