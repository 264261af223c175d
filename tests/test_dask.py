"""SBC and sweeps through a two-worker dask.distributed LocalCluster on the loopback address.

The cluster runs its workers as threads (``processes=False``), so the tasks
share this process's compiled programs and the tests stay cheap.
"""

import json

import pytest
from dask.distributed import LocalCluster

from lmpromp_ppl.calibration.report import write_sbc_report
from lmpromp_ppl.calibration.runner import run_tasks, task_path
from lmpromp_ppl.calibration.sbc import SbcProblem, sbc_tasks
from lmpromp_ppl.calibration.sweep import sweep_table, sweep_tasks
from lmpromp_ppl.cli import main

DATASET = "synthetic:latent?L=8&D=1&J=4&V=1&seed=0"


@pytest.fixture(scope="module")
def cluster():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp://", host="127.0.0.1",
                      dashboard_address=":0", scheduler_kwargs={"dashboard": False}) as cluster:
        yield cluster


@pytest.fixture(scope="module")
def problem():
    return SbcProblem(num_demos=6, num_basis=4, num_steps=12, latent_dim=1, num_draws=29)


def test_sbc_resumes_after_interruption_and_reports_failures(cluster, problem, tmp_path):
    tasks = sbc_tasks(problem, ["cavi"], 6, seed=1, cavi_batch=3)
    tasks["broken"] = {"kind": "fail", "message": "deliberate"}
    first_ids = [next(iter(tasks))]
    # the "interrupted" run finished only the first task
    first = run_tasks({t: tasks[t] for t in first_ids}, tmp_path, scheduler=cluster.scheduler_address)
    assert first.computed == first_ids and not first.failed
    stamp = task_path(tmp_path, first_ids[0]).stat().st_mtime_ns
    full = run_tasks(tasks, tmp_path, scheduler=cluster.scheduler_address)
    assert full.reused == first_ids
    assert sorted(full.computed) == sorted(set(tasks) - set(first_ids))
    assert task_path(tmp_path, first_ids[0]).stat().st_mtime_ns == stamp
    assert full.failed == ["broken"]
    broken = json.loads(task_path(tmp_path, "broken").read_text())
    assert broken["status"] == "error" and "deliberate" in broken["error"] and "Traceback" in broken["traceback"]
    # the failure is retried, the finished tasks are not
    again = run_tasks(tasks, tmp_path, scheduler=cluster.scheduler_address)
    assert again.computed == ["broken"] and sorted(again.reused) == sorted(set(tasks) - {"broken"})
    indices = sorted(r["index"] for t in tasks if t != "broken" for r in full.records[t]["result"]["replicates"])
    assert indices == list(range(6))
    content = write_sbc_report(full.records, tmp_path, problems={"lmpromp": problem.to_dict()},
                               num_draws=problem.num_draws, seed=1)
    assert {r["quantity"] for r in content["rows"]} == {"alpha", "b", "gram_eig", "pred_mean", "pred_sd"}
    assert all(r["replicates"] == 6 for r in content["rows"])
    assert content["failed"] == {"broken": "RuntimeError: deliberate"}
    assert (tmp_path / "pit_ecdf_lmpromp_cavi.png").stat().st_size > 0
    assert "| lmpromp | cavi | alpha |" in (tmp_path / "uniformity.md").read_text()


def test_changed_spec_is_recomputed(cluster, tmp_path):
    tasks = {"t": {"kind": "fail", "message": "one"}}
    run_tasks(tasks, tmp_path, scheduler=cluster.scheduler_address)
    changed = run_tasks({"t": {"kind": "fail", "message": "two"}}, tmp_path, scheduler=cluster.scheduler_address)
    assert changed.computed == ["t"] and "two" in changed.records["t"]["error"]


def test_sweep_through_default_local_cluster(tmp_path):
    grid = {"beta": [50.0, 200.0]}
    tasks = sweep_tasks(DATASET, grid, num_basis=4, test_fraction=0.25, seed=0)
    run = run_tasks(tasks, tmp_path, num_workers=2, processes=False)
    assert not run.failed and len(run.computed) == 2
    rows = sweep_table(run.records, "lpd")
    assert [r["lpd"] for r in rows] == sorted((r["lpd"] for r in rows), reverse=True)
    assert {r["beta"] for r in rows} == {50.0, 200.0}
    assert all(r["num_train"] == 6 and r["num_test"] == 2 for r in (run.records[t]["result"] for t in tasks))


def test_cli_sweep_on_existing_scheduler_and_errors(cluster, tmp_path, capsys):
    out = tmp_path / "sweep"
    args = ["sweep", DATASET, "--out", str(out), "--grid", "beta=50,200", "--num-basis", "4",
            "--scheduler", cluster.scheduler_address, "--quiet"]
    assert main(args) == 0
    content = json.loads((out / "sweep.json").read_text())
    assert len(content["rows"]) == 2 and content["failed"] == {}
    assert main(args) == 2  # existing output without --resume or --force
    assert main(args + ["--resume"]) == 0
    assert main(["sweep", DATASET, "--out", str(tmp_path / "x"), "--grid", "nope=1"]) == 2
    assert main(["sbc", "--out", str(tmp_path / "y"), "--engines", "hmc"]) == 2
    assert main(["sbc", "--out", str(tmp_path / "z"), "--models", "promp", "--engines", "cavi"]) == 2
    err = capsys.readouterr().err
    assert "unknown grid parameter 'nope'" in err and "unknown engine 'hmc'" in err
