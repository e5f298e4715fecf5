"""A benchmark part that is interrupted loses none of its finished results (``FinishedRows``)."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest
import torch

from meshmei.benchmarks import _report
from meshmei.benchmarks._report import FinishedRows


@pytest.fixture
def docs(tmp_path, monkeypatch):
    monkeypatch.setenv("MESHMEI_DOCS", str(tmp_path))
    return tmp_path


def _never():
    raise AssertionError("a finished result was computed again")


def test_results_finished_before_an_interruption_are_taken_by_the_next_run(docs):
    first = FinishedRows("part")
    assert first.get("a", lambda: (1, "x", 2.5)) == [1, "x", 2.5]  # its JSON form, as a resumed run gets it
    assert first.get("b", lambda: {"k": (3,)}) == {"k": [3]}
    with pytest.raises(KeyboardInterrupt):
        first.get("c", lambda: (_ for _ in ()).throw(KeyboardInterrupt()))
    assert set(json.loads((docs / ".part.partial.json").read_text())["rows"]) == {"a", "b"}

    again = FinishedRows("part")
    assert again.get("a", _never) == [1, "x", 2.5] and again.get("b", _never) == {"k": [3]}
    assert again.get("c", lambda: 7) == 7
    assert again.resumed == 2 and "2 of its results" in again.note()
    again.close()
    assert not (docs / ".part.partial.json").exists()
    assert FinishedRows("part").get("a", lambda: "new") == "new"  # closed: nothing left to take


def test_results_of_other_source_or_with_restart_are_computed_again(docs, monkeypatch, capsys):
    FinishedRows("part").get("a", lambda: 1)
    assert FinishedRows("part", restart=True).get("a", lambda: 2) == 2
    assert "--restart" in capsys.readouterr().out
    FinishedRows("part").get("a", lambda: 1)  # restart dropped it; saved again
    monkeypatch.setattr(_report, "source_hash", lambda: "edited")
    assert FinishedRows("part").get("a", lambda: 3) == 3
    assert "source has changed" in capsys.readouterr().out


@pytest.mark.parametrize("text", ["", "{\"rows\": ", "[]", "{\"rows\": 3}"])
def test_a_damaged_file_is_a_run_to_redo(docs, text):
    (docs / ".part.partial.json").write_text(text)
    rows = FinishedRows("part")
    assert rows.get("a", lambda: 1) == 1 and rows.resumed == 0


def test_numpy_and_torch_scalars_keep_their_kind(docs):
    import numpy as np

    got = FinishedRows("part").get("a", lambda: [np.int64(3), np.float32(0.5), torch.tensor(2), np.bool_(True)])
    assert got == [3, 0.5, 2, True] and [type(x) for x in got] == [int, float, int, bool]


def test_a_file_without_its_start_time_is_still_taken(docs):
    from meshmei.benchmarks._report import source_hash

    (docs / ".part.partial.json").write_text(json.dumps({"source": source_hash(), "rows": {"a": 1}}))
    rows = FinishedRows("part")
    assert rows.get("a", _never) == 1 and "not recorded" in rows.note()


def test_without_a_name_nothing_is_written(docs):
    rows = FinishedRows(None)
    assert rows.get("a", lambda: 1) == 1 and rows.get("a", _never) == 1
    rows.close()
    assert list(docs.iterdir()) == []


def test_an_interrupted_thin_part_resumes_where_it_stopped(docs, monkeypatch):
    """The thin targets' part: the run interrupted in its third run takes the first two from the file, and
    large steps' budget is the saved default run's time; the table is the uninterrupted run's."""
    from meshmei.benchmarks import validity

    V, F = torch.rand(40, 3), torch.randint(0, 40, (60, 3))
    monkeypatch.setattr(validity, "target_surface", lambda name: name)
    monkeypatch.setattr(validity, "resolve_source", lambda init, n, dtype, target: (V, F, None))
    calls, stop_at = [], [0]  # the call that is interrupted (0: none)

    def fake_run(V, F, target, method, seed, **kw):
        calls.append((target, method, kw.get("time_budget")))
        if len(calls) == stop_at[0]:
            raise KeyboardInterrupt
        health = dict(self_intersections=0, inverted_faces=0, min_quality=0.25, watertight=True, nonmanifold_edges=0)
        final = SimpleNamespace(chamfer_l2=len(target) * (2e-6 if method == "largesteps" else 1e-6),
                                as_dict=lambda: health)
        wall = 10.0 + len(target) + (1.0 if kw else 0.0)  # the cup's default run: 13 s
        return SimpleNamespace(final=final, wall_time=wall, info={"stages": [{"refused": 1}]})

    monkeypatch.setattr(validity, "_default_run", fake_run)
    whole = validity.thin_outcomes(names=("cup", "fin"), n_vertices=40)
    calls.clear()
    stop_at[0] = 3
    with pytest.raises(KeyboardInterrupt):
        validity.thin_outcomes(names=("cup", "fin"), n_vertices=40, finished=FinishedRows("validity-thin"))
    assert len(calls) == 3
    calls.clear()
    stop_at[0] = 0
    resumed = FinishedRows("validity-thin")
    rows = validity.thin_outcomes(names=("cup", "fin"), n_vertices=40, finished=resumed)
    assert resumed.resumed == 2
    # large steps on the cup ran now, with the budget its default run took (13 s) before the interruption
    assert calls[0] == ("cup", "largesteps", 13.0) and [c[0] for c in calls[1:]] == ["fin"] * 3
    assert rows == whole and len(rows) == 6
