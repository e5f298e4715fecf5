"""The Python examples in docs/ run as written, with only their sizes cut down.

Each page's blocks run in order in one namespace (later blocks use names from earlier ones, as a reader
would), in an empty folder. The examples name `model`, the user's own network: a small one stands in.
Every cut-down substitution must find its text, so an edited example cannot slip past at full size.
"""

import re
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]

# page -> (pattern, replacement) pairs; each must match at least once
SHORTER = {
    "encoders.md": [(r'init="sheet"\)', 'init="sheet", steps=3, seeds=(0,))')],
    "mei.md": [(r"steps=300", "steps=3"), (r"steps=200", "steps=3"), (r"progress=True", "progress=False")],
    "population.md": [(r"range\(100\)", "range(2)"), (r"steps=300", "steps=3")],
    "reconstruction.md": [(r"time_budget=30", "time_budget=1"), (r"eval_times=\(10, 20\)", "eval_times=(0.5,)"),
                          (r"progress=True", "progress=False"),
                          (r'stages="auto"\)', 'stages="auto", steps=12, n_samples=500, target_pool=2000, '
                                               'eval_samples=1000)')],
    "rendering.md": [],
    "shapes.md": [],
    "tuning.md": [],
}


class _UserModel(torch.nn.Module):
    """A stand-in for a lab's network: 100 x 100 RGB images in, 120 positive responses out."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.conv = torch.nn.Conv2d(3, 4, 5, stride=4)
        self.readout = torch.nn.Linear(4 * 24 * 24, 120)

    def forward(self, x, data_key=None):
        return torch.nn.functional.elu(self.readout(self.conv(x).flatten(1))) + 1


def _blocks(page):
    return re.findall(r"```python\n(.*?)```", (ROOT / "docs" / page).read_text(), re.S)


def _examples(page):
    """The page's blocks with SHORTER applied; fails if a pattern no longer occurs."""
    blocks = _blocks(page)
    for pattern, _ in SHORTER[page]:
        assert any(re.search(pattern, code) for code in blocks), f"docs/{page} lost {pattern!r}: update SHORTER"
    for pattern, replacement in SHORTER[page]:
        blocks = [re.sub(pattern, replacement, code) for code in blocks]
    return blocks


def test_every_page_with_examples_is_listed():
    pages = {p.name for p in (ROOT / "docs").glob("*.md") if _blocks(p.name)}
    assert pages == set(SHORTER)


def _prepare_tuning_run():
    # tuning.md starts from a saved run of neuron 3 whose encoder can be rebuilt
    from meshmei.encoders import make_encoder
    from meshmei.mei import optimize_mei, save_run

    save_run(optimize_mei(make_encoder("demo"), neuron=3, init="sheet", steps=3, seeds=(0,)), "runs/n3")


@pytest.mark.parametrize("page", sorted(SHORTER))
def test_examples_run(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    if page == "tuning.md":
        _prepare_tuning_run()
    namespace = {"model": _UserModel()}
    for code in _examples(page):
        exec(compile(code, f"docs/{page}", "exec"), namespace)
    if page == "mei.md":
        assert (tmp_path / "runs" / "complex_sheet" / "summary.json").is_file()
        assert torch.equal(namespace["again"].V, namespace["res"].V)
    if page == "tuning.md":
        assert (tmp_path / "runs" / "n3" / "pose" / "sweep.npz").is_file()
