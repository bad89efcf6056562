"""Cohorts on Dask distributed: studies, phantom cases and the hidden-effect suite as tasks whose
inputs and results are files (a rerun resumes, a lost worker costs one task), run in this
process, on a local cluster (one worker per GPU) or on an existing cluster by its scheduler's
address (docs/cohorts.md)."""

from BreastBiomechLib.cohort.cluster import SCHEDULER_ENVIRONMENT, Placement, cohort_client, place
from BreastBiomechLib.cohort.runner import CohortCancelled, CohortProgress, run_tasks
from BreastBiomechLib.cohort.tasks import Task, TaskOutcome, ordered
from BreastBiomechLib.io.atomic import write_json_atomically

__all__ = ["CohortCancelled", "CohortProgress", "Placement", "SCHEDULER_ENVIRONMENT", "Task", "TaskOutcome",
           "cohort_client", "ordered", "place", "run_tasks", "write_json_atomically"]
