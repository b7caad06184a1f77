"""One verdict per tissue and per knee that a cohort can filter on: ``ok``, ``review`` or ``failed``.

``ok`` means every target was met for the file that ships; ``review`` means the file exists but
misses a fidelity or plausibility target; ``failed`` means there is no usable file.  Every
``review`` and ``failed`` lists its reasons.  The targets are those of
:mod:`kneemesh_core.hexmesh.targets` (cartilage) and :mod:`kneemesh_core.surfaces.targets` (bone).
"""

from __future__ import annotations

from kneemesh_core.hexmesh.fidelity import FIGURES, beyond_rim_checks, fidelity_checks
from kneemesh_core.hexmesh.targets import (ELEMENT_SIZE_TOL, FUSED_TOL_MM, MAX_DEVIATION_MEDIAN_MM, MAX_DEVIATION_P95_MM,
                                           MAX_EDGE_RATIO, MAX_FRAC_EDGE_RATIO, MIN_COVERAGE, MIN_SCALED_JACOBIAN,
                                           USABLE_FRAC_BELOW, USABLE_FRAC_EDGE_RATIO, USABLE_MIN_SCALED_JACOBIAN, VOLUME_TOL)
from kneemesh_core.surfaces.targets import MAX_MEAN_DISTANCE_MM, MAX_P95_DISTANCE_MM

OK, REVIEW, FAILED = "ok", "review", "failed"
_RANK = {OK: 0, REVIEW: 1, FAILED: 2}


def worst(statuses) -> str:
    return max(statuses, key=_RANK.get, default=OK)


def bone_reasons(e: dict) -> list[str]:
    out = []
    if not (e.get("watertight") and e.get("manifold")):
        out.append("the bone shell is not closed and manifold")
    if e.get("self_intersections"):
        out.append(f"the bone shell crosses itself ({e['self_intersections']} edges)")
    d = e.get("surface_distance_mm", {})
    missed = [f"{d.get('mean')} mm (mean; target {MAX_MEAN_DISTANCE_MM} mm)"] if d.get("mean", 0) > MAX_MEAN_DISTANCE_MM else []
    if d.get("p95", 0) > MAX_P95_DISTANCE_MM:
        missed.append(f"{d.get('p95')} mm (p95; target {MAX_P95_DISTANCE_MM} mm)")
    if missed:
        out.append(f"the bone shell lies {' and '.join(missed)} from its label")
    return out


