"""A small sweep runner: (scene, variant, seed) jobs in parallel processes, or on Ray.

Conventions:
  - A `Job` names one run: `scene`, `variant`, `seed`, free `params` (e.g. the training steps) and
    `result`, the path of its result JSON. A job whose result file exists is finished and is not
    run again (its record is read back), so an interrupted sweep resumes where it stopped.
  - `fn(job) -> dict` does the work. It must be picklable: a module-level function. Its dict (any
    JSON values) goes into the record under "result".
  - The record (one JSON per job, written atomically by the driver, never by a worker) holds the
    job, the seed, the wall time in seconds, the machine the job ran on, and the result. A job
    that raises writes no result file; its record carries "error" and the sweep goes on.
  - Processes: `concurrent.futures.ProcessPoolExecutor(workers)` on this machine, started by
    "spawn": a forked child of a driver that has already run JAX (its thread pools) can hang
    forever, and a job function may train in process. Ray (the
    optional extra `ofjax[cluster]`): `ray_address="local"` starts a local instance for the sweep
    (and shuts it down after); any other address is passed to `ray.init(address=...)`, e.g.
    "auto" or "ray://head:10001"; an already initialised Ray is used as it is. Each job becomes
    one `@ray.remote` task asking for `cpus_per_job` CPUs, so Ray does the scheduling. The
    modules of `fn` and of this file are shipped by value (cloudpickle), so the workers need
    ofjax installed but not this checkout; paths in the jobs must be on a filesystem the workers
    share with the driver.

`python experiments/sweep.py JOBS.json [--workers N] [--ray ADDRESS]` runs command jobs: JOBS.json
is a list of {"scene", "variant", "seed", "result", "command": [argv...]}; each command runs as a
subprocess and a non-zero exit is the job's error.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import json
import multiprocessing
import subprocess
import sys
import time
import traceback
from pathlib import Path
from typing import Any, Callable

from ofjax import fileio, machine
from ofjax.errors import UserError, cli

STDOUT_TAIL_CHARS = 2000  # what a command job keeps of its output in the record


@dataclasses.dataclass(frozen=True)
class Job:
  """One run of a sweep; `result` is the path of its record (JSON)."""
  scene: str
  variant: str
  seed: int
  result: str
  params: dict[str, Any] = dataclasses.field(default_factory=dict)

  @property
  def name(self) -> str:
    return f"{self.scene}/{self.variant}/seed{self.seed}"


def execute(job: Job, fn: Callable[[Job], dict]) -> dict[str, Any]:
  """Runs one job where it is called (a worker process or a Ray task) and returns its record."""
  record = {"job": dataclasses.asdict(job), "name": job.name, "seed": job.seed,
            "machine": machine.describe()}  # on Ray each worker reports its own node
  t0 = time.time()
  try:
    record["result"] = fn(job)
  except Exception as e:  # a failing job must not take the sweep down; the record says why
    record["error"] = f"{type(e).__name__}: {e}"
    record["traceback"] = traceback.format_exc()
  record["wall_s"] = time.time() - t0
  return record


def _finish(job: Job, record: dict[str, Any], log: Callable[[str], None]) -> dict[str, Any]:
  if "error" in record:
    log(f"sweep: FAILED {job.name} after {record['wall_s']:.1f} s: {record['error']}")
  else:
    fileio.write_json(job.result, record)
    log(f"sweep: done {job.name} in {record['wall_s']:.1f} s")
  record["skipped"] = False
  return record


def _ray(address: str):
  try:
    import ray
  except ImportError as e:
    raise UserError("--ray needs the optional dependency ray; install it with "
                    "`pip install 'ofjax[cluster]'` (or `pip install 'ray>=2.9'`)") from e
  return ray


def run_jobs(jobs: list[Job], fn: Callable[[Job], dict], workers: int = 1,
             ray_address: str | None = None, cpus_per_job: float = 1,
             log: Callable[[str], None] = print) -> list[dict[str, Any]]:
  """Runs the unfinished `jobs` and returns one record per job, in the order of `jobs`.

  Finished jobs (result file present) come back as their stored record with "skipped": True.
  `workers` bounds the processes on this machine; with `ray_address` it is the CPU count of a
  local Ray instance ("local") and is otherwise unused (the cluster's resources bound the tasks).
  """
  names = [j.result for j in jobs]
  if len(set(names)) != len(names):
    raise UserError("sweep: two jobs share a result file; give every (scene, variant, seed) its own")
  records: dict[int, dict[str, Any]] = {}
  todo = []
  for i, job in enumerate(jobs):
    if Path(job.result).exists():
      records[i] = {**json.loads(Path(job.result).read_text()), "skipped": True}
    else:
      todo.append(i)
  log(f"sweep: {len(jobs)} jobs, {len(jobs) - len(todo)} finished before, {len(todo)} to run"
      + (f" on Ray ({ray_address})" if ray_address else f" in {workers} process(es)"))
  if not todo:
    return [records[i] for i in range(len(jobs))]

  if ray_address is None:
    with concurrent.futures.ProcessPoolExecutor(
        max_workers=workers, mp_context=multiprocessing.get_context("spawn")) as pool:
      futures = {pool.submit(execute, jobs[i], fn): i for i in todo}
      for fut in concurrent.futures.as_completed(futures):
        i = futures[fut]
        records[i] = _finish(jobs[i], fut.result(), log)
    return [records[i] for i in range(len(jobs))]

  ray = _ray(ray_address)
  started_here = not ray.is_initialized()
  if started_here:
    if ray_address == "local":
      ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    else:
      ray.init(address=ray_address, log_to_driver=False)
  try:
    # Ship fn's module and this one by value: Ray workers need not have this checkout on their path.
    for module in {fn.__module__, execute.__module__} - {"__main__"}:
      ray.cloudpickle.register_pickle_by_value(sys.modules[module])
    remote = ray.remote(num_cpus=cpus_per_job)(execute)
    pending = {remote.remote(jobs[i], fn): i for i in todo}
    while pending:
      ready, _ = ray.wait(list(pending), num_returns=1)
      i = pending.pop(ready[0])
      records[i] = _finish(jobs[i], ray.get(ready[0]), log)
  finally:
    if started_here:
      ray.shutdown()
  return [records[i] for i in range(len(jobs))]


def run_command(job: Job) -> dict[str, Any]:
  """A command job: runs `job.params["command"]` (argv list); a non-zero exit raises."""
  proc = subprocess.run(job.params["command"], capture_output=True, text=True)
  if proc.returncode != 0:
    raise RuntimeError(f"exit {proc.returncode}: {proc.stderr.strip()[-STDOUT_TAIL_CHARS:]}")
  return {"returncode": proc.returncode, "stdout_tail": proc.stdout[-STDOUT_TAIL_CHARS:]}


def load_command_jobs(path: str) -> list[Job]:
  """Reads a JOBS.json file (see the module docstring)."""
  try:
    items = json.loads(Path(path).read_text())
    return [Job(scene=str(d["scene"]), variant=str(d["variant"]), seed=int(d["seed"]),
                result=str(d["result"]), params={"command": [str(a) for a in d["command"]]})
            for d in items]
  except FileNotFoundError:
    raise UserError(f"{path}: no such file; give a JSON list of jobs") from None
  except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
    raise UserError(f"{path}: not a list of jobs with scene, variant, seed, result and command "
                    f"({type(e).__name__}: {e}); fix the file") from None


@cli
def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python experiments/sweep.py", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("jobs", help="JSON list of {scene, variant, seed, result, command}")
  p.add_argument("--workers", type=int, default=1, help="parallel processes (default 1)")
  p.add_argument("--ray", metavar="ADDRESS",
                 help="run the jobs as Ray tasks: 'local' starts a local instance, else "
                      "ray.init(address=ADDRESS)")
  p.add_argument("--cpus-per-job", type=float, default=1, help="CPUs one Ray task asks for")
  args = p.parse_args(argv)
  if args.workers < 1:
    raise UserError(f"--workers {args.workers}: need at least 1")
  records = run_jobs(load_command_jobs(args.jobs), run_command, workers=args.workers,
                     ray_address=args.ray, cpus_per_job=args.cpus_per_job)
  failed = [r["name"] for r in records if "error" in r]
  if failed:
    print(f"sweep: {len(failed)} job(s) failed: {', '.join(failed)}", file=sys.stderr)
  return 1 if failed else 0


if __name__ == "__main__":
  sys.exit(main())
