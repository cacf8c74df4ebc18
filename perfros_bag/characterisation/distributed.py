"""Run independent tasks (one per recording, or per chunk range) in-process or on Dask.

``run_distributed(tasks, fn, scheduler=None, workers=None)`` runs ``fn`` on every task
in this process; dask is not even imported then. With ``scheduler="tcp://HOST:PORT"``
the tasks go to an existing dask.distributed cluster; with ``workers=N`` a
``LocalCluster`` of N single-threaded worker processes is started for the run and
closed afterwards. Dask is an optional extra (``perfros-bag[dask]``): without it those two
raise a :class:`~perfros_bag.errors.PerfrosError` saying how to install it.

Either way the caller gets one :class:`Outcome` per task, in task order: the value,
or the :class:`~perfros_bag.errors.PerfrosError` the task raised (a bad recording is
reported exactly as in the local path, the other tasks go on). A worker that dies is
replaced and its tasks are re-run by the scheduler (``distributed.scheduler
.allowed-failures`` times; a task given up on is submitted once more, since it may have
shared the worker with the culprit); a task whose worker keeps dying, or that raises an
unexpected exception after ``retries`` re-runs, becomes an error outcome naming the
task, never a lost result or a traceback. Functions and task items must be picklable
and importable on the workers (install perfros-bag on every worker of a real cluster).
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from perfros_bag.errors import InputError, PerfrosError

if TYPE_CHECKING:  # pragma: no cover
    from distributed import Client

T = TypeVar("T")
R = TypeVar("R")

#: Re-runs of a task that raised an unexpected (non-PerfrosError) exception.
DEFAULT_RETRIES = 2
#: How long to try to reach a ``--scheduler`` before giving up.
CONNECT_TIMEOUT = "10s"


@dataclass(frozen=True)
class Outcome(Generic[R]):
    """The result of one task: ``value`` on success, else ``error`` (one line for the user)."""

    label: str
    value: R | None = None
    error: PerfrosError | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


#: Called once per finished task, in completion order (e.g. to advance a progress bar).
ProgressCallback = Callable[[Outcome[Any]], None]


@dataclass(frozen=True)
class _Failure:
    """A PerfrosError flattened for pickling (InputError's __init__ does not round-trip)."""

    message: str
    exit_code: int


def _call(fn: Callable[[T], R], item: T) -> R | _Failure:
    """Run on the worker: user errors come back as values, so Dask does not retry them."""
    try:
        return fn(item)
    except PerfrosError as exc:
        return _Failure(str(exc), exc.exit_code)


def _error(message: str, exit_code: int = 2) -> PerfrosError:
    exc = PerfrosError(message)
    exc.exit_code = exit_code
    return exc


def _outcome(label: str, result: Any) -> Outcome[Any]:
    if isinstance(result, _Failure):
        return Outcome(label, error=_error(result.message, result.exit_code))
    return Outcome(label, value=result)


def run_distributed(
    tasks: Sequence[T],
    fn: Callable[[T], R],
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    progress: bool | ProgressCallback = False,
    label: Callable[[T], str] = str,
    retries: int = DEFAULT_RETRIES,
    description: str = "characterising",
) -> list[Outcome[R]]:
    """Run ``fn(task)`` for every task; one :class:`Outcome` per task, in task order.

    ``progress=True`` shows a rich bar on stderr advancing as tasks complete; a callable
    is called with each :class:`Outcome` as it completes instead.
    """
    if scheduler is not None and workers is not None:
        raise InputError(None, "both a Dask scheduler address and a number of local workers were given: use one")
    if workers is not None and workers < 1:
        raise InputError(None, f"the number of local workers must be at least 1, got {workers}")
    items = list(tasks)
    labels = [label(item) for item in items]
    if scheduler is None and workers is None:
        with _progress(progress, len(items), description) as advance:
            return _run_local(items, labels, fn, advance)
    with _client(scheduler, workers) as client, \
            _progress(progress, len(items), description) as advance:
        return _run_dask(client, items, labels, fn, advance, retries)


def _run_local(items: list[T], labels: list[str], fn: Callable[[T], R],
               advance: ProgressCallback) -> list[Outcome[R]]:
    outcomes: list[Outcome[R]] = []
    for item, name in zip(items, labels, strict=True):
        try:
            result: Outcome[R] = Outcome(name, value=fn(item))
        except PerfrosError as exc:  # in-process: the original exception, type and all
            result = Outcome(name, error=exc)
        advance(result)
        outcomes.append(result)
    return outcomes


def _run_dask(client: Client, items: list[T], labels: list[str], fn: Callable[[T], R],
              advance: ProgressCallback, retries: int) -> list[Outcome[R]]:
    from distributed import as_completed

    run = uuid.uuid4().hex[:12]  # keys unique per run: a cluster may still hold old keys
    index: dict[str, int] = {}
    futures = []

    def submit(i: int, attempt: int) -> Any:
        key = f"perfros-{run}-{i}-{attempt}-{_safe(labels[i])}"
        future = client.submit(_call, fn, items[i], key=key, retries=retries, pure=False)
        index[key] = i
        futures.append(future)
        return future

    outcomes: list[Outcome[R] | None] = [None] * len(items)
    resubmitted: set[int] = set()
    try:
        pending = as_completed([submit(i, 0) for i in range(len(items))])
        for future in pending:
            i = index[str(future.key)]
            try:
                # result() also waits when the result was lost with its worker after the
                # task finished (the scheduler recomputes it)
                result = _outcome(labels[i], future.result())
            except (KeyboardInterrupt, SystemExit):
                raise
            except BaseException as exc:  # the task's exception, KilledWorker, cancelled
                if type(exc).__name__ == "KilledWorker" and i not in resubmitted:
                    # Its worker died while it ran, maybe because of another task: once more.
                    resubmitted.add(i)
                    pending.add(submit(i, 1))
                    continue
                result = Outcome(labels[i], error=_task_error(labels[i], exc))
            outcomes[i] = result
            advance(result)
    finally:
        for future in futures:
            future.release()
    return [o for o in outcomes if o is not None]


def _task_error(name: str, exc: BaseException) -> PerfrosError:
    kind = type(exc).__name__
    if kind == "KilledWorker":
        return _error(f"{name}: the Dask worker running this task died repeatedly (out of memory? "
                      "see the worker logs); it was not characterised")
    return _error(f"{name}: failed on a Dask worker: {kind}: {exc}")


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "._-" else "_" for c in name)[-80:]


