"""Populations on a Ray cluster: groups of neurons as Ray tasks, results gathered by the driver.

Each task runs :func:`meshmei.population.run.neuron_results` on a group of neurons (as many as fill one
batch of (neuron, seed) items) and returns their results; only the driver writes run folders, as each
task finishes, so a task that Ray retries (its worker died) cannot write twice, and what finished before an
interruption is kept. Ray is an optional dependency: ``pip install "meshmei[cluster]"``.
"""

from __future__ import annotations

import signal
import threading

from ..encoders import encoder_from_spec, encoder_spec
from ..errors import MEIError
from ..mei import MEISettings
from .run import neuron_results

__all__ = ["ray_neuron_results", "neuron_groups", "check_shippable"]


def neuron_groups(neurons: list[int], batch_size: int, n_seeds: int) -> list[list[int]]:
    """Neurons in groups whose (neuron, seed) items fill one batch (at least one neuron per group)."""
    per = max(1, batch_size // max(1, n_seeds))
    return [neurons[i:i + per] for i in range(0, len(neurons), per)]


def _task(encoder, spec, neurons, init, settings: dict, batch_size, pixel_steps, device=None):
    """``(results, error)``: the group's finished neurons, and the error that stopped the rest (None when
    none did) as one line: a failure on one neuron does not take the group's finished ones with it.
    ``device``: where the task runs its copy of the encoder (a CUDA task sees the GPU Ray gave it as
    ``cuda``); the results come back on the CPU."""
    done = []
    try:
        enc = encoder if encoder is not None else encoder_from_spec(spec)
        if device is not None:
            enc = enc.to(device)
        for item in neuron_results(enc, neurons, init, MEISettings.from_dict(settings), batch_size=batch_size,
                                   pixel_steps=pixel_steps):
            done.append(item)
    except Exception as err:  # noqa: BLE001 - handed to the driver, which raises it after saving the rest
        return done, f"{type(err).__name__}: {err}"
    return done, None


def _collect(ray, ref) -> tuple:
    """``(results, failure)`` of a finished task: its finished neurons, and why the rest did not finish (a
    line; None if they all did): the optimisation's error, or Ray's (a worker that died every retry)."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as err:
        return [], str(err.cause if err.cause is not None else err)
    except ray.exceptions.RayError as err:  # a worker that crashed on every retry, a lost object
        return [], f"{type(err).__name__}: {str(err).strip().splitlines()[0] if str(err).strip() else ''}"


def check_shippable(encoder) -> None:
    """MEIError, before anything is written, unless ``encoder`` can reach Ray's workers: pickled (as
    :func:`ray_neuron_results` sends it), or rebuilt from the file it was loaded from (a TorchScript model)."""
    import ray.cloudpickle

    try:
        ray.cloudpickle.dumps(encoder)
        return
    except Exception as err:  # noqa: BLE001 - any pickling failure; the spec may still rebuild it
        why = f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
    try:
        encoder_from_spec(encoder_spec(encoder))
    except Exception:  # noqa: BLE001 - no file to rebuild it from
        raise MEIError(f"the encoder cannot reach Ray's workers: it cannot be pickled ({why}) and was not loaded "
                       "from a file it could be rebuilt from (load_model, --model); make it picklable, or run "
                       "without --cluster") from None


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
                       pixel_steps: int, max_retries: int = 3, device=None):
    """Yield ``(neuron, result, seconds)`` as Ray tasks finish (see :func:`~meshmei.population.run_population`).

    ``cluster``: ``"ray"`` (the cluster ``RAY_ADDRESS`` names, else a local instance started here and stopped
    at the end) or ``"ray://HOST:PORT"``. A task whose worker dies is retried up to ``max_retries`` times; an
    exception raised by the optimisation itself, or a task that still fails, ends the run with MEIError
    after every neuron that finished has been handed out: the failed task's own finished neurons and the
    other tasks' that had finished by then (the tasks still running are cancelled).

    ``device`` (a torch device or None: the encoder's): a CUDA device makes each task ask Ray for one GPU
    (``num_gpus=1``) and run on it; a cluster without GPUs is refused before any task starts.
    """
    ray = check_cluster(cluster)
    started = not ray.is_initialized()
    if started:
        # ray.init installs its own SIGTERM handler (which aborts the driver); keep the caller's, which turns
        # SIGTERM into the interrupt that keeps what finished (run_population)
        term = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
        ray.init(address=None if cluster == "ray" else cluster, log_to_driver=False, include_dashboard=False)
        if term is not None:
            signal.signal(signal.SIGTERM, term)
    try:
        try:  # the encoder itself when Ray can ship it, else its spec (a TorchScript model is reloaded)
            payload, spec = ray.put(encoder), None
        except Exception:
            payload, spec = None, encoder_spec(encoder)
        gpus = 1 if device is not None and device.type == "cuda" else 0
        if gpus and ray.cluster_resources().get("GPU", 0) < 1:
            raise MEIError(f"device {str(device)!r} asked for, but the Ray cluster has no GPU "
                           f"({ray.cluster_resources().get('CPU', 0):g} CPUs); run with --device cpu")
        # Ray sets each GPU task's CUDA_VISIBLE_DEVICES: the task's "cuda" is the GPU it was given
        where = None if device is None else ("cuda" if gpus else str(device))
        task = ray.remote(num_cpus=1, num_gpus=gpus, max_retries=max_retries)(_task)
        pending = {task.remote(payload, spec, group, init, settings.to_dict(), batch_size, pixel_steps, where): group
                   for group in neuron_groups(list(neurons), batch_size, len(settings.seeds))}
        failure = None
        while pending and failure is None:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                pending.pop(ref)
                results, failure = _collect(ray, ref)
                yield from results
        if failure is not None:
            # the tasks that finished meanwhile are kept too; the others are cancelled
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=0) if pending else ([], [])
            for ref in ready:
                pending.pop(ref)
                yield from _collect(ray, ref)[0]
            for ref in pending:
                try:
                    ray.cancel(ref, force=False)
                except Exception:  # noqa: BLE001 - it finished meanwhile: nothing to cancel
                    pass
            raise MEIError(f"a Ray task failed: {failure}")
    finally:
        if started:
            ray.shutdown()
