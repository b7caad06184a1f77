"""Every target a cartilage mesh is held to, in one place: the mesher, the blend, the reports and
the tests read them here.

The gate (judged on the swept mesh, before blending) follows Gibbons et al. 2022: no element
below a scaled Jacobian of 0.5, nothing collapsed or inverted. The fidelity targets say how well
the mesh stands for the cartilage label; the blend targets what the blended, fused mesh must keep.
"""

from __future__ import annotations

# -- the quality gate ---------------------------------------------------------------------------
#: Every element's scaled Jacobian (Verdict) at least this.
MIN_SCALED_JACOBIAN = 0.5
#: An element's longest over shortest edge ...
MAX_EDGE_RATIO = 6.0
#: ... may exceed MAX_EDGE_RATIO for at most this fraction of the elements.
MAX_FRAC_EDGE_RATIO = 0.001
#: What the rim columns and the column optimiser aim for: a little under MAX_EDGE_RATIO, so that
#: the articular faces' own edge ratios (checked last) stay within the gate.
EDGE_RATIO_AIM = 5.8
#: A mesh that misses the gate is still *usable* for finite elements (shipped as ``review``, never
#: thrown away) when nothing is collapsed, inverted or crossing itself, every element is at least
#: this ...
USABLE_MIN_SCALED_JACOBIAN = 0.2
#: ... at most this fraction of elements is below MIN_SCALED_JACOBIAN ...
USABLE_FRAC_BELOW = 0.002
#: ... and at most this fraction has an edge ratio above MAX_EDGE_RATIO.  (The paper's released
#: meshes: median min SJ 0.06-0.17, 4-5 % of elements below 0.5, 99th percentile of the edge ratio
#: 4.3-7.5, every one analysable; a whole tissue is not discarded for a handful of elements.)
USABLE_FRAC_EDGE_RATIO = 0.01

# -- fidelity to the label ----------------------------------------------------------------------
#: A reconstructed-surface patch counts as covered within this distance of the mesh, mm.
COVERAGE_TOL_MM = 0.5
#: At least this fraction of the reconstructed surface's area covered.
MIN_COVERAGE = 0.97
#: Mesh volume within this fraction of the label's.
VOLUME_TOL = 0.05
#: Articular nodes' distance to the reconstructed surface, mm: median and 95th percentile.
MAX_DEVIATION_MEDIAN_MM = 0.15
MAX_DEVIATION_P95_MM = 0.5
#: The in-plane element size that ships within this fraction of the size asked for (a fallback with
#: smaller elements meets the other targets at the cost of the size a mesh-convergence study asked for).
ELEMENT_SIZE_TOL = 0.10
#: An attempt further off the label's volume than this is no mesh of the cartilage at all.
MAX_ATTEMPT_VOLUME_ERROR = 0.5
#: Every column keeps a floor of layers x element / EDGE_RATIO_AIM (no element beyond the edge ratio), so
#: cartilage thinner than that is meshed too thick.  Where the floor would add more than this fraction to the
#: cartilage's volume (:func:`.mesher.floor_excess`), the fallbacks with smaller elements, whose floor is lower, go
#: first.  Tuned on phantom seeds 31600-31799: of their 21 cartilages above it, none met every target with
#: full-size elements and 14 met them with smaller elements after 8-12 attempts (22-40 s for a femoral
#: cartilage); 752 of the 779 under it met them with full-size elements.
MAX_FLOOR_EXCESS = 0.03

# -- after blending and fusion ------------------------------------------------------------------
#: Worst element after blending (the outermost ring may drop this low; from ring 2 inwards every
#: element keeps MIN_SCALED_JACOBIAN), ...
BLEND_MIN_SCALED_JACOBIAN = 0.2
#: ... with at least this fraction of elements at MIN_SCALED_JACOBIAN or better (the paper's
#: blended meshes reach about 95 %).
BLEND_FRAC_GOOD = 0.99
#: A bone-side node this close to the bone counts as fused, and no node may lie deeper than this
#: inside its bone, mm.
FUSED_TOL_MM = 0.05
