"""Populations: 3D-MEIs of many neurons with several seeds each, batched, resumable, on a cluster."""

from .run import DEFAULT_BATCH_SIZE, DEFAULT_PIXEL_STEPS, check_device, population_config, run_population
from .store import parse_neurons, read_table

__all__ = ["run_population", "population_config", "check_device", "parse_neurons", "read_table", "DEFAULT_BATCH_SIZE",
           "DEFAULT_PIXEL_STEPS"]
