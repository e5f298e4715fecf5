"""The device of a 3D-MEI run is its model's: every tensor on the run's path is made on its inputs' device.

On any machine (no GPU needed): under ``torch.set_default_device("meta")`` a tensor that the code makes without
naming a device lands on "meta", which holds no values. Such a tensor fails as soon as it meets the run's data
(on the CPU) or a value is read from it. A run that finishes under it, with the same numbers as without it,
made every tensor from its inputs' device, or named the CPU on purpose (host-side work: libigl's exact
predicates, the compiled kernels, the random draws). Within :func:`meshmei.native.torch_reference` the run takes
the torch code that a CUDA run takes, since the compiled kernels accept CPU tensors only.

Where torch sees a GPU, the same runs on it agree with the CPU's to float rounding (skipped elsewhere).
"""

from __future__ import annotations

import contextlib
import re
from pathlib import Path

import pytest
import torch

from meshmei import native
from meshmei.encoders import GaborComplexCell, GaborSimpleCell, encoder_from_model
from meshmei.errors import MEIError
from meshmei.mei import MEISettings, optimize_mei, optimize_mei_batch
from meshmei.population import run_population

SMALL = dict(steps=4, seeds=(0, 1), image_size=20, n_vertices=50)
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")


def cells(image_size=20, dtype=torch.float32):
    """Three Gabor cells as one lab model's neurons (a ModelEncoder, with a device and a dtype of its own)."""
    units = torch.nn.ModuleList([GaborSimpleCell(), GaborComplexCell(orientation=0.7),
                                 GaborSimpleCell(orientation=1.2, phase=1.0)])

    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.units = units
            self.gain = torch.nn.Parameter(torch.ones(()))  # a parameter: the model has a device

        def forward(self, x):
            return self.gain * torch.cat([u(x, preprocessed=True) for u in self.units], 1)

    return encoder_from_model(Model().to(dtype), mean=0.5, std=0.2, image_size=image_size)


@contextlib.contextmanager
def stray_tensors_on_meta():
    """Tensors made without a device go to "meta" (where nothing can be computed) until the block ends."""
    torch.set_default_device("meta")
    try:
        yield
    finally:
        torch.set_default_device("cpu")


def _adam_names_its_step_device() -> bool:
    """Whether torch's Adam makes its step counter on the CPU by name. torch 2.13 does; 2.11 makes it on the
    default device, so under "meta" its own ``step.item()`` fails whatever meshmei does (seen on a GPU machine
    with torch 2.11, 2026-11-29: every optimising run failed there, in ``torch/optim/adam.py``)."""
    p = torch.zeros(1, requires_grad=True, device="cpu")
    p.grad = torch.ones(1, device="cpu")
    opt = torch.optim.Adam([p], foreach=False)
    try:
        with stray_tensors_on_meta():
            opt.step()
    except (RuntimeError, NotImplementedError):
        return False
    return opt.state[p]["step"].device.type == "cpu"


# The checks under "meta" need torch's own optimiser state off the default device (CI's torch 2.13 has that).
meta = pytest.mark.skipif(not _adam_names_its_step_device(),
                          reason="this torch's Adam makes its step counter on the default device")


def code(compiled: bool):
    return contextlib.nullcontext() if compiled else native.torch_reference()


RUNS = {  # name -> (init, overrides): the paths a population's items take, and the scene's optional parts
    "sheet": ("sheet", {}),
    "sphere": ("sphere", {}),
    "torus, unguarded": ("torus", {"valid_steps": False}),
    "light, pose and albedo": ("sheet", {"optimize_light": True, "optimize_pose": True, "albedo": True}),
    "robust": ("sphere", {"robust_pose": 10.0, "robust_light": 10.0, "robust_points": 2}),
}


def _same(a, b):
    assert a.seed == b.seed
    assert a.activation == b.activation
    assert torch.equal(a.V, b.V) and torch.equal(a.image, b.image)
    assert a.history == b.history


@meta
@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch code"])
@pytest.mark.parametrize("run", list(RUNS))
def test_a_3d_mei_makes_no_tensor_off_its_inputs_device(run, compiled):
    init, overrides = RUNS[run]
    enc = cells()
    with code(compiled):
        with stray_tensors_on_meta():
            probed = optimize_mei(enc, 1, init, **SMALL, **overrides)
        plain = optimize_mei(enc, 1, init, **SMALL, **overrides)
    _same(probed, plain)
    assert probed.V.device.type == "cpu" and probed.image.device.type == "cpu"


