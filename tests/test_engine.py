"""The engine in this process: keyed chunks, results by key, clear errors."""

import functools

import pytest

import thetahat.engine

from thetahat.cli import main
from thetahat.engine import EngineError, chunks, run_keyed, seed_task
from thetahat.errors import DimensionError, ThetahatError
from thetahat.simulation.batch import monte_carlo


def _square_chunk(items, *, calls):
    calls.append(list(items))
    return [(x, x * x) for x in items]


def test_chunks_are_fixed_by_size_not_by_where_they_run():
    assert chunks(list(range(7)), 3) == [[0, 1, 2], [3, 4, 5], [6]]
    assert len(chunks(list(range(100)))) == 15            # ceil(100 / CHUNK_TARGET) = 7 each
    with pytest.raises(DimensionError, match="chunk_size"):
        chunks([1], 0)


def test_run_keyed_returns_every_key_in_order():
    calls = []
    out = run_keyed(functools.partial(_square_chunk, calls=calls), [5, 3, 9, 1], [5, 3, 9, 1],
                    chunk_size=3, progress=False)
    assert list(out.items()) == [(5, 25), (3, 9), (9, 81), (1, 1)]
    assert calls == [[5, 3, 9], [1]]


def test_run_keyed_rejects_duplicate_keys_and_lost_results():
    with pytest.raises(DimensionError, match="unique"):
        run_keyed(lambda c: c, [1, 2], [1, 1])
    with pytest.raises(EngineError, match="missing"):
        run_keyed(lambda chunk: [], [1, 2], [1, 2], progress=False)


@pytest.fixture
def quick_timeout(monkeypatch):
    monkeypatch.setattr(thetahat.engine, "CONNECT_TIMEOUT_S", 1.0)


def test_bad_scheduler_is_a_clear_error(quick_timeout):
    pytest.importorskip("distributed")
    with pytest.raises(EngineError, match="scheduler must be"):
        run_keyed(lambda c: c, [1], [1], scheduler="localhost")
    with pytest.raises(EngineError, match="cannot reach") as info:
        run_keyed(lambda c: c, [1], [1], scheduler="tcp://127.0.0.1:9")
    assert isinstance(info.value, ThetahatError)


def test_monte_carlo_through_the_engine_matches_the_loop():
    fn = functools.partial(pow, 3)
    assert seed_task(fn)([1, 2]) == [(1, 3), (2, 9)]
    pytest.importorskip("distributed")
    with pytest.raises(EngineError):
        monte_carlo(fn, [0, 1], scheduler="nowhere")


def test_cli_bad_scheduler_exit_2(tmp_path, capsys, quick_timeout):
    pytest.importorskip("distributed")
    from pathlib import Path
    model = Path(__file__).resolve().parents[1] / "examples" / "prop3.toml"
    (tmp_path / "a.csv").write_text("t,u,y\n0,0,0\n0.1,0,0\n")
    code = main(["estimate", str(model), str(tmp_path), "--scheduler", "tcp://127.0.0.1:9"])
    assert code == 2
    assert "cannot reach the Dask scheduler" in capsys.readouterr().err
