"""Contact set helpers: joint material assignment, subsets, concatenation."""

from __future__ import annotations

import numpy as np

from engine.contact.constraints import ContactSet, assign_joint_materials


def make_set(block_i, block_j, face_tag) -> ContactSet:
    c = len(block_i)
    return ContactSet(
        block_i=np.asarray(block_i), block_j=np.asarray(block_j),
        kind=np.zeros(c, np.int8), point_i=np.zeros((c, 3)), point_j=np.zeros((c, 3)),
        normal=np.tile([0.0, 0.0, 1.0], (c, 1)), tangent=np.tile([1.0, 0.0, 0.0], (c, 1)),
        mode=np.zeros(c, np.int8), gap=np.arange(c, dtype=float),
        key=np.zeros((c, 4), np.int64), face_tag=np.asarray(face_tag),
        joint_material=np.zeros(c, np.int64),
        cand_indptr=np.r_[0, np.cumsum(np.arange(c) % 2)].astype(np.int64),
        cand_normals=np.tile([1.0, 0.0, 0.0], (int(np.sum(np.arange(c) % 2)), 1)),
    )


def test_pair_wins_over_tag_over_default():
    c = make_set([1, 2, 3, 3, 5], [0, 1, 0, 2, 4], [-1, 7, 7, 8, 7])
    assign_joint_materials(c, default=9, of_tag={7: 1, 8: 2}, of_pair={(3, 0): 5, (4, 5): 6})
    assert c.joint_material.tolist() == [9, 1, 5, 2, 6]
    assert c.joint_material.dtype == np.int64


def test_assign_on_empty_set():
    c = ContactSet()
    assign_joint_materials(c, 3, {1: 2}, {(0, 1): 4})
    assert c.joint_material.shape == (0,)


def test_subset_and_concatenate_keep_candidates():
    c = make_set([1, 2, 3, 4], [0, 0, 0, 0], [0, 0, 0, 0])
    sub = c.subset(np.array([3, 1]))
    assert sub.gap.tolist() == [3.0, 1.0]
    assert sub.cand_indptr.tolist() == [0, 1, 2]
    both = ContactSet.concatenate([sub, c])
    assert len(both) == 6 and both.cand_indptr[-1] == len(both.cand_normals) == 4
