"""The one definition of a KneeMesh job, shared by the command line and the service's workers.

- :mod:`.options` - what a user can ask (:class:`JobRequest`) and what the steps are told
  (:class:`JobOptions`);
- :mod:`.steps` - what runs on one knee: ingest, segment, mesh a tissue (a cartilage: mesh, then blend), conform, anatomy, decks,
  overlaps, simulate;
- :mod:`.plan` - the stages in order, what each step waits for, and :func:`run_step`, which runs and records one step;
- :mod:`.outputs` - the job folder: file names, step records, ``report.json``, the bundle;
- :mod:`.local` - the in-process runner (:func:`run`).
"""

from kneemesh_core.job.local import JobCancelled, run
from kneemesh_core.job.options import GROUPS, INPUT_TYPES, JobOptions, JobRequest
from kneemesh_core.job.outputs import BUNDLE_FILE, MANIFEST_FILE, REPORT_FILE, bundle, read_step, utc_now
from kneemesh_core.job.plan import (ANATOMY, BUNDLE, CONFORM, DECKS, HEX_STEPS, INGEST, OVERLAPS, REPORT, SEGMENT, SIMULATE,
                                   needs, plan, run_step, start_order)

__all__ = ["ANATOMY", "BUNDLE", "BUNDLE_FILE", "CONFORM", "DECKS", "OVERLAPS", "SIMULATE", "GROUPS", "HEX_STEPS", "INGEST",
           "INPUT_TYPES", "JobCancelled", "JobOptions", "JobRequest", "MANIFEST_FILE", "REPORT", "REPORT_FILE", "SEGMENT",
           "bundle", "needs", "plan", "read_step", "run", "run_step", "start_order", "utc_now"]
