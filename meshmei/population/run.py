"""3D-MEIs of a population of neurons: batched, resumable, idempotent, locally or on a Ray cluster."""

from __future__ import annotations

import hashlib
import time
from dataclasses import replace
from pathlib import Path

import torch

from .._files import terminate_as_interrupt
from ..encoders import Encoder, encoder_identity, frozen_encoder
from ..errors import MEIError
from ..mei import MEIResult, MEISettings, mei_batches, pixel_image_size, pixel_mei, save_run
from ..mei.batch import check_batch_size
from ..mei.optimize import check_neuron, initial, settings_for_encoder, start_name
from ..optim import MAX_STEPS, Progress
from .store import CONFIG_FORMAT, finished_neurons, neuron_dir, prepare_folder, read_summary, table_row, write_table

__all__ = ["run_population", "population_config", "neuron_results", "check_device", "DEFAULT_BATCH_SIZE",
           "DEFAULT_PIXEL_STEPS"]

DEFAULT_BATCH_SIZE = 8  # (neuron, seed) items optimised together
DEFAULT_PIXEL_STEPS = 200  # steps of each neuron's pixel MEI


def population_config(encoder: Encoder, init: str, settings: MEISettings, pixel_steps: int) -> dict:
    """What shapes every neuron's result: hashed into the folder, so that other settings never mix in. A
    lab's model enters by its identity (:func:`~meshmei.encoders.encoder_identity`: weights, code, options
    and the model file's hash, not the path it was reached by)."""
    return {"format": CONFIG_FORMAT, "encoder": encoder_identity(encoder), "init": start_identity(init, settings),
            "settings": settings.to_dict(), "pixel_mei": {"steps": pixel_steps, "seeds": list(settings.seeds)}}


def start_identity(init, settings: MEISettings) -> str:
    """A built-in start by its name; a mesh of your own by its counts and a hash of its vertices (as float64)
    and faces as the run uses them: the same mesh given as tensors, arrays or lists is one start, and a start
    that differs anywhere another (its printed form, used before, abbreviates a large tensor and rounds to
    four decimals, so a dented sphere passed for the sphere)."""
    if isinstance(init, str):
        return init
    V0, F, _ = initial(init, settings)
    h = hashlib.sha256()
    h.update(V0.detach().cpu().double().contiguous().numpy().tobytes())
    h.update(F.detach().cpu().long().contiguous().numpy().tobytes())
    return f"mesh: {V0.shape[0]} vertices, {F.shape[0]} faces, sha256 {h.hexdigest()[:16]}"


def check_device(device, *, here: bool = True) -> torch.device | None:
    """``cpu``, ``cuda`` or ``cuda:N`` as a torch device (None stays None: the encoder's own device); a clear
    error for anything else, and, with ``here``, for a CUDA device this machine does not have. A cluster's
    driver checks the name only (``here=False``): its workers have the GPUs."""
    if device is None:
        return None
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise MEIError(f"device must be cpu, cuda or cuda:N, got {device!r}") from None
    if dev.type not in ("cpu", "cuda") or (dev.type == "cpu" and dev.index not in (None, 0)):
        raise MEIError(f"device must be cpu, cuda or cuda:N, got {device!r}")
    if dev.type == "cuda" and here:
        if not torch.cuda.is_available():
            raise MEIError(f"device {device!r} asked for, but this machine has no CUDA device (torch "
                           f"{torch.__version__}{', a CPU-only build' if torch.version.cuda is None else ''})")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise MEIError(f"device {device!r} asked for, but this machine has {torch.cuda.device_count()} CUDA "
                           f"device(s): cuda:0 to cuda:{torch.cuda.device_count() - 1}")
    return dev


def _on_device(encoder: Encoder, device: torch.device | None) -> Encoder:
    """``encoder`` moved to ``device`` (in place, as ``Module.to`` does; None: where it is)."""
    if device is None or encoder.device == device or (device.index is None and encoder.device.type == device.type):
        return encoder
    return encoder.to(device)


