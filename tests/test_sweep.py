"""The sweep runner (experiments/sweep.py): processes, skipping finished jobs, failures, Ray."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
import sweep  # noqa: E402


def square_job(job: sweep.Job) -> dict:
  """A cheap job: the seed squared times a parameter, plus who ran it (to see the parallelism)."""
  if job.variant == "broken":
    raise ValueError("this variant always fails")
  return {"value": job.seed ** 2 * job.params.get("scale", 1), "pid": os.getpid()}


def jax_job(job: sweep.Job) -> dict:
  """A job that runs XLA, as a job training in process does."""
  import jax
  import jax.numpy as jnp
  return {"value": float(jax.jit(lambda x: jnp.sum(x * x))(jnp.arange(job.seed + 1.0)))}


def make_jobs(root: Path, variants=("a", "b"), seeds=(0, 1, 2)) -> list[sweep.Job]:
  return [sweep.Job(scene="s", variant=v, seed=s, result=str(root / f"{v}_{s}.json"),
                    params={"scale": 3})
          for v in variants for s in seeds]


def check_records(jobs, records, skipped: bool):
  assert [r["name"] for r in records] == [j.name for j in jobs]
  for job, rec in zip(jobs, records):
    assert rec["skipped"] is skipped
    assert rec["seed"] == job.seed
    assert rec["result"]["value"] == 3 * job.seed ** 2
    assert rec["wall_s"] >= 0 and rec["machine"]["host"]
    stored = json.loads(Path(job.result).read_text())
    assert stored["result"] == rec["result"] and stored["job"]["params"] == {"scale": 3}


def test_processes_then_skip(tmp_path):
  jobs = make_jobs(tmp_path)
  records = sweep.run_jobs(jobs, square_job, workers=2, log=lambda m: None)
  check_records(jobs, records, skipped=False)
  assert all(r["result"]["pid"] != os.getpid() for r in records)  # ran in worker processes

  # A second call runs nothing: every record is read back, unchanged.
  before = {j.result: Path(j.result).stat().st_mtime_ns for j in jobs}
  again = sweep.run_jobs(jobs, square_job, workers=2, log=lambda m: None)
  check_records(jobs, again, skipped=True)
  assert {j.result: Path(j.result).stat().st_mtime_ns for j in jobs} == before

  # Only the missing one runs when one result is deleted.
  os.remove(jobs[4].result)
  third = sweep.run_jobs(jobs, square_job, workers=2, log=lambda m: None)
  assert [r["skipped"] for r in third] == [True] * 4 + [False, True]


def test_failure_is_recorded_not_written(tmp_path):
  jobs = make_jobs(tmp_path, variants=("a", "broken"), seeds=(1,))
  records = sweep.run_jobs(jobs, square_job, workers=1, log=lambda m: None)
  assert "error" not in records[0] and Path(jobs[0].result).exists()
  assert "ValueError: this variant always fails" in records[1]["error"]
  assert not Path(jobs[1].result).exists()  # so the next sweep retries it


def test_duplicate_results_refused(tmp_path):
  job = make_jobs(tmp_path, seeds=(0,))[0]
  with pytest.raises(sweep.UserError, match="share a result file"):
    sweep.run_jobs([job, job], square_job, log=lambda m: None)


def test_command_cli(tmp_path):
  jobs = [{"scene": "s", "variant": "echo", "seed": s, "result": str(tmp_path / f"{s}.json"),
           "command": [sys.executable, "-c", f"print({s} * 7)"]} for s in (0, 1)]
  jobs_file = tmp_path / "jobs.json"
  jobs_file.write_text(json.dumps(jobs))
  assert sweep.main([str(jobs_file), "--workers", "2"]) == 0
  assert json.loads((tmp_path / "1.json").read_text())["result"]["stdout_tail"].strip() == "7"
  jobs_file.write_text(json.dumps([{**jobs[0], "result": str(tmp_path / "x.json"),
                                    "command": [sys.executable, "-c", "raise SystemExit(3)"]}]))
  assert sweep.main([str(jobs_file)]) == 1
  assert sweep.main([str(tmp_path / "missing.json")]) == 2


def test_ray_local(tmp_path):
  ray = pytest.importorskip("ray")
  ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
  try:
    jobs = make_jobs(tmp_path)
    records = sweep.run_jobs(jobs, square_job, ray_address="local", log=lambda m: None)
    check_records(jobs, records, skipped=False)
    assert ray.is_initialized()  # the runner leaves a Ray it did not start running
    assert all(r["result"]["pid"] != os.getpid() for r in records)  # ran in Ray workers
    again = sweep.run_jobs(jobs, square_job, ray_address="local", log=lambda m: None)
    check_records(jobs, again, skipped=True)
  finally:
    ray.shutdown()


@pytest.mark.timeout(120)
def test_workers_run_jax_after_the_driver_did(tmp_path):
  """Workers are spawned, not forked: a fork of a process whose XLA thread pools are running can
  hang forever in the child (seen when a sweep ran inside the test session)."""
  import jax.numpy as jnp
  float(jnp.ones(4).sum())  # the driver has XLA running
  jobs = [sweep.Job(scene="s", variant="jax", seed=s, result=str(tmp_path / f"{s}.json"))
          for s in range(3)]
  records = sweep.run_jobs(jobs, jax_job, workers=2, log=lambda m: None)
  assert [r["result"]["value"] for r in records] == [0.0, 1.0, 5.0]
