"""Running a stage's independent tasks (per GOP, per GOP x QP) in this process or on a Ray cluster."""

from stgs.tasks.runner import LocalRunner, Runner, Task, TaskFailedError

__all__ = ["LocalRunner", "Runner", "Task", "TaskFailedError", "open_runner"]


def open_runner(address: str | None, retries: int = 3, progress: bool = True) -> Runner:
    """This process (address None) or a Ray cluster: "local" (started here, on this machine's cores), "auto" (the
    cluster `ray start` made on this machine, or RAY_ADDRESS) or HOST:PORT / ray://HOST:PORT. Ray is imported only
    for a cluster."""
    if address is None:
        return LocalRunner()
    from stgs.tasks.ray_runner import RayRunner

    return RayRunner.connect(address, retries, progress)
