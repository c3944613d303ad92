"""Identification (no ROS): fit the GPI model, test its residual, add the effect it lacks, report."""

from sma_stage.identify.fit import FitResult, fit_gpi, information_criterion, predict
from sma_stage.identify.metrics import ErrorMetrics, error_metrics

__all__ = ["ErrorMetrics", "FitResult", "error_metrics", "fit_gpi", "information_criterion", "predict"]
