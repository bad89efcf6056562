"""Cohorts on Dask (BreastBiomechLib.cohort): task order, placement choices, and real local
clusters of two CPU worker processes: failures reported while the others finish, a worker killed
mid-task costing only that task, cancel and resume; the four-model study through the cluster equal
to the in-process run, with a worker killed mid-fit and a broken case beside the good ones."""

from __future__ import annotations

import json
import shutil

import pytest

import cohort_tasks
from BreastBiomechLib.cohort import CohortCancelled, Placement, Task, ordered, place, run_tasks

TWO_CPU_WORKERS = Placement(None, 2, (), "cpu")
HERE = Placement(None, 0, (), "cpu")


def test_tasks_run_after_what_they_need_and_cycles_are_refused():
    first, second, third = (Task("a", cohort_tasks.total), Task("b", cohort_tasks.total, needs=("c",)),
                            Task("c", cohort_tasks.total, needs=("a", "done-earlier")))
    assert [t.key for t in ordered([second, third, first])] == ["a", "c", "b"]
    with pytest.raises(ValueError, match="cycle: b -> c -> b"):
        ordered([Task("b", cohort_tasks.total, needs=("c",)), Task("c", cohort_tasks.total, needs=("b",))])
    with pytest.raises(ValueError, match=r"unique; repeated: \['a'\]"):
        ordered([first, first])


def test_placement_choices(monkeypatch):
    monkeypatch.delenv("BREASTBIOMECH_SCHEDULER", raising=False)
    assert place(workers=0) == Placement(None, 0, (), None)
    assert place(workers=3, device="cpu") == Placement(None, 3, (), "cpu")
    assert place(device="cpu").workers >= 1  # one per core
    assert place("tcp://10.0.0.1:8786").describe() == "the Dask cluster at tcp://10.0.0.1:8786"
    assert Placement(None, 1, (0, 1), "cuda").describe() == "a local Dask cluster of 1 worker on GPU 0"
    assert Placement(None, 4, (0, 1), "cuda").describe() == "a local Dask cluster of 4 workers on GPUs 0, 1"
    monkeypatch.setenv("BREASTBIOMECH_SCHEDULER", "tcp://10.0.0.2:8786")
    assert place(device="cuda").scheduler == "tcp://10.0.0.2:8786"  # the cluster's workers own the GPUs
    with pytest.raises(ValueError, match="--workers sizes a local cluster"):
        place(workers=2)
    monkeypatch.delenv("BREASTBIOMECH_SCHEDULER")
    with pytest.raises(ValueError, match="0 .this process. or more"):
        place(workers=-1)
    with pytest.raises(ValueError, match="tcp://HOST:PORT"):
        place("nowhere")
    with pytest.raises(ValueError, match="cpu, cuda or cuda:K"):
        place(device="gpu")
    import warp as wp

    wp.init()
    if wp.get_cuda_device_count() == 0:
        with pytest.raises(ValueError, match="no CUDA device; use --device cpu"):
            place(device="cuda")
        assert place().gpus == () and place().task_device == "cpu"


def _square_tasks(out):
    return [Task(f"square/{x}", cohort_tasks.square, {"x": x, "out": str(out)}) for x in range(5)] + [
        Task("total", cohort_tasks.total, {"out": str(out)}, needs=tuple(f"square/{x}" for x in range(5) if x != 3)),
        Task("after-three", cohort_tasks.total, {"out": str(out)}, needs=("square/3",))]


