"""3D-MEI run directories: write a result atomically (mesh, exact state, summary, figures) and read it back
bit for bit."""

from __future__ import annotations

import hashlib
import io
import json
import math
import pickle
import re
from pathlib import Path

import torch

from .._checks import is_finite_real, is_int, seed_twin
from .._files import atomic_directory
from ..encoders import Encoder, encoder_from_spec, eval_mode
from ..errors import MEIError, MeshError
from ..mesh import check_mesh, check_rest_pose, save_mesh
from ..plots import mei_figures
from ..quality import health_report
from .settings import MEIResult, MEISettings, rebuild_deformer

__all__ = ["RUN_FORMAT", "RUN_FILES", "is_complete_summary", "save_run", "load_run"]

RUN_FORMAT = 1
# the files a complete run folder holds (load_run needs each)
RUN_FILES = ("summary.json", "state.pt", "mesh.obj")
_SUMMARY_KEYS = {"format", "complete", "neuron", "init", "activation", "fraction_of_bound", "seed", "seed_activations",
                 "encoder", "settings", "light", "rotation_axis_angle", "translation", "n_vertices", "n_faces",
                 "wall_time_s", "seconds_per_step", "quality", "history", "loss_history", "reg_history",
                 "time_history", "sha256"}
# the files whose digests summary.json records (since 2026-11-30): another run's state.pt or mesh.obj copied in
# was read as this run's
DIGESTED = ("state.pt", "mesh.obj")


def _summary(result: MEIResult) -> dict:
    own = _own_summary(result)
    clash = sorted(set(result.extra) & set(own))
    if clash:  # load_run would read them back as the run's own (a changed activation, or a refused format)
        raise MEIError(f"result.extra holds {clash}, which are the run's own fields in summary.json; rename them")
    return {**own, **result.extra}


def _own_summary(result: MEIResult) -> dict:
    return {
        "format": RUN_FORMAT,
        "complete": True,
        "neuron": result.neuron,
        "init": result.init,
        "activation": result.activation,
        "fraction_of_bound": result.fraction_of_bound,
        "seed": result.seed,
        # a seed whose run ended without a finite response (it lost) as null: JSON has no NaN, and Python's json
        # wrote one that strict readers refuse (load_run reads null back as NaN)
        "seed_activations": {str(k): v if math.isfinite(v) else None for k, v in result.seed_activations.items()},
        "encoder": result.encoder,
        "settings": result.settings.to_dict(),
        "light": None if result.light is None else result.light.tolist(),
        "rotation_axis_angle": result.rotation.tolist(),
        "translation": result.translation.tolist(),
        "n_vertices": int(result.V.shape[0]),
        "n_faces": int(result.F.shape[0]),
        "wall_time_s": result.wall_time,
        "seconds_per_step": result.seconds_per_step,
        "quality": health_report(result.V, result.F, result.V0, self_intersections=result.V.shape[0] <= 20000),
        "history": result.history,
        "loss_history": result.loss_history,
        "reg_history": result.reg_history,
        "time_history": result.time_history,
    }


def save_run(result: MEIResult, directory, *, overwrite: bool = False, figures: bool = True) -> Path:
    """Write a run directory: ``mesh.obj``, ``rest.obj``, ``state.pt``, ``summary.json`` and PNG figures.

    ``state.pt`` holds the exact tensors (rest mesh, faces, deformer ``state_dict``, light, pose, image), so
    :func:`load_run` rebuilds the mesh and the scene bit for bit; ``summary.json`` holds the settings,
    encoder description, histories and mesh quality. Everything is written to a temporary sibling
    directory that is renamed into place only when complete, so an interrupted save never leaves a
    directory that :func:`load_run` would take for a finished run.
    """
    def write(tmp: Path):
        save_mesh(tmp / "mesh.obj", result.V, result.F)
        save_mesh(tmp / "rest.obj", result.V0, result.F)
        torch.save({"format": RUN_FORMAT, "V": result.V, "F": result.F, "V0": result.V0,
                    "deformer": result.deformer_state, "light": result.light, "rotation": result.rotation,
                    "translation": result.translation, "image": result.image, "albedo": result.albedo,
                    "albedo_uv": result.albedo_uv},
                   tmp / "state.pt")
        if figures:
            mei_figures(result, tmp)
        with open(tmp / "summary.json", "w") as fh:
            json.dump({**_summary(result), "sha256": {name: _digest(tmp / name) for name in DIGESTED}}, fh, indent=1)

    return atomic_directory(directory, write, overwrite=overwrite, error=MEIError)