@meta
@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "torch code"])
def test_a_batch_makes_no_tensor_off_its_inputs_device(compiled):
    enc = cells()
    with code(compiled):
        with stray_tensors_on_meta():
            probed = optimize_mei_batch(enc, [0, 2], "sheet", **SMALL, batch_size=4)
        plain = optimize_mei_batch(enc, [0, 2], "sheet", **SMALL, batch_size=4)
    for n in (0, 2):
        _same(probed[n], plain[n])


@meta
def test_a_population_with_pixel_meis_makes_no_tensor_off_its_inputs_device(tmp_path):
    enc, s = cells(), MEISettings(**SMALL)
    with native.torch_reference():
        with stray_tensors_on_meta():
            probed = run_population(enc, [0, 1], tmp_path / "probed", settings=s, batch_size=4, pixel_steps=3,
                                    progress=False)
        plain = run_population(enc, [0, 1], tmp_path / "plain", settings=s, batch_size=4, pixel_steps=3,
                               progress=False)
    for a, b in zip(probed, plain, strict=True):
        for k in ("neuron", "seed", "mei_response", "pixel_mei_response", "self_intersections", "min_quality"):
            assert a[k] == b[k], k


@meta
def test_diverse_meis_and_the_random_baseline_make_no_tensor_off_their_inputs_device():
    from meshmei.mei import diverse_meis, random_mesh_responses

    enc = cells()
    kw = dict(steps=4, seeds=(0,), image_size=20, n_vertices=50)
    with native.torch_reference():
        with stray_tensors_on_meta():
            probed = (diverse_meis(enc, 1, k=2, **kw), random_mesh_responses(enc, 1, "sphere", n=6, batch=4,
                                                                             settings=MEISettings(**kw)))
        plain = (diverse_meis(enc, 1, k=2, **kw), random_mesh_responses(enc, 1, "sphere", n=6, batch=4,
                                                                        settings=MEISettings(**kw)))
    for a, b in zip(probed[0].results, plain[0].results):
        _same(a, b)
    assert torch.equal(probed[0].dissimilarity, plain[0].dissimilarity)
    assert torch.equal(probed[1], plain[1])


@meta
@pytest.mark.parametrize("method", ["rbf", "largesteps", "vertex"])
def test_a_reconstruction_makes_no_tensor_off_its_inputs_device(method):
    """Guarded (the default), coarse to fine; in the torch code, as on a GPU."""
    from meshmei.reconstruct import reconstruct
    from meshmei.shapes import initial_mesh, target_mesh

    target, src = target_mesh("bunny"), initial_mesh("sphere", n_vertices=300)
    kw = dict(steps=6, stages=(100, 300), n_samples=500, target_pool=2000, eval_samples=500)
    with native.torch_reference():
        with stray_tensors_on_meta():
            probed = reconstruct(src, target, method, **kw)
        plain = reconstruct(src, target, method, **kw)
    assert torch.equal(probed.V, plain.V) and torch.equal(probed.F, plain.F)
    assert probed.final.chamfer_l2 == plain.final.chamfer_l2


def test_tuning_sweeps_make_no_tensor_off_their_inputs_device():
    from meshmei.tuning import light_sweep, pose_sweep

    enc = cells()
    res = optimize_mei(enc, 0, "sheet", **SMALL)
    with native.torch_reference():
        with stray_tensors_on_meta():
            probed = (pose_sweep(res, enc, elevation=[-30, 0, 30], azimuth=[0, 45], batch_size=4),
                      light_sweep(res, enc, elevation=[10, 60], azimuth=[0, 90, 180], batch_size=4))
        plain = (pose_sweep(res, enc, elevation=[-30, 0, 30], azimuth=[0, 45], batch_size=4),
                 light_sweep(res, enc, elevation=[10, 60], azimuth=[0, 90, 180], batch_size=4))
    for a, b in zip(probed, plain):
        assert (a.responses == b.responses).all() and a.reference == b.reference