@pytest.mark.parametrize("placement", [HERE, TWO_CPU_WORKERS], ids=["in-process", "two-workers"])
def test_a_failing_task_is_reported_and_the_others_finish(placement, tmp_path):
    seen, lines = [], []
    outcomes = run_tasks(_square_tasks(tmp_path), placement, progress=lambda s: lines.append(s.line()),
                         on_outcome=seen.append, dashboard=None)
    by_key = {o.key: o for o in outcomes}
    assert [o.key for o in seen] == [o.key for o in outcomes] and len(outcomes) == 7
    assert by_key["square/3"].error == "ValueError: three is refused" and "cohort_tasks.py" in by_key["square/3"].traceback
    assert by_key["after-three"].error == "not run: it needs square/3, which failed"
    assert by_key["total"].ok and by_key["total"].result == {"total": 0 + 1 + 4 + 16}
    assert all(by_key[f"square/{x}"].result["device"] == "cpu" for x in (0, 1, 2, 4))
    ran = [by_key[f"square/{x}"] for x in (0, 1, 2, 4)]  # where and when each ran (bench cohort's timeline)
    workers = {"here"} if placement is HERE else {"breastbiomech-0", "breastbiomech-1"}
    assert {o.worker for o in ran} <= workers and all(o.seconds >= 0.9 and o.started_at > 1e9 for o in ran)
    assert lines[-1].startswith("[########################] 7/7 tasks, 2 failed")
    assert any("square/1: " in line for line in lines)  # the tasks' own progress lines reached the client


def test_a_cluster_starts_the_ready_tasks_of_higher_priority_first(tmp_path):
    """On one worker, four tasks made ready together by a first one start in priority order,
    not in the order they were submitted."""
    gate = Task("square/0", cohort_tasks.square, {"x": 0, "out": str(tmp_path)})
    tasks = [gate] + [Task(f"square/{x}", cohort_tasks.square, {"x": x, "out": str(tmp_path)}, needs=("square/0",),
                           priority=priority) for x, priority in ((1, 0), (2, 30), (4, 10), (5, 20))]
    outcomes = run_tasks(tasks, Placement(None, 1, (), "cpu"), dashboard=None)
    assert [o.key for o in sorted(outcomes, key=lambda o: o.started_at)] == [
        "square/0", "square/2", "square/5", "square/4", "square/1"]


def test_a_tasks_dependents_go_to_whichever_worker_is_free(tmp_path):
    """Eight fits of one case and one of another on two workers: the first case's fits spread
    over both workers once its mesh is made, instead of queueing on the worker that made it (as
    they did when Dask was given the dependencies: one GPU then idled while the other worked)."""
    tasks = [Task("mesh/one", cohort_tasks.pause, {"seconds": 1.0}, priority=10),
             Task("mesh/two", cohort_tasks.pause, {"seconds": 0.2}, priority=10),
             Task("fit/two/0", cohort_tasks.pause, {"seconds": 1.0}, needs=("mesh/two",))]
    tasks += [Task(f"fit/one/{k}", cohort_tasks.pause, {"seconds": 1.0}, needs=("mesh/one",)) for k in range(8)]
    outcomes = run_tasks(tasks, TWO_CPU_WORKERS, dashboard=None)
    assert all(o.ok for o in outcomes)
    fits = {w: sum(o.key.startswith("fit/one/") for o in outcomes if o.worker == w)
            for w in ("breastbiomech-0", "breastbiomech-1")}
    # 4 each when shared evenly (5 and 3 if one goes the other way); 6 and 2 with Dask's dependencies
    # (Dask's work stealing moved two of them; 5 and 3 at times)
    assert min(fits.values()) >= 3, fits


