"""Block cutting: split a domain polyhedron into rock blocks along joint planes.

The pipeline, one module a stage:

- `planes`: every plane involved (joint planes, the side planes of bounded joints' extent
  prisms, and for a concave domain its own face planes) registered once, parallel planes
  sharing one normal;
- `cells`: the domain (or its bounding box, if concave) cut by the full arrangement of
  those planes into convex cells, so neighbouring cells share identical facets;
- `facets`: cell vertices merged, facets of neighbour cells matched, and each matched
  facet found real (on a joint's extent) or fictitious;
- `slivers`: cells glued back together across fictitious facets, every group one block;
  blocks too small or too thin merged into a neighbour;
- `blocks`: each group's surface faces and, for a concave block, its convex pieces;
- `cut`: `cut_blocks` running the stages, and `convex_decomposition` (the same stages
  on one block's own face planes).

The joint planes themselves, and their makers (`joint_set_planes`, `disc_polygon`), are in
:mod:`engine.geometry.joints`. These modules import only their :mod:`engine.geometry`
siblings and :mod:`engine.tolerances` (besides numpy and scipy): nothing above geometry,
in particular not :mod:`engine.model`.
"""

from engine.geometry.cutting.cut import CutResult, convex_decomposition, cut_blocks

__all__ = ["CutResult", "convex_decomposition", "cut_blocks"]
