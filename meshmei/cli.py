"""Command-line entry point, ``meshmei <command>``: every command's parser, its defaults read from the
settings dataclasses, and a thin runner that calls the library."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import torch

from ._checks import positive_int
from ._files import atomic_directory, check_apart, check_output, terminate_as_interrupt
from .encoders import load_model, make_encoder
from .errors import MEIError, ReconstructionError, TuningError
from .mei import MEISettings, diverse_meis, optimize_mei, pixel_image_size, pixel_mei, save_run
from .mei.diverse import MAX_MEMBERS
from .mei.optimize import start_from_file
from .mei.runs import RUN_FILES
from .mei.settings import ALBEDO_MIN_STEPS, DEFAULT_STEPS
from .plots import diverse_figure
from .population import DEFAULT_BATCH_SIZE, DEFAULT_PIXEL_STEPS, check_device, parse_neurons, run_population
from .quality import closedness, health_line
from .regularizer_table import tabulate_regularizers
from .reconstruct import (
    METHODS,
    SOURCE_NAMES,
    ReconstructionSettings,
    ReconstructionWarning,
    reconstruct,
    resolve_source,
    save_reconstruction,
    schedule_from_text,
    target_surface,
)
from .reconstruct.surgery import surgery_lines
from .shapes import DEFAULT_N_VERTICES, INITIAL_KINDS
from .shapes.targets import THIN_TARGETS
from .story import FULL, QUICK, run_story
from .tuning import parse_range, run_tuning
from .tuning.files import SWEEP_KINDS

__all__ = ["main", "build_parser"]

ENCODERS = ("gabor-simple", "gabor-complex", "demo")


def _steps_help(mesh_files: bool) -> str:
    return (f"Adam steps per seed (default: {DEFAULT_STEPS['sheet']} from the sheet"
            + (f", {DEFAULT_STEPS['custom']} from a mesh file" if mesh_files else "")
            + f", {DEFAULT_STEPS['sphere']} from the sphere, {DEFAULT_STEPS['torus']} from the torus; at least "
              f"{ALBEDO_MIN_STEPS} with --albedo)")


# the options that name files or folders (a model spec, path:factory, too)
PATH_OPTIONS = ("out", "init", "target", "model", "mei")


def _add_model_options(p, instead: str) -> None:
    """``--model`` and the adapter's options (:func:`meshmei.encoders.load_model`), shared by mei and demo."""
    p.add_argument("--model", default=None, metavar="SPEC",
                   help=f"your own model instead of {instead}: path/to/model.py:factory (the factory returns "
                        "meshmei.encoder_from_model(...) or a dict of its arguments) or a TorchScript file "
                        "(give --mean and --std)")
    p.add_argument("--mean", type=float, default=None, help="training mean, in the model's pixel units (--model)")
    p.add_argument("--std", type=float, default=None, help="training std, in the model's pixel units (--model)")
    p.add_argument("--norm", type=_norm, default=None,
                   help="L2 norm of the preprocessed image, or 'none' to keep the standardised image as it is "
                        "(--model; default 25)")
    p.add_argument("--channels", type=int, default=None, help="input channels of the model (--model; default 1)")
    p.add_argument("--pixel-range", default=None, metavar="LO,HI",
                   help="the model's pixel units for the renderer's 0..1, e.g. 0,255 (--model; default 0,1)")
    p.add_argument("--clip", action="store_true", default=None, help="clip pixels to --pixel-range (--model)")
    p.add_argument("--data-key", default=None, help="passed to the model as data_key=... (multi-session readouts)")


def _add_encoder_options(p, default: str) -> None:
    """``--encoder`` (a built-in one, ``default`` when neither it nor ``--model`` is given) and ``--model``."""
    p.add_argument("--encoder", default=None, choices=ENCODERS, help=f"a built-in encoder (default {default})")
    p.set_defaults(default_encoder=default)  # None above: an --encoder given with --model is refused, not ignored
    _add_model_options(p, "--encoder")


def _encoder_name(args) -> str:
    """The built-in encoder a ``meshmei mei`` or ``population`` run without ``--model`` uses."""
    return args.encoder or args.default_encoder