def _digest(path: Path, data: bytes | None = None) -> str:
    """SHA-256 of the file at ``path``, or of ``data``, its bytes when already read."""
    return hashlib.sha256(path.read_bytes() if data is None else data).hexdigest()


def _check_summary(summary: dict, state: dict, directory: Path, state_bytes: bytes) -> None:
    """Raise MEIError unless summary.json's own fields have their types and agree with state.pt and the files
    (a NaN or text activation, a neuron of -1 or 3.7, a history of text were read as they were; another run's
    state.pt or summary.json copied in was read as this run)."""
    def damaged(why: str):
        return MEIError(f"{directory / 'summary.json'} is damaged: {why}")

    def reals(x) -> bool:
        return isinstance(x, list) and all(map(is_finite_real, x))

    def by_seed(x) -> bool:  # {"0": 0.91, "1": null}: null for a seed that ended without a finite response
        return isinstance(x, dict) and all(re.fullmatch(r"-?[0-9]+", k) and (v is None or is_finite_real(v))
                                           for k, v in x.items())

    for key, ok, want in (("neuron", lambda x: is_int(x) and x >= 0, "a non-negative integer"),
                          ("seed", is_int, "an integer"),  # a seed beyond SEED_RANGE (-3) loads as its twin
                          ("activation", is_finite_real, "a finite number"),
                          ("wall_time_s", lambda x: is_finite_real(x) and x >= 0, "a finite number >= 0"),
                          ("seconds_per_step", lambda x: is_finite_real(x) and x >= 0, "a finite number >= 0"),
                          ("init", lambda x: isinstance(x, str), "a string"),
                          ("history", reals, "a list of finite numbers"),
                          ("loss_history", reals, "a list of finite numbers"),
                          ("seed_activations", by_seed, "a dict of seeds to finite numbers or null")):
        if key in summary and not ok(summary[key]):
            raise damaged(f"{key} must be {want}, got {summary[key]!r:.80}")
    sizes = {"n_vertices": state["V"].shape[0], "n_faces": state["F"].shape[0]}
    for key, size in sizes.items():
        if key in summary and summary[key] != size:
            raise MEIError(f"{directory}: summary.json's {key} is {summary[key]!r} and state.pt's mesh has {size}: "
                           "the two files are not of one run")
    digests = summary.get("sha256")
    if digests is None:  # a run saved before 2026-11-30
        return
    if not isinstance(digests, dict):
        raise damaged(f"sha256 must be a dict of file digests, got {type(digests).__name__}")
    read = {"state.pt": state_bytes}  # read once, for torch.load and for its digest
    changed = [name for name in DIGESTED
               if name in digests and _digest(directory / name, read.get(name)) != digests[name]]
    if changed:
        raise MEIError(f"{directory}: {' and '.join(changed)} {'is' if len(changed) == 1 else 'are'} not the file(s) "
                       "save_run wrote with this summary.json (another run's, or edited); save the run again")


def is_complete_summary(summary) -> bool:
    """Whether a parsed ``summary.json`` is one :func:`save_run` finished, in this :data:`RUN_FORMAT`."""
    return isinstance(summary, dict) and summary.get("complete") is True and summary.get("format") == RUN_FORMAT