def neuron_results(encoder: Encoder, neurons, init, settings: MEISettings, *, batch_size: int,
                   pixel_steps: int, progress: Progress | None = None):
    """Yield ``(neuron, MEIResult with the pixel MEI's response in extra, seconds)`` as neurons finish.

    The work of one process: the neurons' (neuron, seed) items in batches (:func:`meshmei.mei.mei_batches`),
    then each finished neuron's pixel MEI in the same image space (``pixel_steps`` 0: none).
    """
    for n, res in mei_batches(encoder, neurons, init, settings, batch_size=batch_size, progress=progress):
        extra, t0 = dict(res.extra), time.perf_counter()
        if pixel_steps:
            pm = pixel_mei(encoder, n, image_size=pixel_image_size(encoder, settings.image_size), steps=pixel_steps,
                           seeds=settings.seeds)  # a non-square model's own (H, W)
            extra["pixel_mei_activation"] = pm.activation
        # the neuron's share of its batches, and its own pixel MEI
        yield n, replace(res, extra=extra), res.wall_time + time.perf_counter() - t0


def _save_neuron(out: Path, digest: str, res: MEIResult, seconds: float, figures: bool) -> dict:
    """Write the neuron's run folder and return its summary; when another job on this folder (a SLURM array's
    overlapping task) finished the neuron first, with the same configuration, its folder is kept instead."""
    res = replace(res, extra={**res.extra, "config_hash": digest, "population_seconds": seconds})
    d = neuron_dir(out, res.neuron)
    try:
        save_run(res, d, figures=figures)  # never replaces a folder, also one that lands while it writes
    except MEIError:
        if not d.exists():  # not a collision: a real failure to write
            raise
    return read_summary(d, digest)  # another job's folder: its summary, or an error if made with other settings