def cartilage_reasons(e: dict) -> list[str]:
    """What the shipped cartilage mesh misses: fidelity to its label, the blend and fusion checks, and
    (after the conform step) cartilage left inside its bone."""
    out = []
    gate = e.get("gate", {})
    if gate.get("gate_passed") is False:
        missed = []
        if gate["min_scaled_jacobian"] < MIN_SCALED_JACOBIAN:
            missed.append(f"min scaled Jacobian {gate['min_scaled_jacobian']}, {gate['frac_sj_below_0_5']:.3%} of elements "
                          f"below {MIN_SCALED_JACOBIAN} (target: none)")
        if gate["frac_edge_ratio_above_6"] > MAX_FRAC_EDGE_RATIO:
            missed.append(f"{gate['frac_edge_ratio_above_6']:.2%} of elements with an edge ratio above {MAX_EDGE_RATIO:g} "
                          f"(target {MAX_FRAC_EDGE_RATIO:.1%})")
        out.append(f"short of the quality gate before blending ({'; '.join(missed) or 'see gate'}) but usable for finite "
                   f"elements (every element at least {USABLE_MIN_SCALED_JACOBIAN}, at most {USABLE_FRAC_BELOW:.1%} below "
                   f"{MIN_SCALED_JACOBIAN}, at most {USABLE_FRAC_EDGE_RATIO:.0%} above the edge ratio)")
    if "layers_asked" in e:
        fewer = f"meshed in {e['n_layers']} element layers, not the {e['layers_asked']} asked for: "
        if e["fewer_layers_because"] == "no_usable_mesh":  # a median that fits can hide a thin part
            out.append(fewer + f"no attempt in {e['layers_asked']} layers gave a mesh usable for finite elements, "
                       f"although the cartilage's median thickness ({e['median_thickness_mm']} mm) would take them: "
                       "thinner parts kept their elements beyond the edge-ratio target or folded its rim")
        else:
            out.append(fewer + f"the cartilage (median {e['median_thickness_mm']} mm thick) is too thin for "
                       f"{e['layers_asked']} layers of {e['element_size_asked_mm']:g} mm elements within the edge-ratio target")
    h, asked = e.get("element_size_mm"), e.get("element_size_asked_mm")
    if h is not None and asked and abs(h / asked - 1.0) > ELEMENT_SIZE_TOL:
        fallback = ", ".join(e.get("fallbacks") or [])
        why = f"the fallback {fallback} met the other targets with them" if fallback else "its median in-plane edge"
        out.append(f"ships elements of {h:.2f} mm, {h / asked - 1.0:+.0%} off the {asked:g} mm asked for "
                   f"(target: within {ELEMENT_SIZE_TOL:.0%}): {why}")
    # the fidelity targets judge the mesh before its edge blend (its figures under "gate" once the
    # headline figures are the shipped file's), and the blended file beyond the rim the blend reshapes
    swept = {**e, **{k: gate[k] for k in FIGURES if k in gate}}
    checks = fidelity_checks(swept)
    blend = e.get("blend")
    # (where the blend was applied, the headline figures are the blended file's: the reason says which mesh it quotes)
    swept_mesh = "before its edge blend, the mesh" if (blend or {}).get("applied") else ""
    whose = f"{swept_mesh}'s " if swept_mesh else ""
    if not checks["coverage"]:
        out.append(f"{swept_mesh} covers {swept['coverage']:.1%} of the cartilage (target {MIN_COVERAGE:.0%})".lstrip())
    if not checks["volume"]:
        out.append(f"{whose}volume {swept['volume_error']:+.1%} off the label's (target within {VOLUME_TOL:.0%})")
    if deviation := _missed_deviation(swept["surface_deviation_mm"], checks):
        out.append(f"{whose}articular surface lies {deviation} from the cartilage's")
    conform = e.get("bone_conform")
    # a blend applied and not passed kept its quality and left a node deeper than FUSED_TOL_MM in the bone as it
    # stood then; where the conform step let that bone give way, the bone that ships is judged (below)
    if blend is not None and not blend.get("passed") and not (blend.get("applied") and conform):
        out.append(f"edge blend: {blend.get('reason', 'missed its targets')}")
    rim = (blend or {}).get("beyond_rim")
    if rim is not None and blend.get("applied") and not rim["passed"]:
        rim_checks = beyond_rim_checks(rim)
        missed = ([f"covers {rim['coverage']:.1%} of the cartilage (target {MIN_COVERAGE:.0%})"] if not rim_checks["coverage"]
                  else [])
        if deviation := _missed_deviation(rim["surface_deviation_mm"], rim_checks):
            missed.append(f"its articular surface lies {deviation} from the cartilage's")
        out.append(f"beyond the {rim['rings']} rings of its edge that the blend reshapes, the blended file " + " and ".join(missed))
    if e.get("chain_stopped_after_s") is not None:
        out.append(f"its fallbacks stopped at their time budget ({e['chain_stopped_after_s']} s): the best usable of "
                   f"{len(e.get('attempts', []))} attempts ships")
    if conform and conform.get("penetration_conformed_mm", 0) > FUSED_TOL_MM:
        out.append(f"lies {conform['penetration_conformed_mm']} mm inside its bone after the bone gave way "
                   f"(target {FUSED_TOL_MM} mm)")
    return out


def _missed_deviation(d: dict, checks: dict) -> str:
    """The articular deviation figures (mm) that miss their targets, each with its target; empty when none does."""
    missed = [f"{d['median']} mm (median; target {MAX_DEVIATION_MEDIAN_MM} mm)"] if not checks["deviation_median"] else []
    if not checks["deviation_p95"]:
        missed.append(f"{d['p95']} mm (p95; target {MAX_DEVIATION_P95_MM} mm)")
    return " and ".join(missed)


def tissue_verdict(tissue_is_bone: bool, e: dict) -> tuple[str, list[str]]:
    """(status, reasons) of one tissue's report entry."""
    if e.get("status") == FAILED:
        return FAILED, [e.get("reason", "failed")]
    reasons = bone_reasons(e) if tissue_is_bone else cartilage_reasons(e)
    return (REVIEW if reasons else OK), reasons


def knee_verdict(report: dict) -> dict:
    """The knee's verdict: the worst of its entries (each tissue of ``tissues``, and every other section
    of the report with a ``status``: the segmentation of an image, the anatomy, the decks, the simulation,
    the overlaps, any new stage's), every reason named, in the report's order."""
    parts: dict[str, dict] = {}
    for key, value in report.items():
        if key == "tissues":
            parts.update(value)
        elif isinstance(value, dict) and "status" in value:
            parts[key] = value
    reasons = []
    for name, e in parts.items():
        if e.get("status") == FAILED:
            reasons.append(f"{name}: failed: {e.get('reason')}")
        elif e.get("status") == REVIEW:
            reasons += [f"{name}: {r}" for r in e.get("reasons", [])]
    return {"status": worst(e.get("status", OK) for e in parts.values()), "reasons": reasons}