def _add_mei(sub) -> None:
    d = MEISettings()
    p = sub.add_parser("mei", help="optimise a 3D-MEI for one neuron and write mesh, renders and summary")
    _add_encoder_options(p, "gabor-simple")
    p.add_argument("--neuron", type=int, default=0)
    p.add_argument("--init", default="sheet",
                   help=f"{', '.join(INITIAL_KINDS)} (default sheet), or a mesh file, centred and scaled to a "
                        "largest side of 1 as the built-in starts")
    p.add_argument("--out", required=True, help="run directory to write (must not exist unless --overwrite)")
    p.add_argument("--steps", type=int, default=None, help=_steps_help(mesh_files=True))
    p.add_argument("--seeds", type=int, nargs="+", default=list(d.seeds))
    p.add_argument("--image-size", type=int, default=None,
                   help=f"render size in pixels (default {d.image_size}); with --model, the model's input size "
                        "(default: what its factory sets, else 100), which it is rendered at (a non-square one at its "
                        "longer side, then centre-cropped)")
    p.add_argument("--n-vertices", type=int, default=None,
                   help=f"vertex count of a built-in --init (default {d.n_vertices}); a mesh file keeps its own")
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--weight", action="append", default=[], metavar="NAME=W",
                   help="regularizer weight, e.g. --weight laplacian=1 (repeatable)")
    p.add_argument("--optimize-light", action="store_true")
    p.add_argument("--optimize-pose", action="store_true")
    _add_objective_options(p, d)
    p.add_argument("--diverse", type=int, default=1, metavar="K",
                   help="K diverse 3D-MEIs of the neuron, optimised together and pushed apart (default 1: one); "
                        "the members' seeds are s, s+1, ..., s+K-1 from the first of --seeds, s (the others are "
                        "not used)")
    p.add_argument("--pixel-mei", action="store_true", help="also run the pixel-MEI baseline and compare")
    p.add_argument("--device", default="cpu",
                   help="cpu, cuda or cuda:N: where the model runs and the mesh is rendered and optimised (the "
                        "step guard's checks stay on the CPU; the run folder is the same either way)")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_run_mei)


def _add_objective_options(p, d: MEISettings) -> None:
    """What a 3D-MEI optimises and how its steps are checked: the options ``mei`` and ``population`` share."""
    p.add_argument("--albedo", action="store_true",
                   help="also optimise the surface albedo (a texture over the sheet's grid; per vertex otherwise)")
    p.add_argument("--robust-pose", type=float, default=0.0, metavar="DEG",
                   help="maximise the expected response over object turns uniform within +-DEG (3 x 3 Gauss-Legendre "
                        "quadrature; default 0: off)")
    p.add_argument("--robust-light", type=float, default=0.0, metavar="DEG",
                   help="maximise the expected response over light positions turned uniformly within +-DEG (3 x 3 "
                        "Gauss-Legendre quadrature; default 0: off)")
    p.add_argument("--valid-steps", action=argparse.BooleanOptionalAction, default=d.valid_steps,
                   help="accept only steps whose mesh has no self-intersection, flipped face or collapsed triangle "
                        f"(default {'on' if d.valid_steps else 'off'})")
    p.add_argument("--reg-ref-vertices", type=_count_or_none, default=d.reg_ref_vertices, metavar="N|none",
                   help=f"the vertex count the regularizer weights are stated for (default {d.reg_ref_vertices}): "
                        "they are scaled to the run's mesh, and a finer mesh's step shrinks with its edge length; "
                        "'none': the weights and --lr as given at every size")


def _count_or_none(text: str):
    """An argparse type: a positive integer, or ``none``."""
    if text.lower() == "none":
        return None
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a positive integer or 'none', got {text!r}") from None


def _objective_settings(args) -> dict:
    return dict(valid_steps=args.valid_steps, albedo=args.albedo, robust_pose=args.robust_pose,
                robust_light=args.robust_light, reg_ref_vertices=args.reg_ref_vertices)


def _weights(items: list) -> dict:
    weights = dict(MEISettings().weights)
    for item in items:
        name, _, w = item.partition("=")
        try:
            weights[name] = float(w)
        except ValueError:
            raise MEIError(f"--weight expects NAME=NUMBER, got {item!r}") from None
    return weights


def _pixel_range(text):
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise MEIError(f"--pixel-range expects LO,HI, e.g. 0,255; got {text!r}") from None
    return (lo, hi)


_NO_NORM = "none"


def _norm(text: str):
    """``--norm``: a number, or ``none`` (no rescaling)."""
    if text.strip().lower() == _NO_NORM:
        return _NO_NORM
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number or 'none', got {text!r}") from None


