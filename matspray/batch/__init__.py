"""Many objects, many machines: the method once per object, as Ray tasks (`matspray batch`)."""

from matspray.batch.objects import BatchObject, batch_objects, run_one_object
from matspray.batch.runner import BatchConfig, run_batch
from matspray.batch.summary import batch_summary, summary_markdown

__all__ = [
    "BatchConfig",
    "BatchObject",
    "batch_objects",
    "batch_summary",
    "run_batch",
    "run_one_object",
    "summary_markdown",
]
