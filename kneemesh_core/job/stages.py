"""The stages of a job, each declared once: its name, the function its steps run, what it reads, when it
runs, its section of ``report.json`` and its line in a summary.

Everything else follows from these declarations: the plan and the order of its steps (:mod:`.plan`),
the runners (:mod:`.local`, and the Celery canvas in ``services.worker``), the report and the knee's
verdict (:mod:`.report`), the step kinds of the API's schema and the command line's table.  A new stage
is one :class:`Stage` added to :data:`STAGES` (:meth:`Stages.add`) and its function, which takes a
:class:`.steps.Step` and returns its result (with ``status`` and ``reasons`` where the knee's verdict
should judge it).
"""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Callable, Iterator

from kneemesh_core.job import steps
from kneemesh_core.job.options import JobOptions
from kneemesh_core.job.steps import Step, hex_step
from kneemesh_core.tissues import BONE_OF, BONES, CARTILAGES, TISSUES

INGEST, SEGMENT, CONFORM, ANATOMY, DECKS, OVERLAPS, SIMULATE, REPORT, BUNDLE = (
    "ingest", "segment", "conform", "anatomy", "decks", "overlaps", "simulate", "report", "bundle")
#: The stages of one step per tissue (their steps are named by the tissue, or ``hex_<cartilage>``).
BONE, HEXMESH, CARTILAGE = "bone", "hexmesh", "cartilage"
#: the step that meshes each cartilage before its own step blends it, and the cartilage it meshes
HEX_STEPS = {hex_step(c): c for c in CARTILAGES}
#: The report section of the tissue stages: one entry per tissue.
TISSUES_SECTION = "tissues"
#: In a stage's ``after``: every stage declared before it (the report reads them all).
EARLIER = "*"