def test_local_workers_share_the_cores_out_for_itk_and_run_without_dasks_sampling_profiler():
    """Each of two local workers runs ITK's filters on half the cores (not one thread per core
    each), and without Dask's profiler, whose hold on a task's frames frees the task's warp
    objects in another thread (cohort/cluster.py, WORKER_CONFIG)."""
    import os

    import dask

    tasks = [Task(f"env/{k}", cohort_tasks.environment, {"name": "ITK_GLOBAL_DEFAULT_NUMBER_OF_THREADS"})
             for k in range(2)] + [Task(f"profile/{k}", cohort_tasks.dask_setting,
                                        {"key": "distributed.worker.profile.enabled"}) for k in range(2)]
    outcomes = {o.key: o for o in run_tasks(tasks, TWO_CPU_WORKERS, dashboard=None)}
    assert {outcomes[f"env/{k}"].result["value"] for k in range(2)} == {
        str(max(1, len(os.sched_getaffinity(0)) // 2))}
    assert dask.config.get("distributed.worker.profile.enabled") is True  # Dask's default, here
    assert [outcomes[f"profile/{k}"].result["value"] for k in range(2)] == [False, False]


def test_a_studys_meshes_go_first_then_its_longest_fits():
    """The study's task priorities: every fitting mesh before any fit (each lets four fits start),
    then fits by budget, heterogeneous before homogeneous at equal budgets."""
    from BreastBiomechLib.optimisation.study import StudySettings, study_tasks

    settings = StudySettings(models=("iso-homo", "iso-hetero", "aniso-homo"),
                             budgets={"iso-homo": 40, "iso-hetero": 20, "aniso-homo": 20}, edge_mm=8.0)
    tasks = study_tasks(["/data/case1", "/data/case2"], "/tmp/never-written", settings)
    by_priority = [t.key for t in sorted(tasks, key=lambda t: -t.priority)]
    assert by_priority[:2] == ["mesh/case1", "mesh/case2"]
    assert [k.split("/")[2] for k in by_priority[2:]] == ["iso-homo-cmaes"] * 2 + ["iso-hetero-cmaes"] * 2 + [
        "aniso-homo-cmaes"] * 2


def test_bench_cohort_timeline_per_worker():
    """`bench cohort`'s per-worker figures: tasks, busy seconds, first start and last end (s after
    the run started)."""
    from BreastBiomechLib.cli.bench import _worker_timeline
    from BreastBiomechLib.cohort import TaskOutcome

    outcomes = [TaskOutcome("a", "a", True, seconds=10.0, worker="w0", started_at=1005.0),
                TaskOutcome("b", "b", True, seconds=4.0, worker="w1", started_at=1006.0),
                TaskOutcome("c", "c", False, seconds=2.5, worker="w0", started_at=1015.0)]
    assert _worker_timeline(outcomes, 1000.0) == {
        "w0": {"tasks": 2, "busy_seconds": 12.5, "first_start_s": 5.0, "last_end_s": 17.5},
        "w1": {"tasks": 1, "busy_seconds": 4.0, "first_start_s": 6.0, "last_end_s": 10.0}}


def test_a_worker_lost_mid_task_costs_only_that_task(tmp_path):
    tasks = _square_tasks(tmp_path)[:3] + [Task("dies-once", cohort_tasks.dies_once, {"out": str(tmp_path)})]
    outcomes = {o.key: o for o in run_tasks(tasks, TWO_CPU_WORKERS, dashboard=None)}
    assert all(o.ok for o in outcomes.values())
    assert outcomes["dies-once"].result["pid"] != outcomes["dies-once"].result["first"]  # ran again elsewhere
    assert sorted(p.name for p in tmp_path.glob("[0-9].json")) == ["0.json", "1.json", "2.json"]


@pytest.mark.parametrize("placement", [HERE, TWO_CPU_WORKERS], ids=["in-process", "two-workers"])
def test_a_task_whose_cuda_graph_capture_broke_runs_once_more_and_its_log_keeps_the_first_error(placement,
                                                                                                tmp_path):
    from BreastBiomechLib.optimisation.study import log_failure

    tasks = [Task("square/0", cohort_tasks.square, {"x": 0, "out": str(tmp_path)}),
             Task("capture-once", cohort_tasks.capture_fails_once, {"out": str(tmp_path)}),
             Task("capture-always", cohort_tasks.capture_always_fails), Task("three", cohort_tasks.square,
                                                                             {"x": 3, "out": str(tmp_path)})]
    log = tmp_path / "failures.log"
    outcomes = {o.key: o for o in run_tasks(tasks, placement, dashboard=None, on_outcome=lambda o: log_failure(log, o))}
    once, always, three = outcomes["capture-once"], outcomes["capture-always"], outcomes["three"]
    assert once.ok and len(once.earlier_errors) == 1 and "error 901" in once.earlier_errors[0]
    assert not always.ok and "error 900" in always.error and len(always.earlier_errors) == 1  # one retry only
    assert not three.ok and three.earlier_errors == ()  # any other error: not run again
    assert outcomes["square/0"].ok and outcomes["square/0"].earlier_errors == ()
    text = log.read_text()
    assert text.count("capture-once: try 1 of 2, run again after: RuntimeError") == 1
    assert "capture-always: RuntimeError" in text and "square/0" not in text


@pytest.mark.parametrize("placement", [HERE, TWO_CPU_WORKERS], ids=["in-process", "two-workers"])
def test_cancel_keeps_what_finished_and_a_rerun_resumes(placement, tmp_path):
    tasks = [t for t in _square_tasks(tmp_path) if t.key != "square/3" and "three" not in t.key]
    with pytest.raises(CohortCancelled, match="rerun to resume"):
        run_tasks(tasks, placement, progress=lambda s: s.finished < 1, dashboard=None)
    finished = {p.name for p in tmp_path.glob("[0-9].json")}  # (tasks already on a worker may finish too)
    assert finished
    # the rerun runs only what is missing (as the study and the suite build their task lists)
    rest = [t for t in tasks if t.key == "total" or f"{t.kwargs['x']}.json" not in finished]
    outcomes = {o.key: o for o in run_tasks(rest, placement, dashboard=None)}
    assert outcomes["total"].result == {"total": 0 + 1 + 4 + 16}


@pytest.mark.slow
def test_the_study_on_two_workers_equals_the_in_process_one(compressed_case_dir, tmp_path, capsys):
    """The study of 2 models on a local cluster of two CPU workers, one of them killed mid-run, for
    two copies of the test case and a broken third: each copy's rows equal the in-process run's of
    the case; the broken case fails alone, reported with its error; a rerun has only it left."""
    import psutil

    from BreastBiomechLib.cli import main
    from BreastBiomechLib.optimisation.study import StudySettings, read_study, run_study

    cases = []
    for name in ("caseA", "caseB"):
        shutil.copytree(compressed_case_dir, tmp_path / name)
        cases.append(tmp_path / name)
    broken = tmp_path / "broken"
    shutil.copytree(compressed_case_dir, broken)
    (broken / "labels.nrrd").unlink()
    settings = StudySettings(models=("iso-homo", "aniso-homo"), budgets={"iso-homo": 1, "aniso-homo": 1},
                             edge_mm=12.0, tolerance_mm=0.05)
    serial = run_study(cases[:1], tmp_path / "serial", settings, placement=HERE)
    assert not serial.failed and len(serial.rows) == 2

    killed = []

    def kill_a_worker_mid_fit(state):
        if not killed and any("solves" in line for line in state.running.values()):  # a fit past its first batch
            workers = [p for p in psutil.Process().children(recursive=True) if "spawn_main" in " ".join(p.cmdline())]
            if workers:
                workers[-1].kill()
                killed.append(workers[-1].pid)

    run = run_study(cases + [broken], tmp_path / "dask", settings, placement=TWO_CPU_WORKERS,
                    progress=kill_a_worker_mid_fit)
    assert killed, "no worker was killed: the test did not test the loss of one"
    assert sorted(o.key for o in run.failed) == ["fit/broken/aniso-homo-cmaes", "fit/broken/iso-homo-cmaes",
                                                 "mesh/broken"]
    assert "labels.nrrd" in next(o.error for o in run.failed if o.key == "mesh/broken")
    assert "mesh/broken" in (tmp_path / "dask" / "failures.log").read_text()

    def comparable(rows, case):
        return sorted((r.model, r.evaluations, r.nmi, r.objective, json.dumps(r.materials, sort_keys=True), r.stopped)
                      for r in rows if r.case == case)

    for case in ("caseA", "caseB"):
        assert comparable(run.rows, case) == comparable(serial.rows, "caseA")
    assert len(read_study(tmp_path / "dask")) == 4

    # the command: a rerun has nothing left but the broken case, which fails again (exit 1, one line each)
    assert main(["study", *map(str, cases + [broken]), "--out", str(tmp_path / "dask"), "--models", "iso-homo",
                 "aniso-homo", "--budget", "iso-homo=1", "aniso-homo=1", "--edge-mm", "12", "--tolerance-mm", "0.05",
                 "--device", "cpu", "--workers", "0", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "FAILED broken fitting mesh: FileNotFoundError" in err and "3 tasks failed" in err


def test_reruns_build_only_the_missing_tasks(tmp_path):
    """The suite and the Table 1 cases: finished results are not tasks again; a case needs its anatomy
    only while the anatomy is not prepared."""
    from BreastBiomechLib.discrepancy.suite import SuiteSettings, suite_cases
    from BreastBiomechLib.discrepancy.suite.runner import suite_tasks
    from BreastBiomechLib.phantom.table1_cases import table1_tasks

    cases = suite_cases([1, 2], ["null", "friction"])
    (tmp_path / cases[0].name).mkdir()
    (tmp_path / cases[0].name / "result.json").write_text("{}")
    (tmp_path / "anatomy2").mkdir()
    (tmp_path / "anatomy2" / "prepared.json").write_text("{}")
    tasks = suite_tasks(tmp_path, cases, SuiteSettings())
    assert [t.key for t in tasks] == ["anatomy/1"] + [f"case/{c.name}" for c in cases[1:]]
    assert [t.needs for t in tasks[1:]] == [(f"anatomy/{c.anatomy}",) for c in cases[1:]]
    assert [t.key for t in ordered(tasks)][0] == "anatomy/1"
    assert tasks[0].priority > max(t.priority for t in tasks[1:])  # on a cluster, anatomies first

    (tmp_path / "t1" / "case2" / "compressed").mkdir(parents=True)
    (tmp_path / "t1" / "case2" / "compressed" / "truth.json").write_text("{}")
    (tmp_path / "t1" / "case3").mkdir()  # a folder without its truth is not a finished case
    assert [t.key for t in table1_tasks(tmp_path / "t1", [1, 2, 3])] == ["table1/case1", "table1/case3"]
    with pytest.raises(ValueError, match="Table 1 has cases"):
        table1_tasks(tmp_path / "t1", [6])


def test_bench_cohort_names_how_far_two_studies_fits_are():
    """`bench cohort`'s comparison of a run with the first: the largest NMI, objective and
    relative material differences, the fits whose solve counts differ, the fits only one has."""
    from BreastBiomechLib.cli.bench import _study_differences
    from BreastBiomechLib.optimisation.study import StudyFit

    def fit(case, nmi, E, evaluations=12):
        return StudyFit(case=case, model="iso-homo", optimiser="cmaes", nmi=nmi, objective=-nmi,
                        evaluations=evaluations, failed=0, seconds=1.0, stopped="budget", landmark_errors=None,
                        materials={"breast": {"E": E, "nu": 0.45, "eta": 0.0}}, truth={}, in_family=True)

    first = [fit("case1", 1.20, 1000.0), fit("case2", 1.10, 2000.0)]
    assert _study_differences(first, first) == {"nmi": 0.0, "objective": 0.0, "materials_relative": 0.0,
                                                "fits_with_other_solve_counts": 0, "fits_in_one_only": []}
    other = [fit("case1", 1.2001, 1010.0, evaluations=13), fit("case3", 1.0, 500.0)]
    differences = _study_differences(other, first)
    assert differences["nmi"] == pytest.approx(1e-4) and differences["objective"] == pytest.approx(1e-4)
    assert differences["materials_relative"] == pytest.approx(10 / 1010)
    assert differences["fits_with_other_solve_counts"] == 1
    assert differences["fits_in_one_only"] == ["case2/iso-homo/cmaes", "case3/iso-homo/cmaes"]


def test_gpu_usage_summarises_each_gpus_samples(tmp_path, monkeypatch):
    """nvidia-smi's CSV samples -> per-GPU mean and peak utilisation, busy share and peak memory,
    unreadable lines skipped; where the machine has no nvidia-smi nothing is sampled (None)."""
    from BreastBiomechLib.cli.gpu_usage import GpuUsage, summarise_samples

    text = "0, 100, 900\n1, 0, 500\n0, 50, 1200\n1, [N/A], 510\n1, 30, 700\n0, 7"
    assert summarise_samples(text) == {
        "0": {"samples": 2, "mean_utilisation_percent": 75.0, "peak_utilisation_percent": 100.0,
              "busy_fraction": 1.0, "peak_memory_mib": 1200.0},
        "1": {"samples": 2, "mean_utilisation_percent": 15.0, "peak_utilisation_percent": 30.0,
              "busy_fraction": 0.5, "peak_memory_mib": 700.0}}
    monkeypatch.setenv("PATH", str(tmp_path))
    with GpuUsage() as usage:
        pass
    assert usage.summary is None
