"""Running a stage's independent tasks (per GOP, per GOP x QP) in this process or on a Ray cluster."""

from stgs.tasks.runner import LocalRunner, Runner, Task, TaskFailedError, open_runner

__all__ = ["LocalRunner", "Runner", "Task", "TaskFailedError", "open_runner"]
