"""sma_stage: hysteresis modelling, compensation and identification for SMA micro-positioning stages."""

__version__ = "0.1.0"