def _always(options: JobOptions) -> bool:
    return True


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of a job.

    ``run`` does the work of one of its steps.  ``after``: the stages whose steps it reads, or must
    follow (a stage absent from a job's plan is passed over; :data:`EARLIER`: every stage declared
    before it), and ``reads(step)``, where a step reads
    only some of their steps (a cartilage's blend: its own mesh and its bone).  ``when``: whether a
    job's plan has the stage; ``steps``: its steps (default: one, named as the stage).  ``section``: the
    key of ``report.json`` its result fills (:data:`TISSUES_SECTION`: one entry per step), judged by the
    knee's verdict; ``fold`` puts its result into the tissues' entries instead.  ``summary``: one line of
    its report entry for the command line.  ``about``: what it does, for the API's schema.
    """

    name: str
    run: Callable[[Step], dict]
    about: str
    after: tuple[str, ...] = ()
    when: Callable[[JobOptions], bool] = _always
    steps: Callable[[JobOptions], tuple[str, ...]] | None = None
    reads: Callable[[str], set[str]] | None = None
    section: str | None = None
    fold: Callable[[dict, dict], None] | None = None
    summary: Callable[[dict], str] | None = None
    input: bool = False  # its steps read the job's input file (they run first, in the runner's own process)

    def planned_steps(self, options: JobOptions) -> tuple[str, ...]:
        """The stage's steps in a job with ``options`` (none when the plan does not have it)."""
        if not self.when(options):
            return ()
        return self.steps(options) if self.steps is not None else (self.name,)


class Stages:
    """The stages of a job in declaration order: the order the report's sections and the verdict's
    reasons follow.  The plan orders their steps by what each reads (:mod:`.plan`)."""

    def __init__(self, stages: list[Stage]):
        self._stages = list(stages)

    def __iter__(self) -> Iterator[Stage]:
        return iter(list(self._stages))

    def __getitem__(self, name: str) -> Stage:
        for stage in self._stages:
            if stage.name == name:
                return stage
        raise KeyError(name)

    def of(self, options: JobOptions, step: str) -> Stage:
        """The stage a step of a job with ``options`` belongs to."""
        for stage in self._stages:
            if step in stage.planned_steps(options):
                return stage
        raise KeyError(step)

    def add(self, stage: Stage, before: str = REPORT) -> None:
        """Declare a stage, before the stage ``before`` in declaration order (by default before the
        report, so that the report has its section)."""
        if any(s.name == stage.name for s in self._stages):
            raise ValueError(f"a stage {stage.name!r} is declared already")
        self._stages.insert(self._stages.index(self[before]), stage)

    def remove(self, name: str) -> None:
        self._stages.remove(self[name])

    @contextlib.contextmanager
    def extended(self, stage: Stage, before: str = REPORT):
        """The registry with ``stage`` added while the block runs (tests, plug-ins tried out)."""
        self.add(stage, before)
        try:
            yield self
        finally:
            self.remove(stage.name)


def _tissues_of(group: tuple[str, ...]) -> Callable[[JobOptions], tuple[str, ...]]:
    return lambda options: tuple(t for t in options.tissues() if t in group)


def _whole_knee(options: JobOptions) -> bool:
    return set(options.tissues()) == set(TISSUES)


def _report(step: Step) -> dict:
    from kneemesh_core.job.report import write_report

    return write_report(step.out, step.options, STAGES)["summary"]


# -- one line of a stage's report entry, for the command line ------------------------------------------
def _anatomy_line(a: dict) -> str:
    res = ", ".join(f"{b} {r:.2f}" for b, r in a["residuals_mm"].items())
    ang = a["angles_deg"]
    return (f"{a['sites_placed']} attachment sites of {a['fibres']} fibres; registration residuals {res} mm; "
            f"flexion {ang['flexion']:.1f}, varus {ang['varus']:.1f}, internal rotation {ang['internal_rotation']:.1f} deg")


def _decks_line(fe: dict) -> str:
    return f"{', '.join(fe['files'][:3])}; {', '.join(f'{n} {t}' for t, n in fe['elements'].items())}, {fe['springs']} ligament springs"


def _simulation_line(sim: dict) -> str:
    from kneemesh_core.fe.results import CONTACTS

    final = sim["final"]
    line = (f"{sim['kind']}, {sim['solver']}, {sim['solver_seconds']:.0f} s: "
            f"{'completed' if sim['completed'] else 'stopped: ' + str(sim['reason'])} at "
            f"{sim['reached_flexion_deg']:.1f} of {sim['target_flexion_deg']:.0f} deg")
    if sim.get("activity") == "knee_bend":
        line += " of anatomical flexion" + (f", back at {final['anatomical_flexion_deg']:.1f} deg"
                                            if final.get("anatomical_flexion_deg") is not None else "")
    elif final.get("anatomical_flexion_deg") is not None:
        line += f" from the image pose (anatomically {final['anatomical_flexion_deg']:.1f} deg)"
    if final.get("medial"):
        line += "; " + ", ".join(f"{k} {final[k]['force_n']:.0f} N on {final[k]['area_mm2']:.0f} mm^2, peak "
                                 f"{final[k]['peak_pressure_mpa']:.1f} MPa" for k in CONTACTS if k in final)
    return line


def _overlaps_line(o: dict) -> str:
    deepest = max(o["pairs"].items(), key=lambda kv: kv[1]["max_depth_mm"], default=None)
    return "none measured" if deepest is None else f"deepest {deepest[1]['max_depth_mm']:.2f} mm ({deepest[0]})"


def _segmentation_line(s: dict) -> str:
    return f"{s['side']} knee, {s['seconds']:.1f} s; " + ", ".join(f"{t} {v:.1f} ml" for t, v in s["tissues_ml"].items())


#: The stages of a KneeMesh job, in declaration order.
STAGES = Stages([
    Stage(INGEST, steps.ingest, "reads the input, decides the label convention and the side, writes canonical labels",
          input=True),
    Stage(SEGMENT, steps.segment, "labels an image with the segmentation network and checks the labels are a knee",
          after=(INGEST,), when=lambda o: o.input_type == "image", section="segmentation", summary=_segmentation_line,
          input=True),
    Stage(BONE, steps.mesh_bone, "a bone's closed shell", after=(INGEST, SEGMENT), steps=_tissues_of(BONES),
          section=TISSUES_SECTION),
    Stage(HEXMESH, steps.hex_cartilage, "a cartilage's all-hex mesh before its blend (it needs only the labels)",
          after=(INGEST, SEGMENT), steps=lambda o: tuple(hex_step(c) for c in _tissues_of(CARTILAGES)(o))),
    Stage(CARTILAGE, steps.finish_cartilage, "a cartilage's mesh blended and fused onto its bone",
          after=(HEXMESH, BONE), steps=_tissues_of(CARTILAGES), reads=lambda c: {hex_step(c), BONE_OF[c]},
          section=TISSUES_SECTION),
    Stage(ANATOMY, steps.place_anatomy, "the knee's frames and ligament attachment sites on the bone meshes",
          after=(BONE,), when=lambda o: set(o.tissues()) >= set(BONES), section="anatomy", summary=_anatomy_line),
    Stage(CONFORM, steps.conform_bones, "each bone gives way where a fused cartilage still dips into it",
          after=(CARTILAGE, ANATOMY),  # the anatomy reads the bones before they give way
          when=lambda o: o.blend is not None and set(o.tissues()) >= set(BONES) | set(CARTILAGES),
          fold=steps.fold_conformed),
    Stage(DECKS, steps.write_decks, "the Abaqus and CalculiX decks of the whole knee",
          after=(CONFORM, ANATOMY, CARTILAGE, BONE), when=_whole_knee, section="fe", summary=_decks_line),
    Stage(SIMULATE, steps.run_simulation, "CalculiX on the decks (on request)", after=(DECKS,),
          when=lambda o: _whole_knee(o) and o.simulate != "none", section="simulation", summary=_simulation_line),
    Stage(OVERLAPS, steps.measure_overlaps, "where the final meshes overlap", after=(CONFORM, CARTILAGE, BONE),
          when=lambda o: any(t in CARTILAGES for t in o.tissues()), section="overlaps", summary=_overlaps_line),
    Stage(REPORT, _report, "report.json: every entry and the knee's verdict", after=(EARLIER,)),
    Stage(BUNDLE, steps.bundle_outputs, "bundle.zip and the list of artifacts with their SHA-256", after=(REPORT,),
          when=lambda o: o.bundle),
])