def test_no_code_moves_tensors_to_a_fixed_gpu():
    """Devices come from the inputs (the model's), or from a user's --device: no ``.cuda()`` anywhere, and
    "cuda" is named only where a user's device is read (the population's check and its Ray tasks)."""
    root = Path(__file__).resolve().parents[1] / "meshmei"
    offenders = []
    for path in sorted(root.rglob("*.py")):
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(r"\.cuda\(", line):
                offenders.append(f"{path.relative_to(root)}:{i}: {line.strip()}")
            elif re.search(r"device\s*=\s*[\"']cuda", line):
                offenders.append(f"{path.relative_to(root)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_a_cuda_device_this_machine_lacks_is_refused_before_the_folder(tmp_path):
    with pytest.raises(MEIError, match="this machine has no CUDA device"):
        run_population(cells(), [0], tmp_path / "p", device="cuda:1", settings=MEISettings(**SMALL),
                       progress=False)
    assert not (tmp_path / "p").exists()


# ---- on a GPU ----------------------------------------------------------------------------------------------

GPU_RUNS = ["sheet", "sphere", "light, pose and albedo"]


@cuda
@pytest.mark.parametrize("run", GPU_RUNS)
def test_a_3d_mei_on_the_gpu_agrees_with_the_cpu(run):
    """With a float64 model the run is float64 end to end, and the devices differ in summation order only."""
    init, overrides = RUNS[run]
    enc = cells(dtype=torch.float64)
    cpu = optimize_mei(enc, 1, init, **SMALL, **overrides, dtype="float64")
    gpu = optimize_mei(enc.to("cuda"), 1, init, **SMALL, **overrides, dtype="float64")
    assert gpu.V.device.type == "cpu"  # results come back on the CPU
    assert gpu.seed == cpu.seed
    assert gpu.activation == pytest.approx(cpu.activation, rel=1e-9)
    assert torch.allclose(gpu.V, cpu.V, rtol=0, atol=1e-10)
    assert torch.allclose(gpu.image, cpu.image, rtol=0, atol=1e-9)


@cuda
@pytest.mark.parametrize("run", GPU_RUNS)
def test_a_float32_model_on_the_gpu_agrees_with_the_cpu_to_its_rounding(run):
    """A lab's model is usually float32: it sees float32 images on either device, and its responses differ
    by float32 rounding, which the Gabor sums' cancellation magnifies (the sheet's response is 0.004 of sums
    of order one) and Adam's first, sign-like steps carry into the vertices."""
    init, overrides = RUNS[run]
    enc = cells()
    cpu = optimize_mei(enc, 1, init, **SMALL, **overrides, dtype="float64")
    gpu = optimize_mei(enc.to("cuda"), 1, init, **SMALL, **overrides, dtype="float64")
    assert gpu.seed == cpu.seed
    assert gpu.activation == pytest.approx(cpu.activation, rel=1e-3)
    assert torch.allclose(gpu.V, cpu.V, rtol=0, atol=1e-3)


@cuda
def test_a_population_on_the_gpu_agrees_with_the_cpu(tmp_path):
    s = MEISettings(**SMALL, dtype="float64")
    cpu = run_population(cells(dtype=torch.float64), [0, 1, 2], tmp_path / "cpu", settings=s, batch_size=4,
                         pixel_steps=3, progress=False)
    gpu = run_population(cells(dtype=torch.float64), [0, 1, 2], tmp_path / "gpu", settings=s, batch_size=4,
                         pixel_steps=3, device="cuda", progress=False)
    for a, b in zip(cpu, gpu, strict=True):
        assert (a["neuron"], a["seed"], a["self_intersections"]) == (b["neuron"], b["seed"], b["self_intersections"])
        assert b["mei_response"] == pytest.approx(a["mei_response"], rel=1e-9)
        # the pixel MEI runs in float32 (pixel_mei's default) whatever the settings' dtype: its start image is
        # a float32 draw, so a population's bound does not move with the dtype. 8.5e-8 between an H200 and a CPU.
        assert b["pixel_mei_response"] == pytest.approx(a["pixel_mei_response"], rel=1e-6)


@cuda
def test_the_cli_runs_a_3d_mei_on_the_gpu(tmp_path, capsys):
    """``meshmei mei --device cuda`` writes the run that ``--device cpu`` writes, to float32 rounding (the
    built-in cell computes in the run's float32)."""
    from meshmei.cli import main
    from meshmei.mei import load_run

    args = ["mei", "--encoder", "gabor-complex", "--steps", "4", "--seeds", "0", "--image-size", "24",
            "--n-vertices", "60", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "cpu")]) == 0
    assert main([*args, "--out", str(tmp_path / "gpu"), "--device", "cuda"]) == 0
    cpu, gpu = load_run(tmp_path / "cpu"), load_run(tmp_path / "gpu")
    assert gpu.V.device.type == "cpu" and gpu.seed == cpu.seed
    assert gpu.activation == pytest.approx(cpu.activation, rel=1e-3)
    assert torch.allclose(gpu.V, cpu.V, rtol=0, atol=1e-3)