def _cli_encoder(args, default=None):
    """The encoder of ``meshmei mei`` or ``demo``: ``--model`` (a lab's model, loaded and checked), else
    ``--encoder`` (mei) or ``default`` (demo: None, the shipped demo model)."""
    if args.model is None:
        given = [f"--{k.replace('_', '-')}" for k in ("mean", "std", "norm", "channels", "pixel_range", "clip", "data_key")
                 if getattr(args, k) is not None]
        if given:
            raise MEIError(f"{', '.join(given)} {'applies' if len(given) == 1 else 'apply'} to --model only")
        return make_encoder(_encoder_name(args)) if hasattr(args, "encoder") else default
    if getattr(args, "encoder", None) is not None:  # it was ignored without a word
        raise MEIError(f"--model and --encoder {args.encoder} each name the model: give one of them")
    given = dict(mean=args.mean, std=args.std, norm=args.norm, channels=args.channels, clip=args.clip,
                 pixel_range=None if args.pixel_range is None else _pixel_range(args.pixel_range),
                 image_size=getattr(args, "image_size", None))  # --image-size: the model's input size
    options = {k: (None if v == _NO_NORM else v) for k, v in given.items() if v is not None}  # what was given
    if args.data_key is not None:
        options["forward_kwargs"] = {"data_key": args.data_key}
    return load_model(args.model, **options)


def _image_size(args, encoder) -> int:
    """The render size: the longer side of a lab's model's input, else ``--image-size``, else the default."""
    size = getattr(encoder, "image_size", None)
    if size is not None:
        return int(max(size))
    return args.image_size if args.image_size is not None else MEISettings.image_size


def _mei_start(init: str):
    """``--init`` of ``meshmei mei``: a built-in start by name, or a mesh file (:func:`start_from_file`)."""
    if init in INITIAL_KINDS:
        return init
    if not Path(init).is_file():
        raise MEIError(f"--init must be one of {', '.join(INITIAL_KINDS)} or a mesh file; {init!r} is neither")
    return start_from_file(init)


def _mei_n_vertices(args, init) -> int:
    """``--n-vertices`` of ``meshmei mei``: a built-in start's size, refused with a mesh file, whose own count is
    what the run records."""
    if isinstance(init, str):
        return MEISettings.n_vertices if args.n_vertices is None else args.n_vertices
    if args.n_vertices is not None:
        raise MEIError(f"--n-vertices {args.n_vertices} sets the size of a built-in --init ({', '.join(INITIAL_KINDS)}); "
                       f"the mesh file {args.init} keeps its own {init[0].shape[0]} vertices: leave --n-vertices out")
    return int(init[0].shape[0])


def _inputs_apart(out, inputs, error) -> None:
    """Refuse an output folder that is, or holds, one of the command's input files (a model file, possibly
    ``path:factory``; a start or target mesh file): ``--overwrite`` would delete it."""
    for given in inputs:
        if given is None:
            continue
        text = str(given)
        path = Path(text) if Path(text).exists() or ":" not in text else Path(text.rsplit(":", 1)[0])
        if path.exists():
            check_apart(out, path, error, f"the input {text}")