def run_population(encoder: Encoder, neurons, out, *, init: str = "sheet", settings: MEISettings | None = None,
                   batch_size: int = DEFAULT_BATCH_SIZE, pixel_steps: int = DEFAULT_PIXEL_STEPS,
                   cluster: str | None = None, device=None,
                   figures: bool = False, progress: bool = True, **overrides) -> list[dict]:
    """3D-MEIs (and pixel MEIs) of ``neurons``, one run folder each under ``out``, and a table of them.

    Parameters
    ----------
    encoder : Encoder
        A built-in encoder or a lab's model (:func:`meshmei.encoders.encoder_from_model`).
    neurons : sequence of int
        The neurons, each with every seed of ``settings.seeds`` (the best seed is its result).
    out : path
        The population folder (see :mod:`meshmei.population.store`). Rerunning the same call skips the
        finished neurons; a call with other settings on the same folder raises :class:`MEIError`.
    init : str
        The start mesh (``"sheet"``, ``"sphere"``, ``"torus"``).
    settings : MEISettings, optional
    batch_size : int
        (neuron, seed) items optimised together in one render and model call per step.
    pixel_steps : int
        Steps of each neuron's pixel MEI (0: none; the table's pixel-MEI columns stay empty).
    cluster : None, ``"ray"`` or ``"ray://HOST:PORT"``
        None: in this process. ``"ray"``: a local Ray instance (or the cluster ``RAY_ADDRESS`` names);
        ``"ray://..."``: that cluster. Needs ``pip install "meshmei[cluster]"``.
    device : None, ``"cpu"``, ``"cuda"`` or ``"cuda:N"``
        Where the meshes are rendered and optimised and the model runs. None: the encoder's own device
        (:attr:`~meshmei.encoders.Encoder.device`). Given, the encoder is moved there (in place, as
        ``Module.to`` moves a module); with ``cluster``, each Ray task moves its copy there and asks Ray
        for one GPU for a CUDA device. The results (run folders, table) are on the CPU either way, and a
        folder's results may come from different devices (they agree to float rounding; the device is not
        part of the configuration hash).
    figures : bool
        Also write each run folder's PNG figures (about a second per neuron).
    progress : bool
        A progress bar over items (neuron x seed).
    **overrides
        Fields of :class:`MEISettings`.

    Returns
    -------
    list of dict
        The table's rows (``population.csv``), by neuron, finished ones from earlier runs included.
    """
    dev = check_device(device, here=cluster is None)
    if cluster is None:
        encoder = _on_device(encoder, dev)
    elif dev is None:  # Ray's tasks run where the encoder is (and ask for a GPU when that is one)
        dev = encoder.device
    settings = settings_for_encoder(MEISettings.with_overrides(settings, overrides), encoder).for_start(start_name(init))
    if isinstance(neurons, (str, bytes)) or not hasattr(neurons, "__iter__"):
        raise MEIError(f"neurons must be a sequence of neuron indices, e.g. [0, 1, 2] (parse_neurons reads '0-99'), "
                       f"got {neurons!r}")
    neurons = [check_neuron(encoder, n) for n in neurons]
    if not neurons:
        raise MEIError("neurons is empty; give at least one neuron")
    if isinstance(pixel_steps, bool) or not isinstance(pixel_steps, int) or pixel_steps < 0:
        raise MEIError(f"pixel_steps must be a non-negative integer, got {pixel_steps!r}")
    # the pixel MEI runs after each neuron's 3D-MEI: what it refuses is refused here, before any of them (a
    # pixel_steps of 1e20 failed after the 3D work, as "steps must be at most 1e+12")
    if pixel_steps > MAX_STEPS:
        raise MEIError(f"pixel_steps must be at most {MAX_STEPS:.0e}, got {pixel_steps!r}")
    if pixel_steps and settings.image_size < 2:  # the image size its pixel_mei call is given
        raise MEIError("the pixel MEI needs images of at least 2 x 2 pixels: raise image_size, or pass pixel_steps=0")
    check_batch_size(batch_size)
    initial(init, settings)  # a start that cannot be built fails here, before anything is written
    if neurons:  # and an encoder that cannot take images of this size (a Gabor cell at 2 px)
        with frozen_encoder(encoder), torch.no_grad():
            encoder(torch.full((1, 1, settings.image_size, settings.image_size), 0.5, dtype=settings.torch_dtype,
                               device=encoder.device), neurons[:1])
    if cluster is not None:
        from .cluster import check_cluster, check_shippable

        check_cluster(cluster)
        check_shippable(encoder)
    out = Path(out)
    digest = prepare_folder(out, population_config(encoder, init, settings, pixel_steps))
    done = finished_neurons(out, digest)
    todo = [n for n in dict.fromkeys(neurons) if n not in done]
    bar = Progress(len(todo) * len(settings.seeds), "population", unit="item", enabled=progress and bool(todo),
                   postfix=lambda rec: {"neuron": rec["neuron"], "3D-MEI": f"{rec['response']:.3f}"})
    try:
        with terminate_as_interrupt():  # a cancelled job keeps its finished neurons
            if cluster is None:
                results = neuron_results(encoder, todo, init, settings, batch_size=batch_size,
                                         pixel_steps=pixel_steps)
            else:
                from .cluster import ray_neuron_results

                results = ray_neuron_results(cluster, encoder, todo, init, settings, batch_size=batch_size,
                                             pixel_steps=pixel_steps, device=dev)
            for n, res, seconds in results:
                done[n] = _save_neuron(out, digest, res, seconds, figures)
                done = {**finished_neurons(out, digest), **done}  # with what other jobs on this folder finished
                write_table(out, done)
                for _ in settings.seeds:
                    bar.update(seconds, {"step": 0, "neuron": n, "response": res.activation})
    finally:
        bar.close()
    done = finished_neurons(out, digest)
    write_table(out, done)
    lost = [n for n in todo if n not in done]
    if lost:  # a safety net: every neuron asked for has a folder, or the run says which have none
        raise MEIError(f"neurons {lost} were asked for but produced no result")
    if done:
        from .figure import population_figure

        population_figure(out, [table_row(done[n]) for n in sorted(done)])
    return [table_row(done[n]) for n in sorted(done)]
