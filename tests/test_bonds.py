"""A joint's cohesion and tensile strength over a face-to-face contact act as one bond (a
contact patch, engine.contact.patches): it slips as a whole, when the patch's shear force
exceeds Σ tan φ N + c A, and it breaks in part, progressively, only where tension over the
patch is uneven, which the run's summary says."""

from __future__ import annotations

import numpy as np
import pytest

from engine.contact.constraints import ContactSet
from engine.contact.patches import ContactPatches, bond_breaks, contact_patches
from engine.geometry.shapes import box
from engine.model import AnalysisControls, Block, JointMaterial, Model, PointLoad
from engine.step.simulation import STATUS_COMPLETED, run
from tests.test_simulation import DOWN_DIP, G, incline_model


def _hanging(tension: float, cohesion: float, load: float, at_x: float,
             dynamic_ratio: float = 0.0) -> Model:
    """A 1 m cube glued under a fixed roof (its top face, 4 corner contacts of 0.25 m²
    each), pulled down by `load` N at (at_x, 0.5, 0) on its bottom face."""
    return Model(
        blocks=[Block(box([-1, -1, 1], [2, 2, 2]), "roof", fixed=True),
                Block(box([0, 0, 0], [1, 1, 1]), "cube")],
        joint_materials=[JointMaterial(np.radians(30), cohesion=cohesion,
                                       tensile_strength=tension)],
        point_loads=[PointLoad(1, np.array([at_x, 0.5, 0.0]), np.array([0, 0, -load]))],
        controls=AnalysisControls(duration=0.2, time_step=1e-3, penalty=1e10,
                                  dynamic_ratio=dynamic_ratio))


def test_a_face_on_a_face_is_one_patch_with_its_area() -> None:
    """The cube's top face against the roof: four corner contacts, one patch of 1 m², a
    quarter each."""
    from engine.contact.detection import detect_contacts

    m = _hanging(1e5, 1e5, 0.0, 0.5)
    cs = detect_contacts([b.polyhedron for b in m.blocks], 1e-3)
    p = contact_patches(cs)
    assert len(cs) == 4 and len(p) == 1
    assert p.area[0] == pytest.approx(1.0, rel=1e-12)
    assert np.all(p.patch == 0) and np.allclose(p.share, 0.25)
    assert len(contact_patches(ContactSet())) == 0


def test_bond_breaks_counts_whole_and_partial_losses() -> None:
    p = ContactPatches(np.array([0, 0, 1, 1, -1]), np.array([1.0, 1.0]), np.full(5, 0.5))
    start = np.zeros(5, dtype=bool)
    assert bond_breaks(p, start, np.array([1, 1, 1, 0, 1], dtype=bool)) == (1, 1)
    assert bond_breaks(p, start, start) == (0, 0)


def test_a_bond_that_holds_as_a_whole_holds_every_corner() -> None:
    """c = 6 000 Pa on the incline of test_simulation (φ 20° on 30°, 1 m² base): W sin α =
    12 753 N ≤ W cos α tan φ + c A = 8 040 + 6 000 N, so the bond holds, though each
    up-slope corner carries more shear (12 753 / 4 N) than its own friction and share of
    cohesion (~1 500 + 1 000 N). Nothing slips, nothing breaks."""
    model = incline_model(20.0, duration=0.3, dynamic_ratio=0.0)
    model.joint_materials = [JointMaterial(np.radians(20.0), cohesion=6000.0)]
    res = run(model)
    assert res.status == STATUS_COMPLETED
    assert abs(np.array(res.summary["blocks"][1]["displacement"]) @ DOWN_DIP) < 1e-5
    assert res.summary["bonds_broken"] == {"whole": 0, "progressively": 0}
    assert res.state.energies["friction_dissipation"] == 0.0


def test_a_bond_too_weak_breaks_whole_and_the_block_slides_on_friction() -> None:
    """c = 4 000 Pa < 4 713 Pa: the patch's bond breaks at once, as a whole (no partial
    loss), and the block slides on residual friction, ½ a t² with a = g (sin α − cos α
    tan φ) = 1.812815 m/s²."""
    model = incline_model(20.0, duration=0.4)
    model.joint_materials = [JointMaterial(np.radians(20.0), cohesion=4000.0)]
    res = run(model)
    assert res.summary["bonds_broken"] == {"whole": 1, "progressively": 0}
    s = np.array(res.summary["blocks"][1]["displacement"]) @ DOWN_DIP
    assert s == pytest.approx(0.5 * 1.812815 * 0.4**2, rel=0.02)


def test_a_uniform_pull_beyond_the_tensile_strength_breaks_the_whole_bond() -> None:
    """σt A = 20 kN < W = 25.5 kN hanging from the roof: the four corners let go together
    and the cube falls freely."""
    res = run(_hanging(20000.0, 0.0, 0.0, 0.5, dynamic_ratio=1.0))
    assert res.summary["bonds_broken"] == {"whole": 1, "progressively": 0}
    assert res.summary["blocks"][1]["displacement"][2] == pytest.approx(-0.5 * G * 0.2**2,
                                                                       rel=0.02)
    assert not res.summary["warnings"]


def test_bending_breaks_a_bond_in_part_and_the_summary_says_so() -> None:
    """σt = c = 100 kPa (25 kN per corner); W = 25 506 N plus P = 40 kN at the edge x = 1
    of the bottom face: as a whole 65.5 kN of tension against 100 kN, but the moment
    P × 0.5 m about the centre puts (W + P) / 4 + P × 0.5 / 2 = 26.4 kN on each corner at
    x = 1: they break, the corners at x = 0 hold the block (a progressive break, said in
    the summary). With the load at the centre, 16.4 kN each: nothing breaks."""
    bent = run(_hanging(1e5, 1e5, 40000.0, 1.0))
    assert bent.status == STATUS_COMPLETED
    assert bent.summary["bonds_broken"] == {"whole": 0, "progressively": 1}
    assert any("progressively" in w for w in bent.summary["warnings"])
    assert abs(bent.summary["blocks"][1]["displacement"][2]) < 0.01  # still hangs
    centred = run(_hanging(1e5, 1e5, 40000.0, 0.5))
    assert centred.summary["bonds_broken"] == {"whole": 0, "progressively": 0}