def _run_mei(args) -> int:
    out = Path(args.out)
    check_output(out, overwrite=args.overwrite, error=MEIError, how="--overwrite")  # before the run, not after it
    _inputs_apart(out, (args.model, args.init), MEIError)
    device = check_device(args.device)  # a device this machine lacks: refused before the model is built
    if not 1 <= args.diverse <= MAX_MEMBERS:  # before the model is built, as the device
        raise MEIError(f"--diverse K needs 1 <= K <= {MAX_MEMBERS} (1: one ordinary 3D-MEI), got {args.diverse}")
    encoder = _cli_encoder(args).to(device)
    init = _mei_start(args.init)
    n_vertices = _mei_n_vertices(args, init)
    image_size = _image_size(args, encoder)
    settings = MEISettings(steps=args.steps, seeds=tuple(args.seeds), image_size=image_size,
                           n_vertices=n_vertices, lr=args.lr, weights=_weights(args.weight),
                           optimize_light=args.optimize_light, optimize_pose=args.optimize_pose,
                           **_objective_settings(args))
    if args.diverse > 1:
        return _run_diverse(args, encoder, settings, out, init)
    res = optimize_mei(encoder, args.neuron, init, settings, progress=not args.quiet)
    frac = res.fraction_of_bound
    line = (f"3D-MEI neuron {res.neuron} ({args.model or _encoder_name(args)}, {args.init}): "
            f"response {res.activation:.4f}")
    if frac is not None:
        line += f" = {frac:.3f} of the upper bound"
    if args.pixel_mei:
        pm = pixel_mei(encoder, args.neuron, image_size=pixel_image_size(encoder, image_size),
                       seeds=settings.seeds)  # --seeds for both
        line += f"; pixel MEI {pm.activation:.4f}"
        res = replace(res, extra={**res.extra, "pixel_mei_activation": pm.activation})
    save_run(res, out, overwrite=args.overwrite)
    h = res.health()
    line += f"; {health_line(h)}"
    undone = res.extra.get("guard", {}).get("undone", 0)
    if undone:  # a stalled run: its response says nothing of the neuron
        line += f"; the step guard undid {undone} of its {res.settings.steps} steps"
    print(line)
    albedo = ", albedo.png" if res.albedo is not None else ""
    print(f"wrote {out}/: mesh.obj, rest.obj, state.pt, summary.json, render.png, views.png, activation.png{albedo} "
          f"({res.wall_time:.1f} s, {1000 * res.seconds_per_step:.0f} ms per step)")
    return 0


def _run_diverse(args, encoder, settings, out: Path, init) -> int:
    """``meshmei mei --diverse K``: OUT/member_<i> run folders, OUT/diversity.json and OUT/diverse.png."""
    d = diverse_meis(encoder, args.neuron, args.diverse, init, settings)
    results, summary = list(d.results), {"responses": d.responses, "dissimilarity": d.dissimilarity.tolist()}
    summary.update({k: v for k, v in d.results[0].extra["diverse"].items() if k != "member"})  # k, seeds, weights
    pixel = ""
    if args.pixel_mei:  # one baseline for the neuron, recorded with every member
        pm = pixel_mei(encoder, args.neuron, image_size=pixel_image_size(encoder, settings.image_size),
                       seeds=settings.seeds)
        results = [replace(r, extra={**r.extra, "pixel_mei_activation": pm.activation}) for r in results]
        summary["pixel_mei_activation"] = pm.activation
        pixel = f"; pixel MEI {pm.activation:.4f}"

    def write(tmp: Path) -> None:  # the whole set at once: --overwrite leaves nothing of an earlier run
        for i, res in enumerate(results):
            save_run(res, tmp / f"member_{i}")
        (tmp / "diversity.json").write_text(json.dumps(summary, indent=1))
        diverse_figure(d, tmp / "diverse.png")

    atomic_directory(out, write, overwrite=args.overwrite, error=MEIError)
    off = d.dissimilarity[~torch.eye(len(d.results), dtype=torch.bool)]
    health = [r.health() for r in d.results]
    clean = sum(1 for h in health if h["self_intersections"] == 0 and h["flipped_faces"] == 0)
    print(f"{len(d.results)} diverse 3D-MEIs of neuron {args.neuron}: responses "
          f"{', '.join(f'{r:.4f}' for r in d.responses)}{pixel}; mean pairwise dissimilarity {float(off.mean()):.3f}; "
          f"{clean} of {len(health)} free of self-intersections and flipped faces (min triangle quality "
          f"{min(h['min_quality'] for h in health):.3f}; {sum(h['watertight'] for h in health)} watertight, "
          f"{sum(h['nonmanifold_edges'] == 0 for h in health)} manifold); wrote {out}/member_*, diversity.json, "
          "diverse.png")
    return 0