def _check_state(state, path: Path) -> None:
    """Raise MEIError naming ``path`` unless ``state`` holds what :func:`save_run` writes: a mesh, its rest
    pose, the deformer's finite tensors, the image and the pose (a missing key was blamed on summary.json, a
    list or an empty V failed inside torch, NaN offsets passed the reproduction check)."""

    def damaged(why: str):
        return MEIError(f"{path} is damaged: {why}")

    if not isinstance(state, dict):
        raise damaged(f"it holds a {type(state).__name__}, not the dict save_run writes")
    if state.get("format", RUN_FORMAT) != RUN_FORMAT:  # a format 9 was read as this version's
        raise damaged(f"its format is {state['format']!r}, not this version's {RUN_FORMAT!r}")
    missing = [k for k in ("V", "F", "V0", "deformer", "rotation", "translation", "image") if k not in state]
    if missing:
        raise damaged(f"missing {missing}")
    wrong = {k: type(state[k]).__name__ for k in ("V", "F", "V0") if not isinstance(state[k], torch.Tensor)}
    if wrong:  # check_mesh takes lists and arrays too; save_run writes tensors
        raise damaged(f"{', '.join(wrong)} must be tensors, got {', '.join(wrong.values())}")
    try:
        V, F = check_mesh(state["V"], state["F"])
        check_rest_pose(state["V0"], V, F)
    except MeshError as err:
        raise damaged(str(err)) from None
    deformer = state["deformer"]
    if not isinstance(deformer, dict) or not all(isinstance(deformer.get(k), torch.Tensor) for k in ("offsets", "V0")):
        raise damaged("the deformer state must be a dict with 'offsets' and 'V0' tensors")
    tensors = {f"deformer {k}": v for k, v in deformer.items() if isinstance(v, torch.Tensor) and v.is_floating_point()}
    tensors.update((k, state[k]) for k in ("rotation", "translation", "image", "light", "albedo")
                   if state.get(k) is not None)
    for name, t in tensors.items():
        if not isinstance(t, torch.Tensor) or not t.is_floating_point() or t.numel() == 0:
            raise damaged(f"{name} must be a non-empty float tensor, got {type(t).__name__}")
        if not bool(torch.isfinite(t).all()):
            raise damaged(f"{name} holds NaN or Inf")
    for name, shape in (("rotation", (3,)), ("translation", (3,)), ("light", (3,))):
        if state.get(name) is not None and tuple(state[name].shape) != shape:
            raise damaged(f"{name} must have shape {shape}, got {tuple(state[name].shape)}")
    albedo, uv, n = state.get("albedo"), state.get("albedo_uv"), V.shape[0]
    if albedo is not None:  # a light of (5,) or an albedo of [1.0] loaded and failed when the run was rendered
        texture = albedo.ndim == 2 and isinstance(uv, torch.Tensor) and tuple(uv.shape) == (n, 2)
        if not (texture or tuple(albedo.shape) == (n,)):
            with_uv = f" with albedo_uv {tuple(uv.shape)}" if isinstance(uv, torch.Tensor) else ""
            raise damaged(f"albedo must be one value per vertex ({n},) or a texture with albedo_uv ({n}, 2), got "
                          f"{tuple(albedo.shape)}{with_uv}")


def _check_response(module: Encoder, image: torch.Tensor, neuron: int, activation: float, directory: Path,
                    given: bool) -> None:
    """Raise MEIError unless ``module`` gives the saved image the response the run recorded (to 1e-3 of its
    size: another device or thread count rounds differently). A summary.json whose encoder was edited, or a
    model that is not the run's, would otherwise be swept and reported under the run's name."""
    with torch.no_grad(), eval_mode(module):  # as the run read it
        response = float(module(image.to(module.device), neuron)[0, 0])
    if not abs(response - activation) <= 1e-3 * (1 + abs(activation)):
        which = "the encoder given" if given else f"the encoder summary.json describes ({directory / 'summary.json'})"
        raise MEIError(f"{directory}: {which} gives the saved image a response of {response:.6g} for neuron "
                       f"{neuron}; the run recorded {activation:.6g}, so it is not the run's encoder")


