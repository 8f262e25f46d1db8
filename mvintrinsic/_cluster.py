"""A dask.distributed cluster for per-view work (optional): one task per view.

Private helpers of :func:`mvintrinsic.pipeline.decompose` and :class:`mvintrinsic.relight.Relighter`
(``client=``, ``docs/distributed.md``). dask is imported only when a client is given.
"""

from __future__ import annotations

import threading
import uuid
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from ._validation import describe


def _as_client(client: object) -> Any:
    """``client`` checked to be a ``dask.distributed.Client``; None passes.

    dask is imported here only, when a client is given: it stays an optional dependency.

    Raises
    ------
    TypeError
        If ``client`` is neither None nor a ``distributed.Client`` (the message names ``client``).
    """
    if client is None:
        return None
    try:
        from distributed import Client
    except ImportError:
        raise TypeError(f"client must be a dask.distributed.Client, got {describe(client)} "
                        "(dask.distributed is not installed: pip install 'dask[distributed]')") from None
    if not isinstance(client, Client):
        raise TypeError(f"client must be a dask.distributed.Client, got {describe(client)}")
    return client


class _Rebuilt:
    """A value that cannot be pickled (an Embree structure), carried as what builds it.

    ``get()`` returns ``build(*args)``, built once per process on first use: pickling keeps
    ``build`` and ``args`` only, so a copy shipped to a dask worker builds its own there, once
    (the worker keeps the unpickled object and hands the same one to each of its tasks).

    Parameters
    ----------
    build : callable
        Importable by name on the workers (a class or module-level function).
    *args
        Its picklable arguments.
    value : object, optional
        The value already built in this process (not pickled).
    """

    def __init__(self, build: Callable[..., Any], *args: Any, value: Any = None) -> None:
        self._build, self._args, self._value = build, args, value
        self._lock = threading.Lock()

    def get(self) -> Any:
        if self._value is None:
            with self._lock:  # two threads of one worker build it once
                if self._value is None:
                    self._value = self._build(*self._args)
        return self._value

    def __getstate__(self) -> dict[str, Any]:
        return {"_build": self._build, "_args": self._args}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self._build, self._args, self._value = state["_build"], state["_args"], None
        self._lock = threading.Lock()


class _ViewTasks:
    """Per-view tasks on a dask cluster, each view's inputs shipped once to one worker (its *home*).

    The views are dealt to the workers round robin over their threads, in scene order; a view's
    inputs are scattered to its home worker once and its tasks are asked to run there (other workers
    may take them when it is busy or gone), so that its later tasks find their inputs in place.
    Inputs every task reads are broadcast to every worker once.

    Parameters
    ----------
    client : distributed.Client
    stems : sequence of str
        The views, in scene order.

    Raises
    ------
    ValueError
        If the cluster has no worker (the message names ``client``).
    """

    def __init__(self, client: Any, stems: Sequence[str]) -> None:
        threads = client.nthreads()
        if not threads:
            raise ValueError("client: the dask cluster has no worker")
        slots = [w for k in range(max(threads.values())) for w in sorted(threads) if threads[w] > k]
        self.client = client
        self.home = {stem: slots[i % len(slots)] for i, stem in enumerate(stems)}

    def scatter(self, values: Mapping[str, Any]) -> dict[str, Any]:
        """``{stem: future}``: each view's value on its home worker (one scatter per worker)."""
        futures: dict[str, Any] = {}
        for worker in sorted(set(self.home[s] for s in values)):
            stems = [s for s in values if self.home[s] == worker]
            scattered = self.client.scatter([values[s] for s in stems], workers=[worker], hash=False)
            futures.update(zip(stems, scattered, strict=True))
        return {s: futures[s] for s in values}

    def broadcast(self, value: Any) -> Any:
        """A future of ``value`` held by every worker, shipped once to each."""
        return self.client.scatter(value, broadcast=True, hash=False)

    def submit(self, name: str, function: Callable[..., Any], args: Mapping[str, tuple], **shared: Any
               ) -> dict[str, Any]:
        """``{stem: future}`` of ``function(*args[stem], **shared)``, one task per view on its home worker.

        ``args`` and ``shared`` may hold futures (resolved on the worker); plain values in them
        travel with every task, so they must be small.
        """
        token = uuid.uuid4().hex[:12]
        return {stem: self.client.submit(function, *a, key=f"mvintrinsic-{name}-{stem}-{token}",
                                         workers=[self.home[stem]], allow_other_workers=True, **shared)
                for stem, a in args.items()}

    def gather(self, futures: Mapping[str, Any], *, desc: str = "views", progress: bool = False) -> dict[str, Any]:
        """``{stem: result}`` of the tasks, in the order of ``futures``; a task's error is raised here."""
        if progress:
            from distributed import as_completed
            from tqdm.auto import tqdm

            for _ in tqdm(as_completed(list(futures.values())), total=len(futures), desc=desc, unit="view"):
                pass
        return dict(zip(futures, self.client.gather(list(futures.values())), strict=True))