def _add_reconstruct(sub) -> None:
    d = ReconstructionSettings()
    p = sub.add_parser(
        "reconstruct",
        help="deform a sphere/torus/mesh into a target mesh by Chamfer minimisation",
        description="Deform a starting mesh into a target by Chamfer minimisation; writes mesh.obj, "
                    "history.json, loss.png and metrics.png to --out.",
    )
    p.add_argument("--init", default="sphere",
                   help="sphere, torus, sheet, torus-centred, torus-through-opening, or a mesh file (default "
                        "sphere). 'torus' starts with its hole through the target's most open through-hole when "
                        "it has one (a teapot's handle; meshmei.reconstruct.openings.torus_through_opening), else "
                        "centred; 'torus-centred' is always centred; 'torus-through-opening' fails without an "
                        "opening")
    p.add_argument("--target", required=True,
                   help=f"bunny, teapot, {', '.join(THIN_TARGETS)} (thin parts), or a mesh file (normalised to "
                        "unit diagonal)")
    p.add_argument("--out", required=True, help="output folder (must not exist unless --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--method", choices=METHODS, default=d.method)
    p.add_argument("--n-vertices", type=int, default=None,
                   help=f"vertices of a generated --init mesh (default {DEFAULT_N_VERTICES}; not for a mesh file)")
    p.add_argument("--steps", type=int, default=d.steps)
    p.add_argument("--time-budget", type=float, default=d.time_budget, help="seconds of optimisation")
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--samples", type=int, default=d.n_samples, help="Chamfer samples per step")
    p.add_argument("--stages", default="auto",
                   help="comma-separated vertex counts, e.g. 600,2500,2500 (equal shares); 'auto2': n/4,n,n; "
                        "'auto3': n/16,n/4,n,n (default_stages(n, levels=3); for rbf also half the --samples and "
                        "pairing by normal in the first stage, at most 150 and 250 steps in the two coarse stages "
                        "and a quarter of the Laplacian weight in the two fine stages: RBF_THREE_LEVEL_OVERRIDES); "
                        "'auto4': auto3's schedule for n/4, then one stage at n (n/64,n/16,n/4,n/4,n; for rbf the "
                        "same settings, at most 350 and 250 steps in the two n/4 stages, and a fifth of their "
                        "Laplacian weight in the last stage: "
                        "RBF_FOUR_LEVEL_OVERRIDES); "
                        "'auto' (default): auto4 for rbf from 8,000 vertices, auto3 from 2,000, else auto2 "
                        "(default_schedule), counted on the start as built (a generated one lands within about 8 %% "
                        "of --n-vertices); 'none': one stage")
    p.add_argument("--eval-every", type=int, default=d.eval_every)
    p.add_argument("--eval-samples", type=int, default=d.eval_samples)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--valid-steps", action=argparse.BooleanOptionalAction, default=d.valid_steps,
                   help="accept only steps whose mesh has no new self-intersection, no face turned over in one "
                        "step and no collapsed triangle; remeshes that add intersections are retried (default "
                        f"{'on' if d.valid_steps else 'off'}; --no-valid-steps turns it off)")
    p.add_argument("--contact-weight", type=float, default=d.w_contact,
                   help="weight of the contact barrier that keeps the surface from touching itself (0: off; "
                        f"default {d.w_contact:g})")
    p.add_argument("--facing-weight", type=float, default=d.w_facing,
                   help="weight of the term on surface turned away from the target's nearest normal, which "
                        f"unfolds folds lying on the target (0: off; default {d.w_facing:g})")
    edges = {"auto": "auto", True: "on", False: "off"}[d.contact_edges]
    p.add_argument("--contact-edges", choices=("auto", "on", "off"), default=edges,
                   help="pair edges with edges in the contact barrier: 'auto' in a stage once the guard has refused "
                        f"a few steps at an edge contact, 'on' in every stage (slower), 'off' never (default {edges})")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run_reconstruct)


