"""Counting the forked workers that `forked.side_by_side` starts (the body fit's directions, the first
sewings), and losing them."""

from __future__ import annotations


def counted_forks(monkeypatch, lose: bool = False) -> tuple[list, list]:
    """Patch `forked.ForkedCall` with one that records each worker it starts (the first list) and, with
    ``lose``, kills each before its result and raises `forked.WorkerLost` (the second list): the driver must
    then compute that item itself."""
    from torch_diffavatar import forked

    started, lost = [], []

    class Counted(forked.ForkedCall):
        def __init__(self, fn):
            super().__init__(fn)
            started.append(self)

        def result(self):
            if not lose:
                return super().result()
            self._process.kill()
            lost.append(self)
            raise forked.WorkerLost("killed")

    monkeypatch.setattr(forked, "ForkedCall", Counted)
    return started, lost