@contextmanager
def _client(scheduler: str | None, workers: int | None) -> Iterator[Client]:
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as exc:  # Dask is an optional extra
        missing = f" ({exc.name} is missing)" if exc.name else ""
        raise PerfrosError(f"running on Dask needs dask.distributed{missing}; "
                           "install it with: pip install 'perfros-bag[dask]'") from None

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError, ValueError) as exc:
            raise InputError(None, f"cannot connect to the Dask scheduler {scheduler}: {exc}") from None
        try:
            yield client
        finally:
            client.close()
        return
    # worker-saturation 1.0: a worker holds only the task it runs, so a worker that dies
    # takes no queued task down with it.
    with dask.config.set({"distributed.scheduler.worker-saturation": 1.0}):
        cluster = LocalCluster(n_workers=workers, processes=True, threads_per_worker=1,
                               dashboard_address=None, silence_logs=logging.ERROR)
    try:
        with Client(cluster) as client:
            yield client
    finally:
        cluster.close()


@contextmanager
def _progress(progress: bool | ProgressCallback, total: int,
              description: str) -> Iterator[ProgressCallback]:
    if callable(progress):
        yield progress
        return
    if not progress:
        yield lambda outcome: None
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    with Progress("[progress.description]{task.description}", BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=Console(stderr=True), transient=False) as bar:
        task = bar.add_task(description, total=total)

        def advance(outcome: Outcome[Any]) -> None:
            bar.advance(task)

        yield advance