def _run_reconstruct(args) -> int:
    # Check the output folder and resolve both meshes first: bad input fails before any optimisation starts.
    check_output(args.out, overwrite=args.overwrite, error=ReconstructionError, how="--overwrite")
    _inputs_apart(args.out, (args.init, args.target), ReconstructionError)
    # a name that is neither is refused below, as a source neither built in nor a file (not "the mesh file bogus")
    if args.n_vertices is not None and args.init not in SOURCE_NAMES and Path(args.init).exists():
        raise ReconstructionError(f"--n-vertices {args.n_vertices} sets the size of a generated --init "
                                  f"({', '.join(SOURCE_NAMES)}), not of the mesh file {args.init}; remesh the file "
                                  f"instead, or leave --n-vertices out")
    target = target_surface(args.target)
    V, F, placement = resolve_source(args.init, DEFAULT_N_VERTICES if args.n_vertices is None else args.n_vertices,
                                      torch.float32, target)
    if placement is not None:
        print(f"{args.init}: {V.shape[0]} vertices, placed {placement}")
    stages, fractions, overrides = schedule_from_text(args.stages, args.method, V.shape[0], n_samples=args.samples)
    with warnings.catch_warnings():  # printed below, as one line each, from the result
        warnings.simplefilter("ignore", ReconstructionWarning)
        res = reconstruct((V, F), target, args.method, steps=args.steps, time_budget=args.time_budget, lr=args.lr,
                          n_samples=args.samples, stages=stages, stage_fractions=fractions, stage_overrides=overrides,
                          eval_every=args.eval_every, eval_samples=args.eval_samples, seed=args.seed,
                          valid_steps=args.valid_steps, w_contact=args.contact_weight, w_facing=args.facing_weight,
                          contact_edges={"auto": "auto", "on": True, "off": False}[args.contact_edges],
                          progress=not args.no_progress)
    out = save_reconstruction(res, args.out, overwrite=args.overwrite, init=str(args.init), target=str(args.target))
    f = res.final
    stalled = res.info["warnings"]
    print(f"{args.method}: {len(res.history)} steps in {res.wall_time:.1f} s; Chamfer-L2 {f.chamfer_l2:.3e}, "
          f"F-score {f.fscore:.3f}, normal consistency {f.normal_consistency:.3f}, area {f.area_ratio:.2f}x the "
          f"target's; {f.self_intersections} self-intersecting pairs, {f.inverted_faces} faces against the "
          f"target's normals, {f.degenerate_faces} degenerate, min triangle quality {f.min_quality:.3f}, "
          f"{closedness(f.boundary_edges, f.nonmanifold_edges)}; wrote {out}"
          + (f"; WARNING: {len(stalled)} warning(s) (below)" if stalled else ""))
    for line in surgery_lines(res.info["stages"]):
        print(line)
    for message in stalled:
        print(f"meshmei reconstruct: warning: {message}", file=sys.stderr)
    return 0


def _add_regularizers(sub) -> None:
    p = sub.add_parser("regularizers", help="build initial meshes and tabulate every regularizer")
    p.add_argument("--n-vertices", type=int, default=DEFAULT_N_VERTICES)
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=lambda a: tabulate_regularizers(a.n_vertices, a.seed) and 0)


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="the main job: 3D-MEI of a demo neuron, its pose and light tuning, plots")
    p.add_argument("--out", default="meshmei-demo", help="output directory (default: ./meshmei-demo)")
    p.add_argument("--neuron", type=int, default=None, help="default: the best-predicted demo neuron (0 with --model)")
    p.add_argument("--init", default="sheet", choices=INITIAL_KINDS)
    p.add_argument("--quick", action="store_true", help="tiny sizes, for a smoke test")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a non-empty --out: the demo's own files and its mei/ folder are replaced, other "
                        "files there are left alone")
    _add_model_options(p, "the demo model")
    p.set_defaults(func=lambda a: run_story(a.out, encoder=_cli_encoder(a), neuron=a.neuron, init=a.init,
                                            preset=QUICK if a.quick else FULL, overwrite=a.overwrite) and 0)


def _add_tune(sub) -> None:
    p = sub.add_parser("tune", help="sweep the pose or the light of a saved MEI run and plot the tuning")
    p.add_argument("what", choices=["pose", "light"])
    p.add_argument("--mei", required=True, help="a run directory written by 'meshmei mei' (with --diverse K: "
                                                "the folder of the K members, each swept; a 'meshmei population' "
                                                "folder: each finished neuron's run, on its own neuron)")
    p.add_argument("--out", default=None, help="output directory (default: MEI_DIR/tuning_<what>, in each member's "
                                               "or neuron's folder; with several runs OUT/member_<i> or "
                                               "OUT/neuron_<n>)")
    p.add_argument("--neurons", type=int, nargs="+", default=None, help="default: the run's neuron")
    p.add_argument("--elevation", default=None, help="lo:hi:n degrees (pose default -90:90:37, light 0:90:10)")
    p.add_argument("--azimuth", default=None, help="lo:hi:n degrees (pose default -90:90:37, light 0:350:36)")
    p.add_argument("--roll", default=None, help="lo:hi:n degrees: add an in-plane roll axis to a pose sweep")
    p.add_argument("--distance", type=float, default=None, help="light distance (default: the camera's)")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=_run_tune)


