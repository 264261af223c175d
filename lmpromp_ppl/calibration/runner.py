"""Run calibration and sweep tasks through dask.distributed, one result file per task.

A task is a JSON-able specification ``{"kind": KIND, ...}`` under a task id;
:func:`execute` dispatches it to the function registered for its kind
(:data:`TASK_KINDS`) and never raises: a failing task returns a record with
its error and traceback.  :func:`run_tasks` submits the tasks to a
``dask.distributed`` cluster (a ``LocalCluster`` on 127.0.0.1 by default, or an
existing scheduler) and writes ``DIR/tasks/TASK_ID.json`` on the client as
each task finishes, so

* an interrupted run resumes: tasks whose file records success are read back,
  not recomputed;
* a failing task is recorded (status ``"error"``) without losing the others,
  and is retried by the next run.

The files are written by the client, so workers need no shared file system.
"""

from __future__ import annotations

import json
import os
import time
import traceback
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, NamedTuple

from lmpromp_ppl.errors import LmprompError
from lmpromp_ppl.results import to_json_value

__all__ = ["TASK_KINDS", "TaskRun", "execute", "task_path", "load_records", "run_tasks"]


def _sbc(spec: Mapping[str, Any]) -> dict:
    from lmpromp_ppl.calibration.sbc import sbc_task

    return sbc_task(spec)


def _sweep(spec: Mapping[str, Any]) -> dict:
    from lmpromp_ppl.calibration.sweep import sweep_task

    return sweep_task(spec)


def _vsbc_numpyro(spec: Mapping[str, Any]) -> dict:
    import jax

    from lmpromp_ppl.calibration.sbc import SbcProblem, design
    from lmpromp_ppl.calibration.vsbc import numpyro_vsbc

    problem = SbcProblem.from_dict(spec["problem"])
    out = numpyro_vsbc(problem.model, design(problem), problem.hyper(), jax.random.key(int(spec["seed"])),
                       **dict(spec.get("options") or {}))
    return {"model": problem.model, **out}


def _fail(spec: Mapping[str, Any]) -> dict:
    """A task that always fails (``{"kind": "fail", "message": ...}``), to exercise error handling."""
    raise RuntimeError(spec.get("message", "deliberate failure"))


TASK_KINDS: dict[str, Callable[[Mapping[str, Any]], dict]] = {
    "sbc": _sbc,
    "sweep": _sweep,
    "vsbc_numpyro": _vsbc_numpyro,
    "fail": _fail,
}


def execute(task_id: str, spec: Mapping[str, Any]) -> dict[str, Any]:
    """Run one task; returns ``{"task_id", "status": "ok"|"error", "result"|"error", "traceback", "seconds", "spec"}``."""
    start = time.perf_counter()
    record: dict[str, Any] = {"task_id": task_id, "spec": dict(spec)}
    try:
        kind = spec.get("kind")
        if kind not in TASK_KINDS:
            raise LmprompError(f"unknown task kind {kind!r}; choose from {sorted(TASK_KINDS)}")
        record["result"] = TASK_KINDS[kind](spec)
        record["status"] = "ok"
    except Exception as exc:  # a failing task is recorded, not raised
        record["status"] = "error"
        record["error"] = f"{type(exc).__name__}: {exc}"
        record["traceback"] = traceback.format_exc()
    record["seconds"] = time.perf_counter() - start
    return to_json_value(record)


def task_path(out_dir: Path, task_id: str) -> Path:
    """``out_dir/tasks/TASK_ID.json``."""
    if not task_id or "/" in task_id or task_id.startswith("."):
        raise LmprompError(f"invalid task id {task_id!r}")
    return Path(out_dir) / "tasks" / f"{task_id}.json"


def _write(path: Path, record: Mapping[str, Any]) -> None:
    """Write atomically (temporary file + rename), so an interruption never leaves half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=1, allow_nan=False))
    os.replace(tmp, path)


def load_records(out_dir: Path) -> dict[str, dict[str, Any]]:
    """Every readable task file of ``out_dir/tasks``: task id -> record."""
    records = {}
    for path in sorted((Path(out_dir) / "tasks").glob("*.json")):
        try:
            record = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            continue
        records[record.get("task_id", path.stem)] = record
    return records


class TaskRun(NamedTuple):
    """What :func:`run_tasks` did.

    Attributes
    ----------
    records : task id -> record (read back or computed), for every task
    computed : ids of the tasks run now
    reused : ids of the tasks read back from earlier runs
    failed : ids of the tasks whose record has status ``"error"``
    """

    records: dict[str, dict[str, Any]]
    computed: list[str]
    reused: list[str]
    failed: list[str]


def run_tasks(
    tasks: Mapping[str, Mapping[str, Any]],
    out_dir: Path,
    *,
    scheduler: str | None = None,
    num_workers: int = 2,
    threads_per_worker: int = 1,
    processes: bool = True,
    progress: Callable[[str, dict], None] | None = None,
) -> TaskRun:
    """Run the tasks not yet finished in ``out_dir/tasks`` on a dask cluster.

    Parameters
    ----------
    tasks : task id -> JSON-able specification with a ``"kind"`` of :data:`TASK_KINDS`
    out_dir : result directory; ``out_dir/tasks/TASK_ID.json`` is written as each task finishes
    scheduler : address of an existing ``dask.distributed`` scheduler; ``None``
        starts a ``LocalCluster`` on 127.0.0.1 (TCP, no dashboard) for this call
    num_workers, threads_per_worker, processes : the ``LocalCluster``
        (``processes=False``: threads in this process, cheap to start)
    progress : called as ``progress(task_id, record)`` after each task finishes

    Returns
    -------
    TaskRun
    """
    from dask.distributed import Client, LocalCluster, as_completed

    if isinstance(num_workers, bool) or int(num_workers) < 1:
        raise LmprompError(f"num_workers must be >= 1, got {num_workers!r}")
    out_dir = Path(out_dir)
    previous = load_records(out_dir)
    records, reused = {}, []
    for task_id in tasks:
        task_path(out_dir, task_id)  # validates the id
        old = previous.get(task_id)
        if old is not None and old.get("status") == "ok" and old.get("spec") == to_json_value(dict(tasks[task_id])):
            records[task_id] = old
            reused.append(task_id)
    pending = [task_id for task_id in tasks if task_id not in records]
    computed: list[str] = []
    if pending:
        cluster = None
        if scheduler is None:
            cluster = LocalCluster(n_workers=int(num_workers), threads_per_worker=int(threads_per_worker),
                                   processes=bool(processes), protocol="tcp://", host="127.0.0.1",
                                   dashboard_address=":0", scheduler_kwargs={"dashboard": False})
        try:
            with Client(cluster if cluster is not None else scheduler) as client:
                futures = {client.submit(execute, task_id, dict(tasks[task_id]), key=f"lmpromp-{task_id}",
                                         pure=False): task_id for task_id in pending}
                for future in as_completed(futures):
                    task_id = futures[future]
                    record = future.result()
                    _write(task_path(out_dir, task_id), record)
                    records[task_id] = record
                    computed.append(task_id)
                    if progress is not None:
                        progress(task_id, record)
        finally:
            if cluster is not None:
                cluster.close()
    failed = [task_id for task_id in tasks if records[task_id].get("status") != "ok"]
    return TaskRun({task_id: records[task_id] for task_id in tasks}, computed, reused, failed)
