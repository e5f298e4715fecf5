"""Populations on a Ray cluster: groups of neurons as Ray tasks, results gathered by the driver.

Each task runs :func:`meshmei.population.run.neuron_results` on a group of neurons (as many as fill one
batch of (neuron, seed) items) and returns their results; only the driver writes run folders, as each
task finishes, so a task that Ray retries (its worker died) cannot write twice, and what finished before an
interruption is kept. Ray is an optional dependency: ``pip install "meshmei[cluster]"``.
"""

from __future__ import annotations

from ..encoders import encoder_from_spec, encoder_spec
from ..errors import MEIError
from ..mei import MEISettings
from .run import neuron_results

__all__ = ["ray_neuron_results", "neuron_groups"]


def neuron_groups(neurons: list[int], batch_size: int, n_seeds: int) -> list[list[int]]:
    """Neurons in groups whose (neuron, seed) items fill one batch (at least one neuron per group)."""
    per = max(1, batch_size // max(1, n_seeds))
    return [neurons[i:i + per] for i in range(0, len(neurons), per)]


def _task(encoder, spec, neurons, init, settings: dict, batch_size, pixel_steps):
    enc = encoder if encoder is not None else encoder_from_spec(spec)
    return list(neuron_results(enc, neurons, init, MEISettings.from_dict(settings), batch_size=batch_size,
                               pixel_steps=pixel_steps))


def check_cluster(cluster: str):
    """Ray's module for ``cluster`` (``"ray"`` or ``"ray://HOST:PORT"``), or MEIError: another value, or Ray
    not installed. Called before anything is written."""
    if cluster != "ray" and not str(cluster).startswith("ray://"):
        raise MEIError(f"cluster must be 'ray' or 'ray://HOST:PORT', got {cluster!r}")
    try:
        import ray
    except ImportError:
        raise MEIError('--cluster ray needs Ray: pip install "meshmei[cluster]"') from None
    return ray


def ray_neuron_results(cluster: str, encoder, neurons, init, settings: MEISettings, *, batch_size: int,
                       pixel_steps: int, max_retries: int = 3):
    """Yield ``(neuron, result, seconds)`` as Ray tasks finish (see :func:`~meshmei.population.run_population`).

    ``cluster``: ``"ray"`` (the cluster ``RAY_ADDRESS`` names, else a local instance started here and stopped
    at the end) or ``"ray://HOST:PORT"``. A task whose worker dies is retried up to ``max_retries`` times; an
    exception raised by the optimisation itself ends the run with that error.
    """
    ray = check_cluster(cluster)
    started = not ray.is_initialized()
    if started:
        ray.init(address=None if cluster == "ray" else cluster, log_to_driver=False, include_dashboard=False)
    try:
        try:  # the encoder itself when Ray can ship it, else its spec (a TorchScript model is reloaded)
            payload, spec = ray.put(encoder), None
        except Exception:
            payload, spec = None, encoder_spec(encoder)
        task = ray.remote(num_cpus=1, max_retries=max_retries)(_task)
        pending = {task.remote(payload, spec, group, init, settings.to_dict(), batch_size, pixel_steps): group
                   for group in neuron_groups(list(neurons), batch_size, len(settings.seeds))}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                pending.pop(ref)
                try:
                    results = ray.get(ref)
                except ray.exceptions.RayTaskError as err:
                    raise MEIError(f"a Ray task failed: {err.cause if err.cause is not None else err}") from None
                yield from results
    finally:
        if started:
            ray.shutdown()