def _runs_to_sweep(root: Path) -> list[Path]:
    """The run folders ``meshmei tune --mei ROOT`` sweeps: ROOT; the members of ``meshmei mei --diverse K``;
    or every finished neuron of ``meshmei population`` (its root was refused as "not a complete MEI run")."""
    if (root / "diversity.json").is_file():  # meshmei mei --diverse K: sweep the members it lists
        try:
            k = len(json.loads((root / "diversity.json").read_text())["responses"])
        except (OSError, ValueError, KeyError, TypeError):
            raise MEIError(f"{root / 'diversity.json'} is damaged; run meshmei mei --diverse again") from None
        members = [root / f"member_{i}" for i in range(k)]
        if not members or not all(m.is_dir() for m in members):
            raise MEIError(f"{root} should hold member_0 to member_{k - 1} ({k} diverse runs); it does not")
        return members
    if (root / "population.json").is_file():  # meshmei population: its finished neurons, each on its own neuron
        members = sorted(p for p in (root / "neurons").glob("neuron_*") if p.is_dir())
        if not members:
            raise MEIError(f"{root} is a population folder without a finished neuron yet; run or resume it first")
        damaged = [m.name for m in members if not all((m / name).is_file() for name in RUN_FILES)]
        if damaged:  # before the first sweep, not after some
            raise MEIError(f"{len(damaged)} of the neuron folders in {root / 'neurons'} are not complete runs "
                           f"({', '.join(damaged[:10])}{' ...' if len(damaged) > 10 else ''}); remove them and "
                           "resume the population, then tune")
        return members
    return [root]


def _run_tune(args) -> int:
    # the command line gives ranges as text; everything else is run_tuning's
    ranges = {k: None if getattr(args, k) is None else parse_range(getattr(args, k))
              for k in ("elevation", "azimuth", "roll")}
    root = Path(args.mei)
    members = _runs_to_sweep(root)
    outs = [args.out if len(members) == 1 or args.out is None else Path(args.out) / run_dir.name
            for run_dir in members]
    for run_dir, out in zip(members, outs):  # every member's output checked before the first sweep
        out = Path(out) if out is not None else run_dir / f"tuning_{args.what}"
        for source in {root, run_dir}:
            check_apart(out, source, TuningError, "the run being swept")
        check_output(out, overwrite=args.overwrite, error=TuningError, how="--overwrite", kinds=SWEEP_KINDS)
    for run_dir, out in zip(members, outs):
        run_tuning(args.what, run_dir, out, neurons=args.neurons, distance=args.distance,
                   overwrite=args.overwrite, how="--overwrite", **ranges)
    return 0


def _add_population(sub) -> None:
    d = MEISettings()
    p = sub.add_parser("population", help="3D-MEIs and pixel MEIs of many neurons: batched, resumable, one folder each",
                       description="3D-MEIs of many neurons (each with every seed; the best kept), their pixel MEIs, "
                                   "one run folder per neuron under --out/neurons, population.csv and population.png. "
                                   "Rerun the same command to resume: finished neurons are skipped.")
    _add_encoder_options(p, "demo")
    p.add_argument("--neurons", required=True, help="ranges and lists, e.g. 0-99 or 0-9,20,30-32")
    p.add_argument("--seeds", type=int, nargs="+", default=list(d.seeds))
    p.add_argument("--steps", type=int, default=None, help=_steps_help(mesh_files=False))
    p.add_argument("--init", default="sheet", choices=INITIAL_KINDS)
    p.add_argument("--image-size", type=int, default=None,
                   help=f"render size in pixels (default {d.image_size}); with --model, the model's input size "
                        "(default: what its factory sets, else 100), which it is rendered at (a non-square one at its "
                        "longer side, then centre-cropped)")
    p.add_argument("--n-vertices", type=int, default=d.n_vertices)
    p.add_argument("--out", required=True, help="the population folder (created, or resumed)")
    p.add_argument("--batch-size", type=int, default=DEFAULT_BATCH_SIZE,
                   help=f"(neuron, seed) items optimised together (default {DEFAULT_BATCH_SIZE})")
    p.add_argument("--pixel-steps", type=int, default=DEFAULT_PIXEL_STEPS,
                   help=f"steps of each pixel MEI (0: none; default {DEFAULT_PIXEL_STEPS})")
    p.add_argument("--cluster", default=None, metavar="ray|ray://HOST:PORT",
                   help="run batches as Ray tasks (pip install 'meshmei[cluster]'); default: in this process")
    p.add_argument("--device", default="cpu",
                   help="cpu, cuda or cuda:N: where the meshes are rendered and optimised and the model runs "
                        "(with --cluster ray, each task asks Ray for a GPU for cuda)")
    _add_objective_options(p, d)
    p.add_argument("--figures", action="store_true", help="also write each run folder's figures")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=_run_population)