def load_run(directory, *, encoder: Encoder | None = None, rebuild_encoder: bool = False) -> MEIResult:
    """Read a run directory written by :func:`save_run` back into an :class:`MEIResult`.

    The vertices are recomputed from the saved rest mesh and deformer state and checked against the saved
    ones, to within the RBF truncation bound (:meth:`MEIResult.deformer`); the saved ones are returned.
    With ``rebuild_encoder=True`` (or ``encoder`` given), the returned result also carries the encoder as
    ``encoder_module``.

    Raises
    ------
    MEIError
        The directory is missing, incomplete (an interrupted save leaves only a hidden ``.partial``
        sibling, never the directory itself), or its files are corrupt.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise MEIError(f"no MEI run directory at {directory}")
    missing = [n for n in RUN_FILES if not (directory / n).is_file()]
    if missing:
        raise MEIError(f"{directory} is not a complete MEI run: missing {missing}")
    try:
        with open(directory / "summary.json") as fh:
            summary = json.load(fh)
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise MEIError(f"{directory / 'summary.json'} is unreadable: {err}") from None
    if not is_complete_summary(summary):
        raise MEIError(f"{directory} holds no complete run of format {RUN_FORMAT}")
    try:
        state_bytes = (directory / "state.pt").read_bytes()
        state = torch.load(io.BytesIO(state_bytes), map_location="cpu", weights_only=True)
    except Exception as err:  # torch.load's errors on a damaged or foreign file
        # not torch's advice to load it with weights_only=False, which would run whatever the file holds
        why = "it is not a file save_run wrote" if isinstance(err, pickle.UnpicklingError) else str(err).split("\n")[0]
        raise MEIError(f"{directory} is corrupt: state.pt: {type(err).__name__}: {why}") from None
    _check_state(state, directory / "state.pt")
    _check_summary(summary, state, directory, state_bytes)
    try:
        settings = MEISettings.from_dict(summary["settings"])
        rbf = rebuild_deformer(state["V0"], state["deformer"], settings)
        with torch.no_grad():
            V = rbf()
    except MEIError:
        raise
    except Exception as err:  # torch.load / load_state_dict errors on a damaged file
        raise MEIError(f"{directory} is corrupt: {type(err).__name__}: {err}") from None
    # The rebuilt deformer's pair list and the optimised one's (from its last rebuild) both hold every
    # (vertex, kernel) pair within r_cut of the final scales; a pair only one of them holds has a weight below
    # exp(-r_cut^2 / 2), and for a given vertex each kernel is missing from at most one of the lists. So the two
    # meshes agree to exp(-r_cut^2 / 2) times the summed offset lengths (plus float round-off), and no closer
    # in general (MEIResult.deformer). The saved vertices are kept.
    offsets = state["deformer"]["offsets"].double()
    bound = math.exp(-rbf.r_cut**2 / 2) * float(offsets.norm(dim=-1).sum())
    bound += 1e-5 * (1 + float(state["V"].abs().max()))
    if V.shape != state["V"].shape or float((V.double() - state["V"].double()).abs().max()) > bound:
        raise MEIError(f"{directory}: the deformer state does not reproduce the saved vertices")
    size = settings.image_size
    if tuple(state["image"].shape) != (1, 1, size, size):  # render.image_size yields to image_size when read
        raise MEIError(f"{directory}: the saved image has shape {tuple(state['image'].shape)}, not the (1, 1, {size}, "
                       f"{size}) of summary.json's image_size")
    try:  # a summary.json of the right format whose fields are missing or of the wrong type
        module = None
        if encoder is not None or rebuild_encoder:
            module = encoder if encoder is not None else encoder_from_spec(summary["encoder"])
            if module.n_neurons <= int(summary["neuron"]):
                raise MEIError(f"the encoder has {module.n_neurons} neurons; the run used neuron {summary['neuron']}")
            _check_response(module, state["image"], int(summary["neuron"]), float(summary["activation"]), directory,
                            given=encoder is not None)
        return MEIResult(
            V=state["V"], F=state["F"], V0=state["V0"], image=state["image"], activation=float(summary["activation"]),
            history=summary["history"], loss_history=summary["loss_history"], reg_history=summary["reg_history"],
            seed=seed_twin(summary["seed"]),  # as MEISettings.from_dict reads a seed beyond SEED_RANGE
            seed_activations={seed_twin(int(k)): math.nan if v is None else v
                              for k, v in summary["seed_activations"].items()},
            settings=settings, neuron=int(summary["neuron"]), encoder=summary["encoder"],
            deformer_state=state["deformer"], light=state["light"], rotation=state["rotation"],
            translation=state["translation"], init=summary["init"], wall_time=float(summary["wall_time_s"]),
            seconds_per_step=float(summary["seconds_per_step"]), time_history=summary.get("time_history", []),
            extra={k: summary[k] for k in summary if k not in _SUMMARY_KEYS}, encoder_module=module,
            albedo=state.get("albedo"), albedo_uv=state.get("albedo_uv"))
    except MEIError:
        raise
    except (KeyError, TypeError, AttributeError, ValueError) as err:
        raise MEIError(f"{directory / 'summary.json'} is damaged: {type(err).__name__}: {err}") from None
