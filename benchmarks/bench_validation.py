"""What a submission's validation costs, by part: the structure the API checks itself
(pydantic field types, then names, references and limits: service.api.submission
.check_structure) against the geometry checked in the validation pool (cutting, closure,
overlaps: schemas.convert.build_model), for scenes of n unit cubes on a slab, side by side
or overlapping (a scene refused only by the geometry check).

    python -m benchmarks.bench_validation [n ...]

Prints one row per scene: bytes of JSON, structure s, geometry s, their ratio, verdict.
The API process spends only the structure part; the ratio is what moving the geometry out
of it saves it.

One run (`python -m benchmarks.bench_validation 100 400 1600`, 2 cores shared, load ~10):

     blocks overlap      JSON  structure s  geometry s   ratio  verdict
        100   False    26,654        0.011       1.083      97  valid
        100    True    26,574        0.002       1.746     703  refused (342 problems)
        400   False   108,834        0.014       0.670      48  valid
        400    True   105,794        0.026       7.497     292  refused (1482 problems)
       1600   False   441,195        0.068       2.901      43  valid
       1600    True   435,115        0.077      29.692     388  refused (6162 problems)
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

from schemas.convert import BOX_FACES, box_vertices


def cubes(n: int, overlap: bool) -> dict[str, Any]:
    """`n` unit cubes in a square grid (pitch 1 m, or 0.5 m: overlapping) on a fixed slab."""
    side = max(1, round(n ** 0.5))
    pitch = 0.5 if overlap else 1.0
    blocks = [{"name": f"b{k}", "faces": BOX_FACES,
               "vertices": box_vertices([pitch * (k // side), pitch * (k % side), 0],
                                        [pitch * (k // side) + 1, pitch * (k % side) + 1,
                                         1]).tolist()}
              for k in range(n)]
    blocks.append({"name": "base", "fixed": True, "faces": BOX_FACES,
                   "vertices": box_vertices([-1, -1, -1], [side + 1, side + 1, 0]).tolist()})
    return {"name": f"{n} cubes", "blocks": blocks,
            "analysis": {"duration": 0.002, "time_step": 0.001}}


def measure(n: int, overlap: bool) -> dict[str, Any]:
    from schemas.convert import build_model
    from schemas.errors import SceneError
    from service.api.submission import check_structure
    from service.settings import Settings

    text = json.dumps(cubes(n, overlap))
    t0 = time.perf_counter()
    scene = check_structure(json.loads(text), Settings())
    t1 = time.perf_counter()
    try:
        build_model(scene)
        verdict = "valid"
    except SceneError as exc:
        verdict = f"refused ({len(exc.problems)} problems)"
    t2 = time.perf_counter()
    return {"n": n, "overlap": overlap, "bytes": len(text), "structure": t1 - t0,
            "geometry": t2 - t1, "verdict": verdict}


def main(argv: list[str]) -> int:
    sizes = [int(a) for a in argv] or [100, 400, 1600]
    print(f"{'blocks':>7} {'overlap':>7} {'JSON':>9} {'structure s':>12} {'geometry s':>11} "
          f"{'ratio':>7}  verdict")
    for n in sizes:
        for overlap in (False, True):
            r = measure(n, overlap)
            print(f"{r['n']:>7} {str(r['overlap']):>7} {r['bytes']:>9,} {r['structure']:>12.3f} "
                  f"{r['geometry']:>11.3f} {r['geometry'] / r['structure']:>7.0f}  "
                  f"{r['verdict']}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
