"""What a user can ask of a job, declared once: :class:`JobRequest` (the user's view, with each
default, bound and description) builds :class:`JobOptions` (the pipeline's view).

The command line and the API both take a :class:`JobRequest`, so every option a user can set
on one can be set on the other, with the same defaults and bounds.  This is the bottom of
:mod:`kneemesh_core.job`: it imports nothing else of it.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.fe.physics import LoadCase
from kneemesh_core.hexmesh import BlendOptions, HexOptions
from kneemesh_core.surfaces.tissue import SurfaceOptions
from kneemesh_core.tissues import BONES, CARTILAGES, TISSUES

INPUT_TYPES = ("labels", "image")
#: The tissue groups a job can be limited to (``only``).
GROUPS = {"bones": BONES, "cartilage": CARTILAGES, "all": TISSUES}


@dataclasses.dataclass(frozen=True)
class JobOptions:
    """Everything the steps of one job need to know, as plain data a queue can carry (:meth:`to_dict`)."""

    input_type: str = "labels"  # or "image": a DESS volume, segmented first
    model: str | None = None  # segmentation model (default: the shipped one)
    preset: str | None = None
    labels: str | None = None
    side: str | None = None
    only: str = "all"
    stl: bool = False
    bundle: bool = False
    simulate: str = "none"  # or "smoke" (to 15 deg) or "full" (the load case's activity): a CalculiX run of the decks
    load: LoadCase = LoadCase()  # the decks' loads, flexion and cartilage (fe/physics.py)
    force: bool = False  # mesh an image's labels although the segmentation fails its plausibility checks
    surface: SurfaceOptions = SurfaceOptions()
    hex: HexOptions = HexOptions()
    blend: BlendOptions | None = BlendOptions()  # None: keep the step at the cartilage edge

    def tissues(self) -> tuple[str, ...]:
        if self.only not in GROUPS:
            raise KneeMeshError("bad_option", f"--only {self.only!r}: expected one of {', '.join(GROUPS)}.")
        return GROUPS[self.only]

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "JobOptions":
        d = dict(d)
        d["surface"] = SurfaceOptions(**d.get("surface", {}))
        d["hex"] = HexOptions(**d.get("hex", {}))
        if "blend" in d:
            d["blend"] = None if d["blend"] is None else BlendOptions(**d["blend"])
        cartilage = d.pop("fe_cartilage", None)  # (records written before the load case had a home of its own)
        d["load"] = LoadCase(**{**d.get("load", {}), **({"cartilage": cartilage} if cartilage else {})})
        return cls(**d)


class JobRequest(BaseModel):
    """The options a user sets for one job, from the command line or the API: each default and bound
    is declared here and nowhere else."""

    model_config = ConfigDict(frozen=True)

    input_type: Literal["labels", "image"] = Field(
        "labels", description="labels (a segmentation) or image (a sagittal DESS volume, segmented first).")
    model: str | None = Field(
        None, description="Segmentation model for image inputs: an .onnx file (the API takes the name of one "
                          "shipped with the server); default: the shipped model.")
    preset: str | None = Field(
        None, description="Label convention: kneemesh, pymskt, oai-zib, imorphics (default: detect).")
    labels: str | None = Field(
        None, description="Custom label mapping 'femur=5,tibia=6,...' (the command line also takes a JSON file).")
    side: Literal["left", "right"] | None = Field(None, description="left or right (default: detect and report how).")
    only: Literal["all", "bones", "cartilage"] = Field("all", description="Tissues to mesh: all, bones or cartilage.")
    element_size: float = Field(1.0, ge=0.2, le=5.0, allow_inf_nan=False,
                                description="Cartilage in-plane element edge, mm.")
    layers: int = Field(4, ge=1, le=12, description="Cartilage element layers through the thickness.")
    blend: bool = Field(True, description="Blend the cartilage edge into the bone and fuse it onto the bone.")
    blend_angle: float = Field(45.0, ge=20.0, le=80.0, allow_inf_nan=False,
                               description="Angle at which the blended cartilage edge meets the bone, deg.")
    bone_edge: float = Field(3.0, ge=0.5, le=10.0, allow_inf_nan=False, description="Target bone triangle edge away from the cartilage, mm (under it: the element size).")
    stl: bool = Field(False, description="Also write the bone shells as .stl.")
    simulate: Literal["none", "smoke", "full"] = Field(
        "none", description="Run the CalculiX deck: smoke (to 15 deg of flexion) or full (the activity, to 90 deg); none: write the decks only.")
    force: bool = Field(False, description="For an image: mesh its labels even where the segmentation fails its "
                                           "plausibility checks (the knee is then review); otherwise the job stops "
                                           "before meshing, with the reasons.")
    joint_load: float = Field(1000.0, ge=0.0, le=6000.0, allow_inf_nan=False,
                              description="The joint load the femur carries, N (down the tibial axis).")
    medial_offset: float = Field(LoadCase.medial_offset_mm, ge=-40.0, le=40.0, allow_inf_nan=False,
                                 description="How far medial of the knee's centre the joint load's line of action "
                                             "passes in the frontal plane, mm (negative: lateral); the knee "
                                             "adduction moment is the joint load times it.")
    quadriceps: float = Field(300.0, ge=0.0, le=3000.0, allow_inf_nan=False,
                              description="The quadriceps force on the patella at its initial length, N.")
    flexion: float = Field(90.0, ge=1.0, le=120.0, allow_inf_nan=False,
                           description="The flexion a full run reaches, deg: from the image pose (activity flexion) or "
                                       "anatomical (knee_bend).")
    activity: Literal["flexion", "knee_bend"] = Field(
        "flexion", description="What a full run does: flexion (from the image pose to the flexion asked for, the joint "
                               "load held) or knee_bend (from anatomical extension to the flexion asked for and back, "
                               "the joint load rising to peak_load at the deepest flexion, as in the paper's activity).")
    peak_load: float = Field(LoadCase.peak_load_n, ge=0.0, le=8000.0, allow_inf_nan=False,
                             description="The knee bend's joint load at its deepest flexion, N.")
    fe_cartilage: Literal["rigid", "deformable"] = Field(
        "rigid", description="Cartilage in the decks: rigid (the paper's choice; contact stiffness from its layers; "
                 "seconds a run) or deformable (solid neo-Hookean hexahedra; stress and strain reported; minutes a run).")

    @classmethod
    def build(cls, **given) -> "JobRequest":
        """A request from the options a user gave (None: not given, so the default); a value out of
        bounds is a ``bad_option`` error that names the option and what is expected."""
        try:
            return cls(**{k: v for k, v in given.items() if v is not None})
        except ValidationError as exc:
            raise KneeMeshError("bad_option", "; ".join(
                f"{'.'.join(map(str, e['loc'])) or 'options'}: {e['msg']}" for e in exc.errors())) from None

    def job_options(self, *, bundle: bool = False) -> JobOptions:
        """The pipeline's options for this request; ``bundle`` zips the outputs (the service does)."""
        return JobOptions(
            input_type=self.input_type, model=self.model, preset=self.preset, labels=self.labels, side=self.side,
            only=self.only, stl=self.stl, bundle=bundle, simulate=self.simulate, force=self.force,
            load=LoadCase(joint_load_n=self.joint_load, medial_offset_mm=self.medial_offset, quadriceps_n=self.quadriceps,
                          flexion_deg=self.flexion, cartilage=self.fe_cartilage, activity=self.activity,
                          peak_load_n=self.peak_load),
            surface=SurfaceOptions(bone_edge_mm=self.bone_edge, articular_edge_mm=min(self.element_size, self.bone_edge)),
            hex=HexOptions(element_size=self.element_size, layers=self.layers),
            blend=BlendOptions(angle_deg=self.blend_angle) if self.blend else None)
