"""The Ray back-end: each zoo job is a Ray task (one CPU) that runs :func:`rlbackdoors.zoo.job.run_job`
and writes its results into the zoo folder itself, so the zoo must be on storage every node
sees at the same path. Ray is an optional extra (``pip install rlbackdoors[ray]``) and is
imported only here.

``max_retries`` is Ray's: a task whose worker process or node dies is run again (it resumes
from the folder's checkpoint). A job that raises is not retried by Ray: the coordinator
counts it and retries it like the local back-end does.
"""

from __future__ import annotations

from pathlib import Path

try:
    import ray
except ImportError as err:  # pragma: no cover - depends on the install
    raise ImportError(f"--backend ray needs Ray: pip install 'rlbackdoors[ray]' ({err})") from None

from rlbackdoors.zoo.plan import PlannedModel


def zoo_task(folder: str) -> dict:
    """The task body: the job's result, or its error as a value (the coordinator retries)."""
    from rlbackdoors.io import first_line
    from rlbackdoors.train.stop import Interrupted
    from rlbackdoors.zoo.job import run_job

    try:
        return run_job(folder, log=True)
    except (Interrupted, KeyboardInterrupt) as err:
        return {"status": "interrupted", "error": first_line(err)}
    except Exception as err:
        return {"status": "error", "error": f"{type(err).__name__}: {first_line(err)}"[:2000]}


class RayExecutor:
    """At most ``workers`` tasks in flight (default: the cluster's CPUs)."""

    def __init__(self, workers: int | None, address: str | None, max_retries: int):
        self.started_ray = False
        if not ray.is_initialized():
            if address:
                ray.init(address=address, log_to_driver=False)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
            self.started_ray = True
        self.capacity = workers or max(1, int(ray.cluster_resources().get("CPU", 1)))
        self.remote = ray.remote(num_cpus=1, max_retries=max_retries)(zoo_task)
        self.refs: dict = {}

    def submit(self, model: PlannedModel, folder: Path) -> None:
        self.refs[self.remote.remote(str(Path(folder).resolve()))] = model

    def wait(self, timeout: float) -> list[tuple[PlannedModel, dict]]:
        if not self.refs:
            return []
        ready, _ = ray.wait(list(self.refs), num_returns=1, timeout=timeout)
        out = []
        for ref in ready:
            model = self.refs.pop(ref)
            try:
                result = ray.get(ref)
            except ray.exceptions.RayError as err:  # the worker died more often than max_retries allows
                text = str(err).strip().splitlines()
                result = {"status": "error", "error": f"{type(err).__name__}: {text[0] if text else ''}"[:2000]}
            out.append((model, result))
        return out

    def running(self) -> int:
        return len(self.refs)

    def stop(self) -> None:
        """Cancel what is in flight (a cancelled task's folder resumes next run), then leave Ray."""
        for ref in list(self.refs):
            ray.cancel(ref, force=False)
        self.refs.clear()
        if self.started_ray:
            ray.shutdown()
