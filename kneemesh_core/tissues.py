"""The knee's tissues and the label conventions that name them, in one place.

Canonical labels (preset ``kneemesh``) are 1..7 in the order of :data:`TISSUES`.
A :class:`LabelConvention` says which values of a foreign label map make up
each canonical tissue.  Lesion labels (osteophytes, bone marrow lesions) are
merged into their bone; a merged tibial cartilage label is split into medial
and lateral plates by :mod:`kneemesh_core.side`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from kneemesh_core.errors import KneeMeshError

TISSUES: tuple[str, ...] = (
    "femur",
    "tibia",
    "patella",
    "femoral_cartilage",
    "medial_tibial_cartilage",
    "lateral_tibial_cartilage",
    "patellar_cartilage",
)
BONES: tuple[str, ...] = TISSUES[:3]
CARTILAGES: tuple[str, ...] = TISSUES[3:]
#: Canonical label value of each tissue.
LABEL: dict[str, int] = {t: i + 1 for i, t in enumerate(TISSUES)}
#: The bone each cartilage lies on.
BONE_OF: dict[str, str] = {
    "femoral_cartilage": "femur",
    "medial_tibial_cartilage": "tibia",
    "lateral_tibial_cartilage": "tibia",
    "patellar_cartilage": "patella",
}
#: Pseudo-tissue of conventions that do not separate the tibial plates.
MERGED_TIBIAL = "tibial_cartilage"
#: Plausible volume ranges in ml used to recognise a convention (generous).
_VOLUME_ML = {
    "femur": (40.0, 900.0),
    "tibia": (40.0, 900.0),
    "patella": (4.0, 80.0),
    "femoral_cartilage": (0.05, 45.0),
    "medial_tibial_cartilage": (0.02, 15.0),
    "lateral_tibial_cartilage": (0.02, 15.0),
    MERGED_TIBIAL: (0.05, 25.0),
    "patellar_cartilage": (0.02, 15.0),
}


@dataclass(frozen=True)
class LabelConvention:
    """Which label values make up each tissue.

    Attributes
    ----------
    name : str
    tissues : dict[str, tuple[int, ...]]
        Tissue (a name from :data:`TISSUES` or :data:`MERGED_TIBIAL`) to the label
        values that form it.
    extra : dict[int, str]
        Known labels that are not meshed (fibula, menisci).
    """

    name: str
    tissues: dict[str, tuple[int, ...]]
    extra: dict[int, str] = field(default_factory=dict)

    @property
    def known_values(self) -> set[int]:
        vals = {v for vs in self.tissues.values() for v in vs}
        return vals | set(self.extra)

    @property
    def has_bones(self) -> bool:
        return all(b in self.tissues for b in BONES)

    @property
    def merged_tibial(self) -> bool:
        return MERGED_TIBIAL in self.tissues

    def value_of(self, name: str) -> tuple[int, ...]:
        """Values of a tissue or a named extra label (e.g. ``"fibula"``); empty if absent."""
        if name in self.tissues:
            return self.tissues[name]
        return tuple(v for v, n in self.extra.items() if n == name)


PRESETS: dict[str, LabelConvention] = {
    "kneemesh": LabelConvention("kneemesh", {t: (LABEL[t],) for t in TISSUES}),
    "pymskt": LabelConvention(
        "pymskt",
        {
            "femoral_cartilage": (1,),
            "medial_tibial_cartilage": (2,),
            "lateral_tibial_cartilage": (3,),
            "patellar_cartilage": (4,),
            "femur": (5,),
            "tibia": (6,),
            "patella": (7,),
        },
        extra={8: "fibula", 9: "medial_meniscus", 10: "lateral_meniscus"},
    ),
    "oai-zib": LabelConvention(
        "oai-zib",
        {
            "femur": (1, 7),
            "femoral_cartilage": (2,),
            "tibia": (3, 8),
            MERGED_TIBIAL: (4,),
            "patella": (5, 9),
            "patellar_cartilage": (6,),
        },
    ),
    "imorphics": LabelConvention(
        "imorphics",
        {
            "femoral_cartilage": (1,),
            "lateral_tibial_cartilage": (2,),
            "medial_tibial_cartilage": (3,),
            "patellar_cartilage": (4,),
        },
        extra={5: "lateral_meniscus", 6: "medial_meniscus"},
    ),
}


def parse_custom(spec: str) -> LabelConvention:
    """Parse ``femur=5,tibia=6+8,...`` or the path of a JSON file ``{"femur": [5], ...}``.

    Tissue names are those of :data:`TISSUES`, ``tibial_cartilage`` for a merged
    tibial label, or ``fibula``/``medial_meniscus``/``lateral_meniscus``/``other``
    for labels that are known but not meshed.
    """
    path = Path(spec)
    if spec.strip().endswith(".json") or path.is_file():
        try:
            raw = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise KneeMeshError("bad_labels_spec", f"{spec}: not a readable JSON label mapping ({exc}).") from exc
        items = [(k, v if isinstance(v, list) else [v]) for k, v in raw.items()]
    else:
        items = []
        for part in filter(None, (p.strip() for p in spec.split(","))):
            if "=" not in part:
                raise KneeMeshError(
                    "bad_labels_spec", f"label mapping item {part!r} is not of the form tissue=value[+value...]."
                )
            k, v = part.split("=", 1)
            items.append((k.strip(), v.split("+")))
    tissues: dict[str, tuple[int, ...]] = {}
    extra: dict[int, str] = {}
    allowed_extra = {"fibula", "medial_meniscus", "lateral_meniscus", "other"}
    for name, vals in items:
        try:
            ints = tuple(int(x) for x in vals)
        except (TypeError, ValueError) as exc:
            raise KneeMeshError("bad_labels_spec", f"label values for {name!r} must be integers, got {vals!r}.") from exc
        if name in TISSUES or name == MERGED_TIBIAL:
            tissues[name] = ints
        elif name in allowed_extra:
            extra.update({v: name for v in ints})
        else:
            raise KneeMeshError(
                "bad_labels_spec",
                f"unknown tissue {name!r} in the label mapping; expected one of "
                f"{', '.join(TISSUES + (MERGED_TIBIAL,) + tuple(sorted(allowed_extra)))}.",
            )
    if not tissues:
        raise KneeMeshError("bad_labels_spec", "the label mapping names no tissue.")
    conv = LabelConvention("custom", tissues, extra)
    _check_disjoint(conv)
    return conv


def _check_disjoint(conv: LabelConvention) -> None:
    seen: dict[int, str] = {}
    for name, vals in list(conv.tissues.items()) + [(n, (v,)) for v, n in conv.extra.items()]:
        for v in vals:
            if v in seen and seen[v] != name:
                raise KneeMeshError("bad_labels_spec", f"label {v} is given to both {seen[v]} and {name}.")
            seen[v] = name


def resolve_convention(preset: str | None, labels: str | None) -> LabelConvention | None:
    """The convention the user asked for, or ``None`` to auto-detect."""
    if labels:
        return parse_custom(labels)
    if preset:
        if preset not in PRESETS:
            raise KneeMeshError(
                "unknown_preset", f"unknown preset {preset!r}; expected one of {', '.join(PRESETS)}."
            )
        return PRESETS[preset]
    return None


def label_volumes_ml(counts: dict[int, int], voxel_ml: float) -> dict[int, float]:
    return {v: c * voxel_ml for v, c in counts.items()}


def _plausible(conv: LabelConvention, volumes: dict[int, float]) -> bool:
    present = {v for v, ml in volumes.items() if v != 0}
    if not present <= conv.known_values:
        return False
    # every present tissue label must have a plausible volume for its tissue
    for tissue, vals in conv.tissues.items():
        if vals[0] in present:  # the main value, not lesion labels
            lo, hi = _VOLUME_ML[tissue]
            if not lo <= volumes[vals[0]] <= hi:
                return False
    # the main tissues must be there (at least two cartilages or two bones)
    main = [t for t, vals in conv.tissues.items() if vals[0] in present]
    return len(main) >= 2


def detect_convention(counts: dict[int, int], voxel_ml: float) -> LabelConvention:
    """Recognise the label convention from the label values and their volumes.

    Raises ``KneeMeshError("ambiguous_preset")`` when no preset or more than one fits.
    """
    volumes = label_volumes_ml(counts, voxel_ml)
    fits = [c for c in PRESETS.values() if _plausible(c, volumes)]
    if len(fits) == 1:
        return fits[0]
    found = ", ".join(f"{v}: {ml:.1f} ml" for v, ml in sorted(volumes.items()) if v)
    if not fits:
        raise KneeMeshError(
            "unknown_labels",
            f"the labels ({found}) match no known convention; pass --preset "
            f"({', '.join(PRESETS)}) or --labels femur=..,tibia=..,...",
        )
    raise KneeMeshError(
        "ambiguous_preset",
        f"the labels ({found}) fit several conventions ({', '.join(c.name for c in fits)}); "
        "pass --preset to say which.",
    )


def check_convention(conv: LabelConvention, counts: dict[int, int], source: str) -> None:
    """Reject label values the convention does not know."""
    unknown = sorted(v for v in counts if v != 0 and v not in conv.known_values)
    if unknown:
        raise KneeMeshError(
            "unknown_labels",
            f"{Path(source).name}: label values {unknown} are not part of the {conv.name!r} convention "
            f"(known: {sorted(conv.known_values)}); pass the right --preset or a --labels mapping.",
        )


def label_counts(arr: np.ndarray) -> dict[int, int]:
    """Voxel count of every label value present (0 included), from a uint8 array."""
    # counted over the labelled voxels only: a bincount casts every voxel to int64 first
    # (7x slower on an OAI map, where 97 % of the voxels are background)
    flat = arr.ravel()
    values = flat[np.flatnonzero(flat)]
    bc = np.bincount(values, minlength=1)
    bc[0] = flat.size - values.size
    return {int(v): int(c) for v, c in enumerate(bc) if c}