def _run_population(args) -> int:
    encoder = _cli_encoder(args)
    settings = MEISettings(steps=args.steps, seeds=tuple(args.seeds), image_size=_image_size(args, encoder),
                           n_vertices=args.n_vertices, **_objective_settings(args))
    try:
        rows = run_population(encoder, parse_neurons(args.neurons, encoder.n_neurons), args.out, init=args.init, settings=settings,
                              batch_size=args.batch_size, pixel_steps=args.pixel_steps, cluster=args.cluster,
                              device=args.device, figures=args.figures, progress=not args.quiet)
    except KeyboardInterrupt:
        print(f"meshmei population: interrupted; finished neurons are kept in {args.out}; run the same command "
              "to resume", file=sys.stderr)
        return 130
    ratios = [r["ratio"] for r in rows if r["ratio"] is not None]
    line = f"population: {len(rows)} neurons in {args.out}"
    if ratios:
        line += f"; 3D-MEI / pixel-MEI response {sum(ratios) / len(ratios):.3f} on average ({min(ratios):.3f}-{max(ratios):.3f})"
    clean = sum(1 for r in rows if r["self_intersections"] == 0)
    unflipped = sum(1 for r in rows if r["flipped_faces"] == 0)
    qualities = [r["min_quality"] for r in rows if r["min_quality"] is not None]
    watertight = sum(1 for r in rows if r["watertight"])
    manifold = sum(1 for r in rows if r["manifold"])
    health = (f"{clean} of {len(rows)} free of self-intersections, {unflipped} without flipped faces, "
              f"{watertight} watertight, {manifold} manifold")
    if qualities:
        health += f", min triangle quality {min(qualities):.3f} at worst"
    wrote = [name for name in ("population.csv", "population.png") if (Path(args.out) / name).is_file()]
    print(f"{line}; {health}; wrote {', '.join(wrote)}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="meshmei", description="3D maximally exciting inputs, their tuning, and mesh "
                                     "reconstruction: meshmei demo runs the main job on built-in data.")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_regularizers, _add_demo, _add_reconstruct, _add_tune, _add_mei, _add_population):
        add(sub)
    return parser


# options whose values may start with a minus sign and are not plain numbers ("-90:90:37", "-1,1"): argparse
# takes such a value for an option of its own unless it is joined to its option with '='
_SIGNED_VALUES = ("--elevation", "--azimuth", "--roll", "--pixel-range")


def _join_signed_values(argv: list) -> list:
    """``--elevation -90:90:37`` as ``--elevation=-90:90:37`` (the help's own format)."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] in _SIGNED_VALUES and i + 1 < len(argv) and re.match(r"-[\d.]", argv[i + 1]):
            out.append(f"{argv[i]}={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


@contextlib.contextmanager
def _warnings_as_lines(command: str):
    """meshmei's own warnings as one line each, as its errors (a rewritten population.json's warning came as
    Python's two lines: the file and line it was raised at, and that line's source); others as Python shows them."""
    package = str(Path(__file__).resolve().parent) + os.sep
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        if str(Path(filename).resolve()).startswith(package):
            print(f"meshmei {command}: warning: {' '.join(str(message).split())}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = shown


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(_join_signed_values(list(sys.argv[1:] if argv is None else argv)))
    for name in PATH_OPTIONS:  # a '~' the shell left (quoted, or after '=') named a folder called '~'
        value = getattr(args, name, None)
        if isinstance(value, str) and value.startswith("~"):
            setattr(args, name, os.path.expanduser(value))
    try:
        with terminate_as_interrupt(), _warnings_as_lines(args.command):  # SIGTERM: code 143 and no word before
            return int(args.func(args) or 0)
    except KeyboardInterrupt:  # Ctrl-C: one line, the shell's code for it; results are only ever written whole
        print(f"meshmei {args.command}: interrupted (runs and sweeps are written whole or not at all)", file=sys.stderr)
        return 130
    except (ValueError, OSError, FloatingPointError) as err:
        # bad input (every meshmei error is a ValueError), files that are missing or in the way, a
        # diverging optimisation: one clear line, no traceback
        print(f"meshmei {args.command}: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
