"""One way to map a function over items in worker processes (SynthGrasp generation,
feature preparation): spawned processes with one torch thread each (the tensors are
small; threads would only contend with the other workers), results in input order."""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

import torch
from tqdm import tqdm

T = TypeVar("T")
R = TypeVar("R")


def _init_worker() -> None:
    torch.set_num_threads(1)


def parallel_map(fn: Callable[[T], R], items: Iterable[T], workers: int, *, progress: bool = False,
                 desc: str = "", unit: str = "item") -> Iterator[R]:
    """``fn`` over ``items`` in ``workers`` processes (1: in this process, one torch thread
    while it runs), yielding results in input order. ``fn`` must be picklable."""
    items = list(items)
    with tqdm(total=len(items), disable=not progress, unit=unit, desc=desc) as bar:
        if workers <= 1:
            threads = torch.get_num_threads()
            _init_worker()
            try:
                for item in items:
                    yield fn(item)
                    bar.update()
            finally:
                torch.set_num_threads(threads)
        else:
            with mp.get_context("spawn").Pool(workers, initializer=_init_worker) as pool:
                for result in pool.imap(fn, items):
                    yield result
                    bar.update()
