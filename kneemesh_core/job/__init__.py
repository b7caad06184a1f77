"""The one definition of a KneeMesh job, shared by the command line and the service's workers.

- :mod:`.options` - what a user can ask (:class:`JobRequest`) and what the steps are told
  (:class:`JobOptions`);
- :mod:`.steps` - what runs on one knee, a function per step: ingest, segment, mesh a bone, mesh a
  cartilage and then blend it, conform, anatomy, decks, simulate, overlaps, bundle;
- :mod:`.stages` - each stage declared once (its function, what it reads, when it runs, its report
  section): the registry everything below follows;
- :mod:`.plan` - the stages in order, what each step waits for, and :func:`run_step`, which runs and
  records one step;
- :mod:`.report` - ``report.json`` and :mod:`.verdict` - the verdicts of each tissue and of the knee;
- :mod:`.outputs` - the job folder: file names, step records, the bundle;
- :mod:`.local` - the in-process runner (:func:`run`).
"""

from kneemesh_core.job.local import JobCancelled, run
from kneemesh_core.job.options import GROUPS, INPUT_TYPES, JobOptions, JobRequest
from kneemesh_core.job.outputs import BUNDLE_FILE, MANIFEST_FILE, REPORT_FILE, bundle, read_step, utc_now
from kneemesh_core.job.plan import needs, plan, run_step, start_order
from kneemesh_core.job.stages import (ANATOMY, BONE, BUNDLE, CARTILAGE, CONFORM, DECKS, HEX_STEPS, HEXMESH, INGEST, OVERLAPS,
                                     REPORT, SEGMENT, SIMULATE, STAGES, Stage)
from kneemesh_core.job.steps import Step

__all__ = ["ANATOMY", "BONE", "BUNDLE", "CARTILAGE", "HEXMESH", "BUNDLE_FILE", "CONFORM", "DECKS", "OVERLAPS", "SIMULATE", "GROUPS", "HEX_STEPS", "INGEST",
           "INPUT_TYPES", "JobCancelled", "JobOptions", "JobRequest", "MANIFEST_FILE", "REPORT", "REPORT_FILE", "SEGMENT",
           "STAGES", "Stage", "Step", "bundle", "needs", "plan", "read_step", "run", "run_step", "start_order", "utc_now"]
