"""An evaluation keeps its finished episodes until its report is written, and a rerun goes on
from them (issue 54: a run stopped by a node that could not run a worker, at 10 of 12
episodes, dropped the 10 it had)."""

from __future__ import annotations

import numpy as np

from uwdock.dockcore.config import replace
from uwdock.rl.env.config import EnvConfig
from uwdock.rl.evaluate.episodes import (
    PARTIAL_EVAL_DIR,
    EpisodeStore,
    EpisodeTrace,
    episodes_key,
    run_episodes_parallel,
)


def _same_traces(a: list[EpisodeTrace], b: list[EpisodeTrace]) -> bool:
    import dataclasses

    for ta, tb in zip(a, b, strict=True):
        for f in dataclasses.fields(EpisodeTrace):
            va, vb = getattr(ta, f.name), getattr(tb, f.name)
            if len(va) != len(vb):
                return False
            if not all(np.array_equal(x, y) for x, y in zip(va, vb, strict=True)):
                return False
    return True


def test_an_evaluation_goes_on_from_the_episodes_it_kept(tmp_path) -> None:
    """Episodes 0 and 2 kept by an earlier run (as it saves them, one by one): the rerun runs
    only 1 and 3 and gives the rows and traces of an uninterrupted run; a store of another
    evaluation (another seed) is not used."""
    cfg = replace(EnvConfig(), episode_s=2.0)
    full = run_episodes_parallel("pid", cfg, 4, seed=3, workers=2)
    folder = tmp_path / PARTIAL_EVAL_DIR
    store = EpisodeStore(folder, episodes_key("pid", cfg, 3, True))
    assert not folder.exists()  # made with the first episode kept
    for k in (0, 2):
        store.save(k, full.episodes[k], full.traces[k])
    saved: list[int] = []
    store = EpisodeStore(folder, episodes_key("pid", cfg, 3, True))
    original = store.save

    def save(k: int, row: dict, trace: EpisodeTrace) -> None:
        saved.append(k)
        original(k, row, trace)

    store.save = save  # type: ignore[method-assign]
    ticks: list[int] = []
    resumed = run_episodes_parallel(
        "pid", cfg, 4, seed=3, workers=2, store=store, progress=lambda k, n: ticks.append(k)
    )
    assert sorted(saved) == [1, 3] and ticks == [2, 3, 4]
    assert resumed.episodes == full.episodes and resumed.summary == full.summary
    assert _same_traces(resumed.traces, full.traces)
    assert sorted(EpisodeStore(folder, episodes_key("pid", cfg, 3, True)).load(4)) == [0, 1, 2, 3]
    # another evaluation's store: its episodes are dropped, not mixed in
    assert EpisodeStore(folder, episodes_key("pid", cfg, 4, True)).load(4) == {}
    assert not list(folder.glob("ep*"))
